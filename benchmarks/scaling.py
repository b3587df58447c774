"""How a training step's time and the run's peak memory grow with resolution and clip length.

    python benchmarks/scaling.py [--work DIR] [--quick] [--paper]

A small synthetic scene (24 frames) is upsampled and tiled into scenes of each size
(the motion repeats every 24 frames; what is measured is cost, not quality): 100 frames at
256x192, 512x384, 1024x768 and 1920x1080, and 100, 300 and 600 frames at 512x384. Each
trains in its own process a short schedule that reaches stage VI with density control
off, so every size carries the same Gaussians; the step time is stage VI's seconds per
step without its one visibility refresh (which renders the training frames, at most
`visibility_max_frames` of them, and is reported apart), the peak is the process's
maximum resident set. Beside each, the estimate
`cogs.train.memory` refuses runs by. The cost should grow with the pixels a step renders,
not with the frames the run holds. Prints one JSON object on its last line.

`--paper` instead projects the paper preset's wall time on 300 frames at 960x540 (issue
25's target): a short run of the paper configuration (a few steps per stage, the density
control on but with no time to grow the Gaussians) measures each stage's seconds per step,
and the projection multiplies them by the paper schedule's step counts. It is a lower
bound: the full run's Gaussians grow to the density caps, and the pose refit (one fit per
training frame) and the visibility passes come on top.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

SCHEDULE = ["schedule.I=5", "schedule.II=5", "schedule.III=5", "schedule.IV=5", "schedule.V=5", "schedule.VI=25",
            "refit.steps=0", "human_density.enabled=false", "object_density.enabled=false",
            "scene_density.enabled=false", "visibility_every=1000", "checkpoint_every=1000"]

CHILD = r"""
import json, resource, sys, time
import cogs
from cogs.config import apply_overrides, preset
from cogs.data.scene import load_scene
from cogs.train.trainer import Trainer
scene, out, name, sets = sys.argv[1], sys.argv[2], sys.argv[3], sys.argv[4:]
cfg = apply_overrides(preset(name), sets)
s = load_scene(scene, ground_truth=False)
refresh = {}
plain = Trainer._refresh
def timed(self, spec, it, weights):  # the visibility refresh renders every (or at most 120) training frames
    t = time.perf_counter(); plain(self, spec, it, weights)
    refresh[spec.name] = refresh.get(spec.name, 0.0) + time.perf_counter() - t
Trainer._refresh = timed
t0 = time.perf_counter()
summary = Trainer(s, cfg, out, show_progress=False).run()
vi = (summary["stage_seconds"]["VI"] - refresh.get("VI", 0.0)) / cfg.schedule.VI
steps = {k: (summary["stage_seconds"][k] - refresh.get(k, 0.0)) / getattr(cfg.schedule, k) for k in "I II III IV V VI".split()}
print(json.dumps({"step_vi_s": vi, "visibility_pass_s": refresh.get("VI", 0.0), "step_s": steps,
                  "peak_rss_gib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2,
                  "n_gaussians": summary["n_gaussians"], "seconds": time.perf_counter() - t0}))
"""


def _tiled_scene(base, frames: int, width: int, height: int, root: Path) -> Path:
    import numpy as np

    from cogs.data.scene import (BodyTrack, CameraTrack, ObjectTrack, Scene, default_frame_ids, resize_image,
                                 resize_mask, save_scene, scale_intrinsics)

    if (root / "scene.json").exists():
        return root
    idx = np.arange(frames) % base.n_frames
    sx, sy = width / base.width, height / base.height
    images = np.stack([resize_image(base.images[i], width, height) if (sx, sy) != (1, 1) else base.images[i] for i in idx])
    hm = np.stack([resize_mask(base.human_masks[i], width, height) for i in idx])
    om = np.stack([resize_mask(base.object_masks[i], width, height) for i in idx])
    split_test = list(range(0, frames, max(frames // 16, 2)))[:16]
    scene = Scene(
        root=None, name=f"tiled_{frames}x{width}x{height}", width=width, height=height, fps=base.fps,
        frame_ids=default_frame_ids(frames),
        split={"train": [t for t in range(frames) if t not in split_test], "test": split_test},
        cameras=CameraTrack(K=scale_intrinsics(base.cameras.K[idx], sx, sy), world_to_camera=base.cameras.world_to_camera[idx]),
        body=BodyTrack(base.body.model, base.body.shape, base.body.pose[idx], base.body.transl[idx]),
        object=ObjectTrack(base.object.centre, base.object.quats[idx], base.object.translations[idx]),
        points_xyz=base.points_xyz, points_rgb=base.points_rgb, planes=base.planes, source={"generator": "benchmarks/scaling.py"},
    )
    scene.set_pixels(images, hm, om)
    return save_scene(scene, root)


def _child(scene: Path, out: Path, preset_name: str, sets: list[str]) -> dict:
    if out.exists():
        import shutil

        shutil.rmtree(out)
    r = subprocess.run([sys.executable, "-c", CHILD, str(scene), str(out), preset_name, *sets], capture_output=True,
                       text=True, cwd=REPO)
    assert r.returncode == 0, r.stderr[-3000:]
    return json.loads(r.stdout.strip().splitlines()[-1])


PAPER_PROBE = ["schedule.I=12", "schedule.II=6", "schedule.III=12", "schedule.IV=6", "schedule.V=12",
               "schedule.VI=24", "refit.steps=0", "visibility_every=100000", "checkpoint_every=100000"]


def project_paper(base, work: Path) -> dict:
    """The paper preset's stage step times on 300 frames at 960x540, times its step counts."""
    from cogs.config import paper_config

    frames, w, h = 300, 960, 540
    scene = _tiled_scene(base, frames, w, h, work / f"scene_{frames}_{w}x{h}")
    t0 = time.perf_counter()
    m = _child(scene, work / "run_paper_probe", "paper", PAPER_PROBE)
    schedule = paper_config().schedule
    projected = sum(m["step_s"][k] * getattr(schedule, k) for k in m["step_s"])
    return {"frames": frames, "width": w, "height": h, "probe": PAPER_PROBE,
            "step_s": {k: round(v, 3) for k, v in m["step_s"].items()},
            "paper_steps": {k: getattr(schedule, k) for k in m["step_s"]},
            "projected_steps_hours": round(projected / 3600, 2), "peak_rss_gib": round(m["peak_rss_gib"], 2),
            "n_gaussians": m["n_gaussians"], "wall_s": round(time.perf_counter() - t0, 1)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--work", type=Path, default=Path("scaling_work"))
    ap.add_argument("--quick", action="store_true", help="two small sizes only (a smoke run)")
    ap.add_argument("--paper", action="store_true", help="project the paper preset on 300 frames at 960x540 instead")
    args = ap.parse_args()
    import cogs  # noqa: F401
    from cogs.config import apply_overrides, quick_config
    from cogs.data.scene import load_scene, save_scene
    from cogs.data.synth import SynthConfig, generate_scene
    from cogs.train.memory import GiB, estimate

    base_dir = args.work / "base"
    if not (base_dir / "scene.json").exists():
        save_scene(generate_scene(SynthConfig(frames=24), show_progress=False), base_dir)
    base = load_scene(base_dir, ground_truth=False)
    if args.paper:
        print(json.dumps(project_paper(base, args.work)))
        return
    sizes = [(100, 256, 192), (100, 512, 384), (100, 1024, 768), (100, 1920, 1080), (300, 512, 384), (600, 512, 384)]
    if args.quick:
        sizes = [(30, 256, 192), (60, 256, 192)]
    cfg = apply_overrides(quick_config(), SCHEDULE)
    rows = []
    for frames, w, h in sizes:
        scene = _tiled_scene(base, frames, w, h, args.work / f"scene_{frames}_{w}x{h}")
        t0 = time.perf_counter()
        m = _child(scene, args.work / f"run_{frames}_{w}x{h}", "quick", SCHEDULE)
        est = estimate(frames, w, h, cfg)
        rows.append({"frames": frames, "width": w, "height": h, "step_vi_s": round(m["step_vi_s"], 3),
                     "visibility_pass_s": round(m["visibility_pass_s"], 2),
                     "peak_rss_gib": round(m["peak_rss_gib"], 2), "estimate_gib": round(est.total / GiB, 2),
                     "n_gaussians": m["n_gaussians"], "wall_s": round(time.perf_counter() - t0, 1)})
        print(json.dumps(rows[-1]), flush=True)
    print(json.dumps({"schedule": SCHEDULE, "rows": rows}))


if __name__ == "__main__":
    main()
