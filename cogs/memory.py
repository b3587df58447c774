"""How much memory this process may still use (for the up-front checks of `cogs train`,
`cogs synth` and `cogs preprocess`, which refuse work that cannot fit instead of meeting
the kernel's out-of-memory killer)."""

from __future__ import annotations

import os

from cogs.errors import UserError

GiB = 1024**3

MEMORY_ENV = "COGS_MEMORY_GB"
"""Environment variable: the memory (GiB) the checks believe available, overriding what
the machine reports (for a shared machine, a container, or a test)."""


def available_bytes() -> int | None:
    """Memory this process may still use: COGS_MEMORY_GB if set, else the kernel's
    MemAvailable (and a cgroup limit, if lower); None where neither can be read."""
    if os.environ.get(MEMORY_ENV):
        try:
            return int(float(os.environ[MEMORY_ENV]) * GiB)
        except ValueError:
            raise UserError(f"${MEMORY_ENV}={os.environ[MEMORY_ENV]!r}: expected a number of GiB") from None
    avail = None
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    avail = int(line.split()[1]) * 1024
    except OSError:
        pass
    for path in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
        try:
            raw = open(path).read().strip()
        except OSError:
            continue
        if raw.isdigit() and int(raw) < (avail or 1 << 62):
            avail = int(raw)
    return avail
