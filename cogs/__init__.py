"""cogs: compositional human-object Gaussian splatting from one monocular video."""

import os as _os

# Torch's CPU thread pool is GNU OpenMP, whose idle workers spin for milliseconds after
# every parallel region before they sleep. With another process on the cores (CI, a
# laptop doing anything else) those spins take the cores from the threads with work:
# measured on 2 cores, 80 steps of stage I under load took 194-247 s with the default
# policy and 17-22 s with PASSIVE. libgomp reads the policy once, when torch first loads
# it, so this works only if cogs is imported before torch (the `cogs` command is); an
# explicit setting in the environment wins.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

__version__ = "0.1.0"
