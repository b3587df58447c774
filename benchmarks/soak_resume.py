"""Kill-and-resume soak: a tiny training run is killed (SIGKILL) at random moments, resumed
with `cogs train --resume` each time, and its end compared with an uninterrupted run's.

    python benchmarks/soak_resume.py [--kills 20] [--seed 0] [--work DIR]

Trains the tests' tiny configuration (every stage and the pose refit, checkpoints every
3 steps) on a small synthetic scene. The kill points are spread over the whole run: each
kill waits until the run has passed a random point of its progress (sorted, so the run
moves on), then a random fraction of a step more, so kills land mid-step, mid-checkpoint
write, between stages, and a few while the process is still starting. After the last
kill the run is resumed to its end; every tensor of its last checkpoint must equal the
uninterrupted run's, bit for bit. Prints one JSON object on its last line.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import cogs  # noqa: E402,F401  (before torch)
import torch  # noqa: E402

from tests.fixtures import TINY  # noqa: E402


def _train(scene: Path, out: Path, resume: bool) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "cogs.cli", "train", "--scene", str(scene), "--out", str(out)]
    cmd += ["--resume"] if resume else ["--set", *TINY]
    return subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONPATH": str(REPO)})


def _where(run: Path) -> tuple[int, int] | None:
    try:
        w = json.loads((run / "checkpoints" / "last.json").read_text())
        return int(w["stage"]), int(w["step"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def _progress(where: tuple[int, int] | None, lengths: list[int]) -> int:
    """Steps done over the whole run at a checkpoint position (stage index, step)."""
    if where is None:
        return 0
    stage, step = where
    return sum(lengths[:stage]) + step


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--kills", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--work", type=Path, default=None)
    args = ap.parse_args()
    rng = random.Random(args.seed)
    work = args.work or Path(tempfile.mkdtemp(prefix="cogs_soak_"))
    work.mkdir(parents=True, exist_ok=True)

    from cogs.data.scene import save_scene
    from cogs.data.synth import SynthConfig, generate_scene

    scene = work / "scene"
    if not (scene / "scene.json").exists():
        save_scene(generate_scene(SynthConfig(frames=16, width=96, height=72, points=1500), show_progress=False), scene)

    t0 = time.perf_counter()
    ref = work / "reference"
    uninterrupted = None  # a reference left in --work by an earlier soak is reused
    if not (ref / "train_summary.json").exists():
        p = _train(scene, ref, resume=False)
        assert p.wait() == 0, p.stderr.read()
        uninterrupted = round(time.perf_counter() - t0, 1)

    from cogs.config import load_config
    from cogs.data.scene import load_scene
    from cogs.train.stages import build_stages

    lengths = [st.steps for st in build_stages(load_config(ref / "config.yaml"), len(load_scene(scene).split["train"]))]
    total = sum(lengths)
    targets = sorted(rng.uniform(-0.1, 1.0) * total for _ in range(args.kills))
    run = work / "killed"
    kills, started = [], time.perf_counter()
    for target in targets:
        p = _train(scene, run, resume=(run / "checkpoints" / "last.pt").exists())
        if target < 0:  # while the process starts
            time.sleep(rng.uniform(0.2, 3.0))
        else:
            while p.poll() is None and _progress(_where(run), lengths) < target:
                time.sleep(0.01)
            time.sleep(rng.uniform(0.0, 0.3))
        if p.poll() is not None:
            assert p.returncode == 0, p.stderr.read()
            kills.append("finished before the kill")
            continue
        p.send_signal(signal.SIGKILL)
        p.wait()
        kills.append(f"{_progress(_where(run), lengths)}/{total}")
    p = _train(scene, run, resume=(run / "checkpoints" / "last.pt").exists())
    assert p.wait() == 0, p.stderr.read()

    a = torch.load(ref / "checkpoints" / "last.pt", map_location="cpu", weights_only=True)["branches"]
    b = torch.load(run / "checkpoints" / "last.pt", map_location="cpu", weights_only=True)["branches"]
    differing = [f"{br}.{k}" for br in a if a[br] is not None for k in a[br]
                 if b.get(br) is None or k not in b[br] or not torch.equal(a[br][k], b[br][k])]
    print(json.dumps({"kills": sum(k != "finished before the kill" for k in kills),
                      "last_checkpoint_at_each_kill": kills, "identical": not differing,
                      "differing": differing[:10], "uninterrupted_seconds": uninterrupted,
                      "soak_seconds": round(time.perf_counter() - started, 1)}))


if __name__ == "__main__":
    main()
