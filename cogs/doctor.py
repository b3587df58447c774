"""`cogs doctor`: what this machine offers cogs, and one-time warm-ups."""

from __future__ import annotations

import importlib
import os
import platform
import time

from cogs.log import console


def _version(mod: str) -> str:
    try:
        m = importlib.import_module(mod)
        return getattr(m, "__version__", "installed")
    except Exception as e:  # any import failure is reported, not raised
        return f"unavailable ({type(e).__name__}: {str(e).splitlines()[0][:80]})"


def _wait_policy() -> str:
    policy = os.environ.get("OMP_WAIT_POLICY", "").upper()
    if policy == "PASSIVE":
        return "PASSIVE (idle torch threads sleep; see cogs/__init__.py)"
    return (f"{policy or 'unset'}: idle torch threads spin, which slows training several-fold "
            "when another process shares the cores (set OMP_WAIT_POLICY=PASSIVE)")


def report(warm: bool = False) -> int:
    import torch

    rows = [
        ("python", platform.python_version()),
        ("torch", f"{torch.__version__}, {torch.get_num_threads()} threads, CUDA {'yes' if torch.cuda.is_available() else 'no'}"),
        ("OpenMP wait policy", _wait_policy()),
        ("numba", _version("numba")),
        ("gsplat (CUDA backend)", _version("gsplat") if torch.cuda.is_available() else "not used (no CUDA device)"),
        ("cpu cores", str(os.cpu_count())),
    ]
    try:
        from cogs.eval.metrics import lpips_status

        rows.append(("LPIPS (AlexNet)", lpips_status()))
    except ImportError:
        rows.append(("LPIPS (AlexNet)", "metrics module not installed"))
    from cogs.body.anny_body import anny_cache_ready

    rows.append(("Anny asset cache", "ready" if anny_cache_ready() else "not built yet (about a minute; `cogs doctor --warm`)"))
    if warm:
        from cogs.body import load_body_model

        t0 = time.perf_counter()
        load_body_model("anny")
        rows.append(("Anny build", f"{time.perf_counter() - t0:.1f} s"))
        try:
            from cogs.render import warmup
        except ImportError:
            warmup = None
        if warmup is not None:
            t0 = time.perf_counter()
            warmup()
            rows.append(("CPU rasterizer kernels", f"compiled/loaded in {time.perf_counter() - t0:.1f} s"))
        from cogs.ssim import warmup as ssim_warmup

        rows.append(("CPU SSIM kernels", f"compiled/loaded in {ssim_warmup():.1f} s"))
    width = max(len(k) for k, _ in rows)
    for k, v in rows:
        console.print(f"{k:<{width}}  {v}", highlight=False)
    return 0
