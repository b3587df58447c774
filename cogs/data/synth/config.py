"""Configuration of the synthetic benchmark scene (dataclasses; tyro turns them into flags)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field


@dataclass
class NoiseConfig:
    """Noise on the inputs a preprocessing pipeline would have produced.

    The noisy values go in the scene's main files (body.npz, object.json, cameras.json,
    masks/, points.ply); the exact ones in gt/. Every term is seeded by the scene seed.
    "Smooth" terms are Gaussian-filtered white noise with time scale `smooth_s`, scaled
    to the given standard deviation; "jitter" terms are independent per frame.
    """

    enabled: bool = True
    """Master switch: False writes the ground truth as the inputs (points exact too)."""
    smooth_s: float = 1.0
    """Time scale (seconds, Gaussian sigma) of the smooth, low-frequency offsets."""
    body_deg: float = 3.0
    """Smooth rotation offset per major joint (spine, neck, head, hips, knees, ankles, shoulders, elbows, wrists), degrees std per axis."""
    body_jitter_deg: float = 0.7
    """Per-frame rotation jitter on the same joints, degrees std per axis."""
    root_deg: float = 2.0
    """Smooth offset of the body's global orientation, degrees std per axis."""
    transl_m: float = 0.025
    """Smooth offset of the body's root translation, metres std per axis."""
    transl_jitter_m: float = 0.005
    """Per-frame root translation jitter, metres std per axis."""
    shape: float = 0.0
    """Noise on the body shape vector (phenotype units, std); 0 keeps the true shape."""
    object_m: float = 0.02
    """Smooth object translation offset, metres std per axis."""
    object_jitter_m: float = 0.006
    """Per-frame object translation jitter, metres std per axis."""
    object_deg: float = 4.0
    """Smooth object rotation offset, degrees std per axis."""
    object_jitter_deg: float = 1.5
    """Per-frame object rotation jitter, degrees std per axis."""
    camera_deg: float = 0.05
    """Per-frame camera rotation error, degrees std per axis. About 0.17 px at the default
    resolution: the sub-pixel consistency structure from motion gives (pycolmap reached a
    0.5 px reprojection RMS, point noise included, on the real clip). Independent per-frame
    jitter of 0.2 deg would already misalign test frames by over a pixel, more than any
    SfM pipeline leaves."""
    camera_m: float = 0.002
    """Per-frame camera position error, metres std per axis."""
    mask_px: float = 0.8
    """Boundary jitter of the masks: std (pixels) of a smooth displacement field, clipped at 2 px."""
    mask_morph_prob: float = 0.5
    """Probability per frame and mask of a 1-pixel erosion or dilation (equally likely)."""
    points_m: float = 0.01
    """Sparse-point position noise, metres std per axis (displacement capped at 3 std)."""


@dataclass
class SynthConfig:
    """The synthetic benchmark scene: an Anny person picks up a box in a textured room."""

    frames: int = 100
    """Number of frames; the 10-second choreography is stretched to the clip."""
    width: int = 256
    """Image width in pixels."""
    height: int = 192
    """Image height in pixels."""
    fps: float = 10.0
    """Frame rate written to scene.json (the 10-second script matches video time only when frames / fps = 10)."""
    seed: int = 0
    """Seed of every random draw of the inputs (noise, point sampling): the rendered video is the same at every seed."""
    variant: int = 0
    """Choreography variant: 0 is the reference script (the demo scene); any other number is
    another video of the same story: the box's resting place and heading, the walk in and out
    and the camera path drawn from this number (`motion.script`)."""
    fov_deg: float = 55.0
    """Vertical field of view of the camera, degrees."""
    supersample: int = 3
    """Samples per pixel side for anti-aliasing (odd)."""
    shape: tuple[float, float, float, float, float, float] = (0.35, 0.62, 0.55, 0.5, 0.5, 0.5)
    """Anny phenotype: gender, age, muscle, weight, height, proportions (an adult, ~1.75 m)."""
    points: int = 5000
    """Maximum number of sparse points."""
    novel_rings: int = 4
    """Frames at which a ring of novel-view cameras is rendered."""
    novel_per_ring: int = 8
    """Cameras per ring."""
    noise: NoiseConfig = field(default_factory=NoiseConfig)
    """Noise on the pipeline-like inputs."""

    def to_dict(self) -> dict:
        return asdict(self)
