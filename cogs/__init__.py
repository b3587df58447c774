"""cogs: compositional human-object Gaussian splatting from one monocular video."""

__version__ = "0.1.0"
