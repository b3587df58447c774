"""Package-level behaviour: what importing cogs does to the process."""

from __future__ import annotations

import os
import subprocess
import sys


def _python(code: str, **env: str) -> str:
    base = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    res = subprocess.run([sys.executable, "-c", code], env={**base, **env}, capture_output=True,
                         text=True, check=True)
    return res.stdout.strip()


def test_importing_cogs_makes_torchs_openmp_workers_sleep_unless_the_user_chose():
    # Set before torch loads libgomp (which reads it once): cogs itself must not pull torch in.
    code = "import sys, os, cogs; print('torch' in sys.modules, os.environ.get('OMP_WAIT_POLICY'))"
    assert _python(code) == "False PASSIVE"
    assert _python(code, OMP_WAIT_POLICY="ACTIVE") == "False ACTIVE"
