"""Kill-and-resume soak: a tiny training run is killed (SIGKILL) at random moments, resumed
with `cogs train --resume` each time, and its end compared with an uninterrupted run's.

    python benchmarks/soak_resume.py [--kills 20] [--seed 0] [--work DIR]

Trains the tests' tiny configuration (every stage and the pose refit, checkpoints every
3 steps) on a small synthetic scene. A kill lands anywhere: while the process starts,
mid-step, mid-checkpoint write, between stages. After the last kill the run is resumed
to its end; every tensor of its last checkpoint must equal the uninterrupted run's, bit
for bit. Prints one JSON object on its last line.
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


def _where(run: Path) -> str:
    try:
        w = json.loads((run / "checkpoints" / "last.json").read_text())
        return f"{w['stage']}:{w['step']}"
    except (OSError, ValueError, KeyError):
        return "none"


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
    if not (ref / "train_summary.json").exists():
        p = _train(scene, ref, resume=False)
        assert p.wait() == 0, p.stderr.read()
    uninterrupted = time.perf_counter() - t0

    run = work / "killed"
    kills, started = [], time.perf_counter()
    for k in range(args.kills):
        p = _train(scene, run, resume=(run / "checkpoints" / "last.pt").exists())
        time.sleep(rng.uniform(0.5, 0.8 * uninterrupted))
        if p.poll() is not None:  # finished before the kill: start over from nothing is not a kill
            err = p.stderr.read()
            assert p.returncode == 0, err
            kills.append({"kill": k, "at": "finished before the kill"})
            break
        p.send_signal(signal.SIGKILL)
        p.wait()
        kills.append({"kill": k, "at": _where(run)})
    p = _train(scene, run, resume=(run / "checkpoints" / "last.pt").exists())
    assert p.wait() == 0, p.stderr.read()

    a = torch.load(ref / "checkpoints" / "last.pt", map_location="cpu", weights_only=True)["branches"]
    b = torch.load(run / "checkpoints" / "last.pt", map_location="cpu", weights_only=True)["branches"]
    differing = [f"{br}.{k}" for br in a if a[br] is not None for k in a[br]
                 if b.get(br) is None or k not in b[br] or not torch.equal(a[br][k], b[br][k])]
    print(json.dumps({"kills": len([x for x in kills if x["at"] != "finished before the kill"]),
                      "killed_at_checkpoint_position": [x["at"] for x in kills], "identical": not differing,
                      "differing": differing[:10], "uninterrupted_seconds": round(uninterrupted, 1),
                      "soak_seconds": round(time.perf_counter() - started, 1)}))


if __name__ == "__main__":
    main()
