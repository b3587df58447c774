"""`--device` values: checked once, before any work, by every command that takes one."""

from __future__ import annotations

from cogs.errors import UserError


def check_device(name: str) -> str:
    """`--device`: cpu, cuda or cuda:N, and only where this torch has it (before any work)."""
    import re

    import torch

    if name == "cpu":
        return name
    if not re.fullmatch(r"cuda(:\d+)?", name):
        raise UserError(f"--device {name!r}: expected cpu, cuda or cuda:N")
    if not torch.cuda.is_available():
        raise UserError(f"--device {name}: this torch ({torch.__version__}) sees no CUDA device; use --device cpu, "
                        "or install a CUDA build of torch and the cuda extra (README, Installation)")
    index = int(name.split(":")[1]) if ":" in name else 0
    if index >= torch.cuda.device_count():
        raise UserError(f"--device {name}: only {torch.cuda.device_count()} CUDA device(s) here")
    return name
