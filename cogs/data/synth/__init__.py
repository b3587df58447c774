"""The synthetic benchmark scene: every quality number of cogs is measured on it.

An Anny person in patterned, deliberately asymmetric clothes walks through a textured
room, bends down, picks up a box (30 x 22 x 18 cm, each face its own colour) from a low
table with the right hand, turns and carries it, twisting it in the hand. A moving camera
films it, seeing the person's right and front far more than the left and back.

Ground truth (images, masks, depth, poses, cameras, planes, novel views) is rendered by
the package's own z-buffer rasterizer (`raster.py`), not by the Gaussian renderer it is
used to judge. The scene's main files hold what a preprocessing pipeline would give:
noisy body poses, object trajectory, cameras and masks, and SfM-like sparse points
(`noise.py`, `points.py`).

    from cogs.data.synth import SynthConfig, generate_scene
    scene = generate_scene(SynthConfig(frames=100))
    save_scene(scene, "out/synth")

or `cogs synth --out out/synth --preview`.
"""

from cogs.data.synth.config import NoiseConfig, SynthConfig

__all__ = ["NoiseConfig", "SynthConfig", "generate_scene", "hosnerf_split"]


def __getattr__(name: str):
    # The generator (and the body model, scipy and the rasterizer it imports) loads on first
    # use: every `cogs` command builds its options from this package's configs, most never
    # generate a scene.
    if name in ("generate_scene", "hosnerf_split"):
        from cogs.data.synth import generate

        return getattr(generate, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
