"""Where a stage-VI training step's time goes, and how busy it keeps the cores.

    python benchmarks/profile_step.py --scene DIR [--preset quick|paper] [--set K=V ...]
        [--steps 30] [--warm 10] [--grow] [--work DIR] [--top 25] [--device cpu|cuda]

Trains `--scene` with the preset's configuration on a compressed schedule that reaches
stage VI quickly (a few steps per earlier stage), then times `--steps` stage-VI steps
after `--warm` unprofiled ones: wall and processor time per step (processor over wall
is how many cores the step keeps busy), split into phases (prepare, the objectives'
renders and terms, the regularisers, backward, Adam, density control), then a cProfile
of the same steps (the `--top` entries by own time). `--grow` lets density control fill
each branch up to its cap during the compressed stage V (gradient threshold 0, a round
every 5 steps), so the profiled step carries the Gaussian counts a full run ends with
rather than the initial ones. `--set` overrides any config field, as `cogs train --set`.
On `--device cuda` every phase boundary synchronises the device, so a phase's wall time
is its kernels' time too (not only the launches); the processor time then counts the
host's launching and waiting.

Prints the profile, then one JSON object on its last line.
"""

from __future__ import annotations

import argparse
import cProfile
import io
import json
import pstats
import sys
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import cogs  # noqa: E402,F401  (before torch: the OpenMP wait policy the cogs command sets)
import torch  # noqa: E402

COMPRESSED = ["schedule.I=20", "schedule.II=5", "schedule.III=20", "schedule.IV=5", "refit.steps=0",
              "visibility_every=100000", "plane_assign_every=100000", "checkpoint_every=100000"]
GROW = ["scene_density.grad_threshold=0", "scene_density.refine_every=5", "scene_density.stop_fraction=1.0",
        "object_density.grad_threshold=0", "object_density.refine_every=5", "object_density.start_fraction=0",
        "object_density.stop_fraction=1.0", "human_density.grad_threshold=0", "human_density.refine_every=5",
        "human_density.stop_fraction=1.0"]


class Phases:
    """Wall and processor seconds per named phase, while `on`."""

    def __init__(self, sync=None):
        self.on = False
        self.sync = sync or (lambda: None)
        self.wall: dict[str, float] = {}
        self.cpu: dict[str, float] = {}

    @contextmanager
    def __call__(self, name: str):
        if not self.on:
            yield
            return
        self.sync()
        t, c = time.perf_counter(), time.process_time()
        try:
            yield
        finally:
            self.sync()
            self.wall[name] = self.wall.get(name, 0.0) + time.perf_counter() - t
            self.cpu[name] = self.cpu.get(name, 0.0) + time.process_time() - c


def _instrument(phases: Phases) -> None:
    """Wrap the step's pieces so that `phases` sees them (the trainer itself is untouched)."""
    from cogs.branches.base import REGISTRY
    from cogs.train import objectives, trainer

    def wrap(owner, attr, name):
        inner = getattr(owner, attr)

        def timed(*a, **k):
            with phases(name):
                return inner(*a, **k)

        setattr(owner, attr, timed)

    for key in list(objectives.OBJECTIVES):
        inner = objectives.OBJECTIVES[key]
        objectives.OBJECTIVES[key] = (lambda f, n: (lambda s: _timed_call(phases, n, f, s)))(inner, f"objective.{key}")
    for cls in REGISTRY.values():
        wrap(cls, "prepare", "prepare")
        wrap(cls, "regularisers", "regularisers")
        wrap(cls, "guard", "guard")
    wrap(torch.Tensor, "backward", "backward")
    wrap(torch.optim.Adam, "step", "adam")
    wrap(trainer.Trainer, "_density_step", "density_refine")
    wrap(trainer.DensityStrategy, "step_post_backward", "density_stats")


def _timed_call(phases, name, f, s):
    with phases(name):
        return f(s)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", type=Path, required=True)
    ap.add_argument("--preset", default="quick")
    ap.add_argument("--set", nargs="*", default=[], dest="sets")
    ap.add_argument("--steps", type=int, default=30, help="profiled stage-VI steps")
    ap.add_argument("--warm", type=int, default=10, help="stage-VI steps before profiling")
    ap.add_argument("--v-steps", type=int, default=20, help="steps of the compressed stage V")
    ap.add_argument("--grow", action="store_true", help="fill every branch to its density cap in stage V")
    ap.add_argument("--work", type=Path, default=None)
    ap.add_argument("--top", type=int, default=25)
    ap.add_argument("--ops", action="store_true", help="also torch.profiler's table of operators (own time)")
    ap.add_argument("--device", default="cpu", help="cpu or cuda (cuda: phases synchronised)")
    args = ap.parse_args()

    from cogs.config import apply_overrides, preset
    from cogs.data.scene import load_scene
    from cogs.train.trainer import Trainer

    sets = COMPRESSED + [f"schedule.V={args.v_steps}", f"schedule.VI={args.warm + args.steps}"]
    if args.grow:
        sets += GROW
    cfg = apply_overrides(preset(args.preset), sets + args.sets)
    scene = load_scene(args.scene, ground_truth=False)
    work = args.work or Path(tempfile.mkdtemp(prefix="cogs_profile_"))
    cuda = torch.device(args.device).type == "cuda"
    phases = Phases(torch.cuda.synchronize if cuda else None)
    _instrument(phases)
    tr = Trainer(scene, cfg, work / "run", device=args.device, show_progress=False)
    plain_step = tr._step
    prof = cProfile.Profile()
    record = {"wall": 0.0, "cpu": 0.0, "n": 0}

    def step(spec, it):
        if spec.name != "VI" or it < args.warm:
            return plain_step(spec, it)
        phases.on = True
        phases.sync()
        t, c = time.perf_counter(), time.process_time()
        prof.enable()
        try:
            return plain_step(spec, it)
        finally:
            phases.sync()
            prof.disable()
            record["wall"] += time.perf_counter() - t
            record["cpu"] += time.process_time() - c
            record["n"] += 1
            phases.on = False

    def vi_step(spec, it):
        if spec.name == "VI" and it == 0 and args.grow:  # the grown counts, then the preset's own density control
            for b, s in tr.strategies.items():
                s.cfg = apply_overrides(preset(args.preset), args.sets).__getattribute__(f"{b}_density")
        if args.ops and spec.name == "VI" and it >= args.warm:
            acts = [torch.profiler.ProfilerActivity.CPU] + ([torch.profiler.ProfilerActivity.CUDA] if cuda else [])
            with torch.profiler.profile(activities=acts, record_shapes=True) as tp:
                r = step(spec, it)
            ops.append(tp.key_averages(group_by_input_shape=True))
            return r
        return step(spec, it)

    ops = []
    tr._step = vi_step
    t0 = time.perf_counter()
    summary = tr.run()
    n = max(record["n"], 1)
    s = io.StringIO()
    pstats.Stats(prof, stream=s).sort_stats("tottime").print_stats(args.top)
    print(s.getvalue())
    if ops:
        key = "self_device_time_total" if cuda else "self_cpu_time_total"
        print(ops[-1].table(sort_by=key, row_limit=args.top))
    print(f"{'phase':<22}{'ms/step':>10}{'cores':>8}")
    for k in sorted(phases.wall, key=phases.wall.get, reverse=True):
        w = phases.wall[k]
        print(f"{k:<22}{1000 * w / n:>10.1f}{phases.cpu[k] / max(w, 1e-9):>8.2f}")
    out = {
        "scene": str(args.scene), "size": [scene.width, scene.height], "preset": args.preset, "sets": args.sets,
        "grow": args.grow, "n_gaussians": summary["n_gaussians"], "profiled_steps": record["n"],
        "step_s": round(record["wall"] / n, 4), "step_cores": round(record["cpu"] / max(record["wall"], 1e-9), 2),
        "phases_ms": {k: round(1000 * v / n, 1) for k, v in sorted(phases.wall.items(), key=lambda kv: -kv[1])},
        "phases_cores": {k: round(phases.cpu[k] / max(v, 1e-9), 2) for k, v in phases.wall.items()},
        "threads": {"torch": torch.get_num_threads()}, "device": args.device,
        "gpu": torch.cuda.get_device_name() if cuda else None,
        "max_memory_allocated_gib": round(torch.cuda.max_memory_allocated() / 2**30, 2) if cuda else None,
        "wall_s": round(time.perf_counter() - t0, 1),
    }
    print(json.dumps(out))


if __name__ == "__main__":
    main()
