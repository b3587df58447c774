"""Wall time of `cogs batch` against running the same sequences one after another.

Usage:  python benchmarks/batch_vs_sequential.py --work DIR [--seeds 0 1 2] [--frames 100]
            [--cpus-per-job 1] [--cpus N] [--only batch|sequential] [--smoke]

Both arms do the same work per sequence: the demo-sized synthetic scene of that seed
(`cogs synth --seed S --frames F`, 256x192), training with the quick preset, evaluation
with `cogs eval`'s defaults (40-step test-time pose fit, renders saved).

* batch: one manifest (WORK/manifest.yaml) run by `cogs batch --out WORK/batch` on local
  Ray, `--cpus-per-job` cores per job (default 1: on a 2-core machine two entries train
  at once);
* sequential: for each seed `cogs synth`, `cogs train`, `cogs eval` into WORK/sequential/,
  one after another, each process using every core (what a user does by hand).

Each arm runs in fresh folders (they are removed first). Both arms train on identical
scenes; their metrics differ in the last digits only where their thread counts differ (a
job with one thread sums floats in another order than a process with two). `--smoke` shrinks everything
(16 frames at 96x72, the tests' TINY training) to check the script in a few minutes.
The load average before and after each arm is reported: other work on the machine slows
both. Progress goes to stderr; the last stdout line is one JSON object.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parent.parent
SMOKE_SYNTH = {"frames": 16, "width": 96, "height": 72}


def tiny_overrides() -> list[str]:
    sys.path.insert(0, str(ROOT))
    from tests.fixtures import TINY

    return list(TINY)


def cogs(*args: str) -> None:
    cmd = [sys.executable, "-m", "cogs.cli", *args]
    print("$ cogs " + " ".join(args), file=sys.stderr, flush=True)
    subprocess.run(cmd, check=True, stdout=sys.stderr)


def run_batch(work: Path, seeds: list[int], synth: dict, overrides: list[str], cpus_per_job: int,
              cpus: int | None) -> dict:
    out = work / "batch"
    shutil.rmtree(out, ignore_errors=True)
    manifest = work / "manifest.yaml"
    doc = {"defaults": {"synth": synth, "train": {"preset": "quick", **({"set": overrides} if overrides else {})}},
           "sequences": [{"synth": {"seed": s}} for s in seeds]}
    manifest.write_text(yaml.safe_dump(doc, sort_keys=False))
    t0, load0 = time.perf_counter(), os.getloadavg()[0]
    args = ["batch", str(manifest), "--out", str(out), "--cpus-per-job", str(cpus_per_job)]
    if cpus:
        args += ["--cpus", str(cpus)]
    cmd = [sys.executable, "-m", "cogs.cli", *args]
    print("$ cogs " + " ".join(args), file=sys.stderr, flush=True)
    rc = subprocess.run(cmd, stdout=sys.stderr).returncode
    wall = time.perf_counter() - t0
    steps, metrics = {}, {}
    for s in seeds:
        rec = json.loads((out / f"synth_seed{s}" / "batch.json").read_text())
        steps[f"seed{s}"] = {k: v.get("seconds") for k, v in rec["steps"].items()}
        metrics[f"seed{s}"] = _metrics(out / f"synth_seed{s}" / "run")
    return {"wall_s": wall, "exit_code": rc, "load_before": load0, "load_after": os.getloadavg()[0],
            "step_seconds": steps, "metrics": metrics, "results_md": (out / "results.md").read_text()}


def _metrics(run: Path) -> dict | None:
    path = run / "eval" / "metrics.json"
    if not path.is_file():
        return None
    m = json.loads(path.read_text())
    return {"full_psnr": m["full"]["psnr"], "human_psnr": m["human_crop"]["psnr"], "train_seconds": m["train_seconds"]}


def run_sequential(work: Path, seeds: list[int], synth: dict, overrides: list[str]) -> dict:
    out = work / "sequential"
    shutil.rmtree(out, ignore_errors=True)
    t0, load0 = time.perf_counter(), os.getloadavg()[0]
    steps, metrics = {}, {}
    for s in seeds:
        scene, run = out / f"seed{s}" / "scene", out / f"seed{s}" / "run"
        sizes = [f"--{k}={v}" for k, v in synth.items()]
        times = {}
        t = time.perf_counter()
        cogs("synth", "--out", str(scene), "--seed", str(s), *sizes)
        times["prepare"] = time.perf_counter() - t
        t = time.perf_counter()
        cogs("train", "--scene", str(scene), "--out", str(run), "--preset", "quick", *(["--set", *overrides] if overrides else []))
        times["train"] = time.perf_counter() - t
        t = time.perf_counter()
        cogs("eval", "--run", str(run))
        times["eval"] = time.perf_counter() - t
        steps[f"seed{s}"] = times
        metrics[f"seed{s}"] = _metrics(run)
    return {"wall_s": time.perf_counter() - t0, "load_before": load0, "load_after": os.getloadavg()[0],
            "step_seconds": steps, "metrics": metrics}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--work", type=Path, required=True)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--cpus-per-job", type=int, default=1)
    ap.add_argument("--cpus", type=int, default=None)
    ap.add_argument("--only", choices=["batch", "sequential"], default=None)
    ap.add_argument("--smoke", action="store_true")
    a = ap.parse_args()
    a.work.mkdir(parents=True, exist_ok=True)
    synth = dict(SMOKE_SYNTH) if a.smoke else {"frames": a.frames}
    overrides = tiny_overrides() if a.smoke else []
    report = {"seeds": a.seeds, "synth": synth, "preset": "quick", "smoke": a.smoke, "cpu_count": os.cpu_count(),
              "cpus_per_job": a.cpus_per_job}
    if a.only in (None, "batch"):
        report["batch"] = run_batch(a.work, a.seeds, synth, overrides, a.cpus_per_job, a.cpus)
        print(report["batch"]["results_md"], file=sys.stderr)
    if a.only in (None, "sequential"):
        report["sequential"] = run_sequential(a.work, a.seeds, synth, overrides)
    if "batch" in report and "sequential" in report:
        report["speedup"] = report["sequential"]["wall_s"] / report["batch"]["wall_s"]
    print(json.dumps(report))


if __name__ == "__main__":
    main()
