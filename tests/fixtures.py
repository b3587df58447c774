"""Small scenes and helpers the tests generate with the project's own writers."""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import numpy as np

from cogs.data.scene import (
    BodyTrack,
    CameraTrack,
    GroundTruth,
    NovelViews,
    ObjectTrack,
    PlaneSpec,
    Scene,
    default_frame_ids,
    save_scene,
)
from cogs.geometry.camera import intrinsics_from_fov, look_at

# `cogs train --set` overrides for a run of every stage in seconds (on `small_synthetic`).
TINY = [
    "schedule.I=6", "schedule.II=4", "schedule.III=6", "schedule.IV=6", "schedule.V=8", "schedule.VI=10",
    "branches.human.n_gaussians=1500", "branches.human.triplane_resolution=16", "branches.object.max_gaussians=400",
    "branches.object.hull_resolution=16", "checkpoint_every=3", "visibility_every=4", "plane_assign_every=3",
    "human_density.refine_every=2", "object_density.refine_every=2", "scene_density.refine_every=2",
    "scene_density.max_gaussians=3000", "branches.color_init_frames=4", "refit.steps=4",
]


def make_tiny_scene(root: Path, n_frames: int = 6, width: int = 40, height: int = 30, seed: int = 0,
                    ground_truth: bool = False) -> Path:
    """A valid scene: random images, disc masks, a camera arc, zero Anny poses, a box track;
    with `ground_truth`, also a gt/ folder (the inputs as truth, a constant depth, the floor
    plane, and two novel views)."""
    rng = np.random.default_rng(seed)
    ids = default_frame_ids(n_frames)
    K = intrinsics_from_fov(width, height, 55.0)
    w2c = np.stack([look_at([2.5 * np.cos(a), 2.5 * np.sin(a), 1.2], [0, 0, 0.9]) for a in np.linspace(-0.4, 0.4, n_frames)])
    yy, xx = np.mgrid[:height, :width]
    human = np.stack([(xx - width / 2) ** 2 + (yy - height / 2) ** 2 < (height / 3) ** 2] * n_frames)
    obj = np.stack([(xx - width / 2 - 8) ** 2 + (yy - height / 2) ** 2 < 16] * n_frames)
    quats = np.tile([1.0, 0.0, 0.0, 0.0], (n_frames, 1))
    scene = Scene(
        root=None,
        name="tiny",
        width=width,
        height=height,
        fps=10.0,
        frame_ids=ids,
        split={"train": list(range(1, n_frames)), "test": [0]},
        cameras=CameraTrack(K=np.tile(K, (n_frames, 1, 1)), world_to_camera=w2c),
        body=BodyTrack(
            model="anny",
            shape=np.full(6, 0.5, dtype=np.float32),
            pose=np.zeros((n_frames, 104, 3), dtype=np.float32),
            transl=np.tile([0.0, 0.0, 0.87], (n_frames, 1)).astype(np.float32),
        ),
        object=ObjectTrack(centre=np.zeros(3), quats=quats, translations=np.tile([0.3, -0.2, 0.9], (n_frames, 1))),
        points_xyz=rng.uniform(-2, 2, (50, 3)).astype(np.float32),
        points_rgb=rng.integers(0, 255, (50, 3), dtype=np.uint8),
        planes=[PlaneSpec(np.array([0.0, 0.0, 1.0]), 0.0, "floor")],
    )
    images = rng.integers(0, 255, (n_frames, height, width, 3), dtype=np.uint8)
    scene.set_pixels(images, human, obj)
    if ground_truth:
        depth = np.full((n_frames, height, width), 2.5, np.float32)
        scene.gt = GroundTruth(
            cameras=scene.cameras, body=scene.body, object=scene.object, human_masks=human, object_masks=obj,
            depth=depth, planes=list(scene.planes),
            novel=NovelViews(frames=np.array([0, n_frames - 1]), cameras=CameraTrack(K=scene.cameras.K[:2], world_to_camera=w2c[::-1][:2].copy()),
                             images=images[:2], human_masks=human[:2], object_masks=obj[:2], depth=depth[:2]),
        )
    return save_scene(scene, root)


def tree_hash(root: Path) -> str:
    """Names, modes and contents of everything under `root` (links not followed)."""
    h = hashlib.sha256()
    for dirpath, dirnames, filenames in sorted(os.walk(root)):
        dirnames.sort()
        for name in sorted(dirnames + filenames):
            p = Path(dirpath) / name
            st = p.lstat()
            h.update(f"{p.relative_to(root)}|{st.st_mode:o}".encode())
            if p.is_file() and not p.is_symlink():
                try:
                    h.update(p.read_bytes())
                except PermissionError:  # a case made it unreadable: its mode is hashed
                    pass
    return h.hexdigest()
