"""Rasterizer benchmark: torch reference vs numba CPU backend.

Usage:  python benchmarks/rasterizer.py [--quick] [--repeats R]

Progress goes to stderr; the last stdout line is one JSON object.

Scene (cogs.render.scenes.splat_scene): camera at the origin, fx = 0.9 W; N Gaussians
uniform in depth z in [2, 6] and across 95 % of the frustum at that depth, so all are in
view; per-axis scales log-uniform so the on-screen standard deviation is 0.5-3 px (3-sigma
radii ~2-10 px, mean ~6 px), random rotations, opacities uniform in [0.05, 0.95]: the small
dense splats of a trained 3DGS scene. RGB colours (D = 3; depth rides as a 4th channel).

Work unit: Gaussian-pixel pairs as the torch reference evaluates them, i.e.
sum over 16x16 tiles of (Gaussians whose 3-sigma square touches the tile) x (pixels in the
tile). The numba kernels evaluate far fewer pairs (support boxes, early termination); the
pairs/s figures count the reference's pairs so both backends are measured in one unit.

Timings are medians; fwd+bwd also reports its minimum (``fwd_bwd_min_ms``) and the
speed-up of the minima, a steadier estimate of the work itself on a shared machine,
where other tenants stretch individual repeats by up to ~40 %; the bar ("met") is judged
on the medians. "fwd" is the forward call with grad-enabled inputs (as in training),
"fwd_bwd" is forward + backward with fixed random upstream gradients on colour, alpha and
depth (torch.autograd.backward), down to the leaf parameters' .grad.

The OpenMP wait policy decides both sides of the speed-up, in opposite directions, so each
backend is timed under the policy its users run it with. The cpu backend runs in this
process under the policy the ``cogs`` command uses (``import cogs`` sets
``OMP_WAIT_POLICY=PASSIVE`` unless the environment says otherwise; reported as
``omp_wait_policy``). The torch reference, a long chain of small parallel torch ops that
runs 2.5x slower when its workers sleep between them, is timed in a child process that
imports torch before cogs with no policy in the environment, i.e. OpenMP's default, as a
plain torch program has it (``torch_omp_wait_policy``). ``--torch-policy same`` times it in
this process instead, under the cpu backend's policy.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

import cogs  # noqa: F401  (before torch: torch's OpenMP wait policy as the cogs command has it)
import torch


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def times_ms(fn, repeats: int, sync=None) -> list[float]:
    """Wall-clock ms of each of ``repeats`` calls; ``sync`` (e.g. torch.cuda.synchronize)
    runs before and after each so asynchronous work is counted."""
    times = []
    for _ in range(repeats):
        if sync:
            sync()
        t0 = time.perf_counter()
        fn()
        if sync:
            sync()
        times.append(1e3 * (time.perf_counter() - t0))
    return times


def median_ms(fn, repeats: int) -> float:
    return statistics.median(times_ms(fn, repeats))


def matmul_gflops(n: int = 2048, repeats: int = 5) -> float:
    a = torch.randn(n, n)
    b = torch.randn(n, n)
    a @ b
    ms = median_ms(lambda: a @ b, repeats)
    return 2.0 * n**3 / (ms * 1e-3) / 1e9


def compile_times() -> dict:
    """First-call JIT compile (empty numba cache) and on-disk cache load, each measured as
    the duration of cogs.render.warmup() in a fresh interpreter (imports excluded)."""
    code = ("import time, torch; import cogs.render as r; t = time.perf_counter(); r.warmup(); "
            "print(time.perf_counter() - t)")
    out = {}
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache)
        for key in ("numba_first_call_compile_s", "numba_cached_load_s"):
            res = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                                 text=True, check=True)
            out[key] = round(float(res.stdout.strip().splitlines()[-1]), 3)
    return out


class Case:
    """One benchmark scene on ``device``: leaf parameters as an optimiser holds them, the
    camera, and fixed random upstream gradients (``scene`` stays on the host)."""

    def __init__(self, n: int, width: int, height: int, device: torch.device | str = "cpu"):
        from cogs.render.scenes import splat_scene

        self.scene = splat_scene(n, width, height, seed=0)
        self.width, self.height = width, height
        self.viewmat, self.K = self.scene.viewmat.to(device), self.scene.K.to(device)
        g = torch.Generator().manual_seed(1)
        self.w = [torch.randn(height, width, c, generator=g).to(device) for c in (3, 1, 1)]
        self.params = [t.to(device).clone().requires_grad_(True) for t in self.scene.gaussians()]

    def run(self, backend: str, backward: bool):
        from cogs.render import rasterize

        for p in self.params:
            p.grad = None
        out = rasterize(*self.params, self.viewmat, self.K, self.width, self.height, backend=backend)
        if backward:
            # random upstream gradients on colour, alpha and depth, fed straight in: the
            # measurement is the rasterizer's backward, not a loss's torch ops
            torch.autograd.backward([out.colors, out.alpha, out.depth], self.w)
        return out


def time_backend(case: Case, name: str, repeats: int, pairs: int) -> dict:
    case.run(name, True)  # warm caches / allocator
    fwd = median_ms(lambda: case.run(name, False), repeats)
    fb_all = times_ms(lambda: case.run(name, True), repeats)
    fb = statistics.median(fb_all)
    log(f"  {name}: fwd {fwd:.1f} ms, fwd+bwd {fb:.1f} ms ({pairs / fb / 1e3:.0f} Mpairs/s)")
    return {
        "fwd_ms": round(fwd, 2),
        "fwd_bwd_ms": round(fb, 2),
        "fwd_bwd_min_ms": round(min(fb_all), 2),
        "fwd_mpairs_per_s": round(pairs / fwd / 1e3, 1),
        "fwd_bwd_mpairs_per_s": round(pairs / fb / 1e3, 1),
    }


def torch_cases(sizes, counts, repeats: int, budget_s: float) -> dict:
    """{"WxH/N": timings or {"skipped": why}} for the torch reference over all cases; a case
    whose fwd+bwd, predicted from the previous count at the same size, exceeds the budget
    is skipped."""
    from cogs.render import count_pairs

    out = {}
    for width, height in sizes:
        s_per_pair = None
        for n in counts:
            case = Case(n, width, height)
            s = case.scene
            pairs = count_pairs(s.means, s.quats, s.scales, s.viewmat, s.K, width, height)
            key = f"{width}x{height}/{n}"
            if s_per_pair is not None and s_per_pair * pairs > budget_s:
                out[key] = {"skipped": f"predicted fwd+bwd {s_per_pair * pairs:.0f} s from the "
                                       "previous size exceeds --torch-budget-s"}
                log(f"{key}: torch skipped")
                continue
            log(f"{key}: torch")
            out[key] = time_backend(case, "torch", repeats, pairs)
            s_per_pair = out[key]["fwd_bwd_ms"] * 1e-3 / pairs
    return out


def torch_cases_in_child(sizes, counts, repeats: int, budget_s: float) -> dict:
    """`torch_cases` in a fresh interpreter whose torch loads OpenMP before cogs can set a
    wait policy, with none in its environment: OpenMP's default, as plain torch has it."""
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    code = ("import torch, runpy, sys; sys.argv = sys.argv[1:]; "
            "runpy.run_path(sys.argv[0], run_name='__main__')")
    argv = [__file__, "--torch-child", json.dumps([sizes, counts, repeats, budget_s])]
    res = subprocess.run([sys.executable, "-c", code, *argv], env=env, stdout=subprocess.PIPE,
                         text=True, check=True)
    return json.loads(res.stdout.strip().splitlines()[-1])


def cpu_profile(case: Case, repeats: int) -> dict:
    """Median ms of each stage of the cpu backend's forward+backward, run one by one."""
    import numpy as np

    from cogs.render import _kernels, cpu_backend
    from cogs.render.projection import tile_grid

    s = case.scene
    W, H = s.width, s.height
    tx, ty = tile_grid(W, H)
    st = {}

    def project():
        params = [t.clone().requires_grad_(True) for t in s.gaussians()]
        proj = cpu_backend.project(params[0], params[1], params[2], s.viewmat, s.K, W, H,
                                   0.01, 1e10)
        return params, proj

    st["projection_fwd"] = median_ms(project, repeats)
    params, proj = project()
    np32 = cpu_backend._np32
    m2, co, op = np32(proj.means2d), np32(proj.conics), np32(params[3])
    depths = np32(proj.depths)
    radii = proj.radii.numpy()
    fe = cpu_backend._pad4(np32(torch.cat([params[4], proj.depths[:, None]], dim=-1)))
    st["depth_sort"] = median_ms(lambda: _kernels.depth_order(depths), repeats)
    order = _kernels.depth_order(depths)
    st["binning"] = median_ms(lambda: _kernels.bin_gaussians(m2, radii, order, tx, ty), repeats)
    offsets, ids = _kernels.bin_gaussians(m2, radii, order, tx, ty)
    st["support_spans"] = median_ms(lambda: _kernels.support_spans(m2, co, op), repeats)
    spans = _kernels.support_spans(m2, co, op)
    to = cpu_backend._tile_order(tx, ty)
    args = (offsets, ids, m2, co, op, fe, spans, W, H, tx, to)
    st["pixels_fwd"] = median_ms(lambda: _kernels.forward(*args), repeats)
    _, T, last = _kernels.forward(*args)
    g = np.random.default_rng(0)
    gF = g.standard_normal((H, W, fe.shape[1])).astype(np.float32)
    gA = g.standard_normal((H, W)).astype(np.float32)
    st["pixels_bwd"] = median_ms(lambda: _kernels.backward(*args, T, last, gF, gA), repeats)
    slots = _kernels.backward(*args, T, last, gF, gA)
    st["slot_reduce"] = median_ms(lambda: _kernels.reduce_slots(ids, m2.shape[0], slots), repeats)

    def proj_bwd():
        p, pr = project()
        loss = pr.means2d.sum() + pr.conics.sum() + pr.depths.sum()
        t0 = time.perf_counter()
        loss.backward()
        return time.perf_counter() - t0

    st["projection_bwd"] = 1e3 * statistics.median(proj_bwd() for _ in range(repeats))
    st = {k: round(v, 2) for k, v in st.items()}
    st["n_intersections"] = int(ids.shape[0])
    return st


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="smoke run: small sizes, 2 repeats")
    ap.add_argument("--repeats", type=int, default=None, help="cpu repeats (default 15, quick 2)")
    ap.add_argument("--torch-budget-s", type=float, default=60.0,
                    help="skip a torch case whose predicted fwd+bwd exceeds this")
    ap.add_argument("--torch-policy", choices=("own", "same"), default="own",
                    help="own: time the torch reference in a child process under OpenMP's "
                         "default wait policy; same: in this process, under the cpu backend's")
    ap.add_argument("--torch-child", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.torch_child:
        sizes, counts, repeats, budget = json.loads(args.torch_child)
        print(json.dumps(torch_cases([tuple(x) for x in sizes], counts, repeats, budget)))
        return

    import numba

    from cogs.render import count_pairs, warmup

    sizes = [(128, 128), (256, 192)]
    counts = [5_000, 20_000, 50_000]
    if args.quick:
        sizes, counts = [(64, 48)], [500, 2_000]
    reps = args.repeats or (2 if args.quick else 15)
    torch_reps = 1 if args.quick else 3

    result = {
        "benchmark": "rasterizer",
        "load_avg_start": [round(x, 2) for x in os.getloadavg()],
        "cpu_count": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"),
        "torch_omp_wait_policy": (os.environ.get("OMP_WAIT_POLICY") if args.torch_policy == "same"
                                  else "OpenMP default (child process, torch loaded before cogs)"),
        "numba_threads": numba.get_num_threads(),
        "numba_threading_layer": None,
        "torch_version": torch.__version__,
        "numba_version": numba.__version__,
        "scene": "cogs.render.scenes.splat_scene: all in frustum, z in [2,6], on-screen sigma "
                 "0.5-3 px (3-sigma radius ~2-10 px), opacity U[0.05,0.95], D=3",
        "pair_definition": "sum over 16x16 tiles of n_gaussians_in_tile * pixels_in_tile "
                           "(the torch reference's dense evaluation)",
        "repeats": {"cpu": reps, "torch": torch_reps},
    }
    log("compile times (fresh interpreters) ...")
    result.update(compile_times())
    result["warmup_in_process_s"] = round(warmup(), 3)
    try:
        result["numba_threading_layer"] = numba.threading_layer()
    except ValueError:
        pass
    log("matmul ...")
    result["matmul_2048_f32_gflops"] = round(matmul_gflops(repeats=3 if args.quick else 7), 1)

    log("torch reference ...")
    if args.torch_policy == "own":
        torch_rows = torch_cases_in_child(sizes, counts, torch_reps, args.torch_budget_s)
    else:
        torch_rows = torch_cases(sizes, counts, torch_reps, args.torch_budget_s)

    cases = []
    for width, height in sizes:
        for n in counts:
            case = Case(n, width, height)
            s = case.scene
            pairs = count_pairs(s.means, s.quats, s.scales, s.viewmat, s.K, width, height)
            row = {"width": width, "height": height, "n_gaussians": n, "pairs": pairs,
                   "load_avg_1min": round(os.getloadavg()[0], 2)}
            log(f"{width}x{height} N={n}: pairs={pairs:,}")
            row["cpu"] = time_backend(case, "cpu", reps, pairs)
            row["torch"] = torch_rows[f"{width}x{height}/{n}"]
            if "fwd_ms" in row["torch"]:
                row["speedup_cpu_over_torch"] = {
                    "fwd": round(row["torch"]["fwd_ms"] / row["cpu"]["fwd_ms"], 1),
                    "fwd_bwd": round(row["torch"]["fwd_bwd_ms"] / row["cpu"]["fwd_bwd_ms"], 1),
                    "fwd_bwd_of_minima": round(row["torch"]["fwd_bwd_min_ms"] / row["cpu"]["fwd_bwd_min_ms"], 1),
                }
            row["cpu_profile_ms"] = cpu_profile(case, reps)
            cases.append(row)
    result["cases"] = cases
    bar = next((c for c in cases if (c["width"], c["height"], c["n_gaussians"]) == (256, 192, 20_000)), None)
    if bar is not None and "speedup_cpu_over_torch" in bar:
        sp = bar["speedup_cpu_over_torch"]["fwd_bwd"]
        mp = bar["cpu"]["fwd_bwd_mpairs_per_s"]
        result["bar_256x192_20k"] = {"speedup_fwd_bwd": sp,
                                     "speedup_fwd_bwd_of_minima": bar["speedup_cpu_over_torch"]["fwd_bwd_of_minima"],
                                     "required_speedup": 30,
                                     "cpu_fwd_bwd_mpairs_per_s": mp, "required_mpairs_per_s": 100,
                                     "met": bool(sp >= 30 and mp >= 100)}
    result["load_avg_end"] = [round(x, 2) for x in os.getloadavg()]
    print(json.dumps(result))


if __name__ == "__main__":
    main()
