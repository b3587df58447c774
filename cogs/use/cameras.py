"""Camera paths for `cogs render --camera`.

    train      the training cameras (the frame of the clip each output frame shows)
    orbit      one horizontal circle round the person, looking at them
    spiral     one and a half turns round the person, closing in and rising
    novel      the synthetic scene's novel-view cameras (gt/novel), one output frame each
    PATH.json  keys in the scene format's convention ({"frames": [{"K": 3x3,
               "world_to_camera": 4x4, "frame": k}, ...]}, "frame" optional: keys spread
               evenly), interpolated smoothly: monotone cubic (PCHIP) camera centres and
               rotation entries projected back onto rotations, K the same way

Orbits use the world's up (`posing.world_up`) and the training cameras' distance and
height above the person (a 2.5 m circle 0.5 m above their centre without a scene).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from cogs.errors import UserError
from cogs.geometry.camera import intrinsics_from_fov, look_at

CHOICES = ("train", "orbit", "spiral", "novel")
DEFAULT_SIZE = (512, 384)
DEFAULT_FOV_DEG = 50.0
ORBIT_RADIUS_SCALE = 0.75
"""Orbits and spirals circle at this fraction of the training cameras' median distance from
the person: the room behind the training cameras was never seen (checked on the demo
scene: at the full distance the circle passes through walls and furniture)."""


@dataclass
class CameraPath:
    viewmats: np.ndarray  # [N, 4, 4] world -> camera (OpenCV)
    Ks: np.ndarray  # [N, 3, 3]
    width: int
    height: int
    clip_frames: np.ndarray | None = None  # [N] the clip frame each camera belongs to (novel views)


def scale_intrinsics(K: np.ndarray, src: tuple[int, int], dst: tuple[int, int]) -> np.ndarray:
    """K [..., 3, 3] of an image src=(W, H) for the same view at dst=(W, H)."""
    K = np.array(K, np.float64, copy=True)
    sx, sy = dst[0] / src[0], dst[1] / src[1]
    K[..., 0, :] *= sx
    K[..., 1, :] *= sy
    return K


def _to_zup(up: np.ndarray) -> np.ndarray:
    """A rotation taking `up` to +z (identity for z-up worlds)."""
    from cogs.geometry.rotations import rotmat_from_two_vectors

    return rotmat_from_two_vectors(torch.from_numpy(np.asarray(up, np.float64)), torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64, device="cpu")).numpy()


def ring(centre: np.ndarray, up: np.ndarray, n: int, radius: float, height: float, spiral: bool = False) -> np.ndarray:
    """n world_to_camera matrices round `centre` about `up`: the report's orbit
    (`orbit_cameras`, in a frame where up is z), or a spiral of 1.5 turns closing from
    `radius` to 0.6 `radius` and rising from `height` - 0.4 m to `height` + 0.4 m."""
    from cogs.eval.report import orbit_cameras

    Rz = _to_zup(up)
    to_w = np.eye(4)
    to_w[:3, :3] = Rz  # world -> z-up frame
    c = Rz @ centre
    if spiral:
        out = []
        for i in range(n):
            u = i / max(n - 1, 1)
            a = 3 * np.pi * u
            r = radius * (1.0 - 0.4 * u)
            eye = c + np.array([r * np.cos(a), r * np.sin(a), height - 0.4 + 0.8 * u])
            out.append(look_at(eye, c))
    else:
        out = orbit_cameras(c, radius, height, n)
    return np.stack([w2c @ to_w for w2c in out])


def camera_path(spec: str, n: int, scene, model, motion, up: np.ndarray, size: tuple[int, int] | None,
                fps: float) -> CameraPath:
    """The cameras of `spec` for `n` output frames (novel: one per novel view)."""
    if spec == "train":
        if scene is None:
            raise UserError("--camera train needs the run's scene (pass --scene)")
        cams = scene.cameras
        if motion.clip_time is not None:
            idx = motion.clip_time.round().long().clamp(0, scene.n_frames - 1).cpu().numpy()
        else:
            idx = np.clip(np.round(np.arange(n) * scene.fps / fps), 0, scene.n_frames - 1).astype(int)
        return _sized(cams.world_to_camera[idx], cams.K[idx], (scene.width, scene.height), size)
    if spec == "novel":
        nv = None if scene is None or scene.gt is None else scene.gt.novel
        if nv is None or len(nv.frames) == 0:
            raise UserError("--camera novel: the run's scene has no novel-view cameras (synthetic scenes have them; pass --scene)")
        path = _sized(nv.cameras.world_to_camera, nv.cameras.K, (scene.width, scene.height), size)
        path.clip_frames = np.asarray(nv.frames, int)
        return path
    if spec in ("orbit", "spiral"):
        centre = _person_centre(model, motion)
        if scene is not None:
            eyes = -np.einsum("tji,tj->ti", scene.cameras.world_to_camera[:, :3, :3], scene.cameras.world_to_camera[:, :3, 3])
            rel = eyes - centre
            height = float(np.median(rel @ up))
            radius = ORBIT_RADIUS_SCALE * float(np.median(np.linalg.norm(rel - np.outer(rel @ up, up), axis=1)))
            K0, src = scene.cameras.K[0], (scene.width, scene.height)
        else:
            radius, height = 2.5, 0.5
            src = size or DEFAULT_SIZE
            K0 = intrinsics_from_fov(src[0], src[1], DEFAULT_FOV_DEG)
        vm = ring(centre, up, n, radius, height, spiral=spec == "spiral")
        return _sized(vm, np.repeat(K0[None], n, 0), src, size)
    path = Path(spec)
    if path.suffix != ".json" or not path.is_file():
        raise UserError(f"--camera {spec}: expected one of {', '.join(CHOICES)} or a camera path .json file")
    return _from_json(path, n, scene, size)


def _sized(vm: np.ndarray, K: np.ndarray, src: tuple[int, int], size: tuple[int, int] | None) -> CameraPath:
    dst = size or src
    return CameraPath(np.asarray(vm, np.float64), scale_intrinsics(K, src, dst), int(dst[0]), int(dst[1]))


@torch.no_grad()
def _person_centre(model, motion) -> np.ndarray:
    """Mean of the body's joints over the motion (a few frames of it)."""
    h = model.human
    if h is None:
        raise UserError("--camera orbit/spiral circles the person: the run has no human branch")
    ks = np.unique(np.linspace(0, len(motion) - 1, min(len(motion), 12)).round().astype(int))
    js = [h.body.bone_transforms(motion.pose[k : k + 1], motion.transl[k : k + 1], h.shape)[1][0].mean(0) for k in ks]
    return torch.stack(js).mean(0).double().cpu().numpy()


def _from_json(path: Path, n: int, scene, size: tuple[int, int] | None) -> CameraPath:
    from scipy.interpolate import PchipInterpolator

    from cogs.use.objects import _key_times
    from cogs.use.posing import polar_rotation

    what = f"--camera {path}"
    try:
        data = json.loads(path.read_text())
        keys = data["frames"]
        vm = np.array([k["world_to_camera"] for k in keys], np.float64)
        Ks = [k.get("K") for k in keys]
        at = [k.get("frame") for k in keys]
    except (ValueError, KeyError, TypeError) as e:
        raise UserError(f"{what}: not a camera path ({{\"frames\": [{{\"K\": 3x3, \"world_to_camera\": 4x4, \"frame\": k}}]}}, "
                        f"\"width\"/\"height\" optional): {type(e).__name__} {e}") from None
    if len(keys) == 0 or vm.shape != (len(keys), 4, 4):
        raise UserError(f"{what}: every key needs a 4x4 world_to_camera")
    bad = ~np.isfinite(vm).all((1, 2))
    if bad.any():
        raise UserError(f"{what}: key {int(np.argmax(bad))} has a non-finite world_to_camera")
    R = vm[:, :3, :3]
    if np.abs(R @ np.swapaxes(R, 1, 2) - np.eye(3)).max() > 1e-3:
        raise UserError(f"{what}: a world_to_camera is not rigid (its 3x3 part must be a rotation)")
    if "width" in data and "height" in data:
        src = (int(data["width"]), int(data["height"]))
    elif scene is not None:
        src = (scene.width, scene.height)
    else:
        src = size or DEFAULT_SIZE
    K0 = scene.cameras.K[0] if scene is not None and "width" not in data else intrinsics_from_fov(src[0], src[1], DEFAULT_FOV_DEG)
    K = np.array([K0 if k is None else k for k in Ks], np.float64)
    if K.shape != (len(keys), 3, 3) or not np.isfinite(K).all():
        raise UserError(f"{what}: every K must be a finite 3x3 matrix")
    t = _key_times(at, len(keys), n, what)
    frames = np.clip(np.arange(n, dtype=np.float64), t[0], t[-1])
    if len(keys) == 1:
        return _sized(np.repeat(vm, n, 0), np.repeat(K, n, 0), src, size)
    centres = -np.einsum("kji,kj->ki", R, vm[:, :3, 3])
    c = PchipInterpolator(t, centres, axis=0)(frames)
    Ri = polar_rotation(torch.from_numpy(PchipInterpolator(t, R.reshape(-1, 9), axis=0)(frames).reshape(-1, 3, 3))).numpy()
    Ki = PchipInterpolator(t, K.reshape(-1, 9), axis=0)(frames).reshape(-1, 3, 3)
    out = np.tile(np.eye(4), (n, 1, 1))
    out[:, :3, :3] = Ri
    out[:, :3, 3] = -np.einsum("nij,nj->ni", Ri, c)
    return _sized(out, Ki, src, size)
