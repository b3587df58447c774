# Two entry points: `make demo` and `make test`. Both create .venv on first use and are
# idempotent. TORCH selects the torch pip requirement installed before the package; a CUDA
# user who already manages torch in an active environment runs `pip install -e ".[cuda,dev]"`
# there instead (pip keeps an installed torch that satisfies `torch>=2.4`).
PYTHON ?= python3
VENV ?= .venv
TORCH ?= torch==2.13.0
DEMO_OUT ?= demo_out
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
# Khronos' glTF validator (npm) for the export test; installed into .tools/ when npm is
# here. Without node/npm that test skips and says why.
GLTF_VALIDATOR_VERSION ?= 2.0.0-dev.3.10
VALIDATOR := .tools/node_modules/gltf-validator/package.json

.PHONY: demo test install clean

# mediapipe (preprocess extra) pulls opencv-contrib-python, a GUI build sharing the cv2
# folder with opencv-python-headless and needing libGL: remove it and restore the headless
# build, so exactly one OpenCV (headless) wins.
$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q "$(TORCH)"
	$(PY) -m pip install -q -e ".[dev,preprocess,batch,viewer]"
	$(PY) -m pip uninstall -q -y opencv-contrib-python
	$(PY) -m pip install -q --force-reinstall --no-deps "opencv-python-headless==$$($(PY) -c 'import importlib.metadata as m; print(m.version("opencv-python-headless"))')"
	touch $(STAMP)

install: $(STAMP)

$(VALIDATOR):
	@if command -v npm >/dev/null 2>&1 && command -v node >/dev/null 2>&1; then \
		npm install --prefix .tools --no-audit --no-fund --silent "gltf-validator@$(GLTF_VALIDATOR_VERSION)"; \
	else \
		echo "node/npm not found: the glTF validator test (tests/test_export.py) will be skipped"; \
	fi

demo: $(STAMP)
	$(VENV)/bin/cogs demo --out $(DEMO_OUT)

test: $(STAMP) $(VALIDATOR)
	$(VENV)/bin/cogs doctor --warm
	$(VENV)/bin/pytest -n 2 --durations=15

clean:
	rm -rf $(VENV) $(DEMO_OUT) .tools
