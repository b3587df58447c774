"""Benchmark `cogs synth`: how long the synthetic benchmark scene takes to make.

    .venv/bin/python benchmarks/synth.py [--frames 100] [--anny-cold]

Runs in a fresh process: imports, body model (from Anny's asset cache), numba kernels
(from numba's cache), generation (with per-stage times), writing, validation+loading and
the preview. `--anny-cold` also times Anny's one-time asset-cache build in a subprocess
with an empty cache folder (about a minute); otherwise the cache-less build time is not
measured and the cached build's `build_seconds` is reported. Prints one JSON object on
its last line.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def _anny_cold_seconds() -> float:
    code = "import time, anny; t = time.perf_counter(); anny.Anny(); print(time.perf_counter() - t)"
    with tempfile.TemporaryDirectory() as d:
        env = dict(os.environ, ANNY_CACHE_DIR=d)
        out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    return float(out.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--width", type=int, default=256)
    ap.add_argument("--height", type=int, default=192)
    ap.add_argument("--anny-cold", action="store_true", help="also time Anny's cache-less build (~1 min)")
    args = ap.parse_args()
    res: dict = {"benchmark": "synth", "frames": args.frames, "width": args.width, "height": args.height}
    t0 = time.perf_counter()
    import torch

    from cogs.data.scene import load_scene, save_scene
    from cogs.data.synth import SynthConfig, generate_scene
    from cogs.data.synth.preview import write_preview
    from cogs.data.synth.render import warmup

    res["import_seconds"] = time.perf_counter() - t0
    res["torch_threads"] = torch.get_num_threads()
    res["cpu_count"] = os.cpu_count()
    t0 = time.perf_counter()
    from cogs.body import load_body_model

    model = load_body_model("anny")
    res["body_model_load_seconds"] = time.perf_counter() - t0
    res["body_model_build_seconds_cached"] = model.build_seconds
    res["anny_cold_build_seconds"] = _anny_cold_seconds() if args.anny_cold else None
    if not args.anny_cold:
        res["notes"] = ["anny_cold_build_seconds not measured (pass --anny-cold); FACTS.md: ~48 s"]
    t0 = time.perf_counter()
    warmup()
    res["numba_kernels_seconds"] = time.perf_counter() - t0
    cfg = SynthConfig(frames=args.frames, width=args.width, height=args.height)
    t0 = time.perf_counter()
    scene = generate_scene(cfg, show_progress=False)
    res["generate_seconds"] = time.perf_counter() - t0
    res["stage_seconds"] = scene.source["timings"]
    with tempfile.TemporaryDirectory() as d:
        root = Path(d) / "synth"
        t0 = time.perf_counter()
        save_scene(scene, root)
        res["write_seconds"] = time.perf_counter() - t0
        res["written_mb"] = sum(p.stat().st_size for p in root.rglob("*") if p.is_file()) / 1e6
        t0 = time.perf_counter()
        load_scene(root)
        res["validate_and_load_seconds"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        write_preview(scene, root / "preview.png")
        res["preview_seconds"] = time.perf_counter() - t0
    res["generate_and_write_seconds"] = res["generate_seconds"] + res["write_seconds"]
    res["counts"] = scene.source["counts"]
    res["body_visibility"] = scene.source["body_visibility"]
    res["n_body_triangles"] = int(model.canonical().faces.shape[0])
    print(json.dumps(res))


if __name__ == "__main__":
    main()
