"""What every benchmark importer shares: COLMAP text models, undistortion, the benchmarks'
splits, SMPL fits in a dataset's world, and the conversion of those fits to a body track
(SMPL kept as is, or retargeted onto Anny).

Importers read a dataset's files, fill an `ImportedFrames` (pixels, cameras, SMPL fits,
points) and hand it to `write_scene`, which converts the body and writes a native scene.
Every problem a user can cause (a missing or malformed file, an unsupported camera model,
SMPL fits without joints and no SMPL model) is a `UserError` naming the file.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from cogs.data.outdir import check_out_folder, staged
from cogs.data.scene import BodyTrack, CameraTrack, ObjectTrack, Scene, save_scene
from cogs.errors import UserError
from cogs.geometry.camera import camera_center, project_points
from cogs.geometry.rotations import axis_angle_to_rotmat, quat_to_rotmat, rotmat_to_axis_angle

log = logging.getLogger(__name__)

# -- small readers ----------------------------------------------------------------------


def require(path: Path, what: str) -> Path:
    """`path` if it exists, else a UserError naming it and what it should hold."""
    if not path.exists():
        raise UserError(f"{path}: missing ({what})")
    return path


def read_rgb(path: Path) -> np.ndarray:
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            return np.asarray(im.convert("RGB"))
    except FileNotFoundError:
        raise UserError(f"{path}: image missing") from None
    except (UnidentifiedImageError, OSError) as e:
        raise UserError(f"{path}: unreadable image ({e})") from None


def read_gray(path: Path) -> np.ndarray:
    """[H, W] uint8 from a PNG/JPG (colour masks are averaged) or a .npy mask."""
    if path.suffix == ".npy":
        try:
            arr = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as e:
            raise UserError(f"{path}: unreadable mask ({e})") from None
        arr = np.asarray(arr)
        if arr.ndim == 3:
            arr = arr[..., 0]
        if arr.dtype == bool or arr.max() <= 1:
            arr = arr.astype(np.uint8) * 255
        return arr.astype(np.uint8)
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            return np.asarray(im.convert("L"))
    except FileNotFoundError:
        raise UserError(f"{path}: mask missing") from None
    except (UnidentifiedImageError, OSError) as e:
        raise UserError(f"{path}: unreadable mask ({e})") from None


def as_array(value, shape: tuple, what: str, where: str) -> np.ndarray:
    """`value` as a float64 array of `shape` (-1 = any), else a UserError naming `where`."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise UserError(f"{where}: `{what}` is not numeric") from None
    if arr.ndim != len(shape) or any(s != -1 and s != a for s, a in zip(shape, arr.shape)):
        raise UserError(f"{where}: `{what}` has shape {list(arr.shape)}, expected {list(shape)}")
    if not np.isfinite(arr).all():
        raise UserError(f"{where}: `{what}` has non-finite numbers")
    return arr


# -- COLMAP text model ------------------------------------------------------------------


@dataclass
class ColmapCamera:
    model: str
    width: int
    height: int
    params: np.ndarray


@dataclass
class ColmapImage:
    name: str
    qvec: np.ndarray  # [4] wxyz, world -> camera
    tvec: np.ndarray  # [3]
    camera_id: int

    def world_to_camera(self) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = quat_to_rotmat(torch.from_numpy(self.qvec)).numpy()
        T[:3, 3] = self.tvec
        return T


def _data_lines(path: Path, keep_blank: bool = False) -> list[str]:
    text = require(path, "COLMAP text model").read_text().splitlines()
    return [ln.strip() for ln in text if not ln.startswith("#") and (keep_blank or ln.strip())]


def read_colmap_cameras(path: Path) -> dict[int, ColmapCamera]:
    cams = {}
    for ln in _data_lines(path):
        tok = ln.split()
        try:
            cams[int(tok[0])] = ColmapCamera(tok[1], int(tok[2]), int(tok[3]), np.array([float(x) for x in tok[4:]]))
        except (IndexError, ValueError):
            raise UserError(f"{path}: malformed camera line {ln!r}") from None
    if not cams:
        raise UserError(f"{path}: no cameras")
    return cams


def read_colmap_images(path: Path) -> list[ColmapImage]:
    """Registered images (each takes two lines; the second, its 2D points, may be blank)."""
    lines = _data_lines(path, keep_blank=True)
    while lines and not lines[-1]:
        lines.pop()
    out, i = [], 0
    while i < len(lines):
        if not lines[i]:  # a blank points line of the previous image
            i += 1
            continue
        tok = lines[i].split()
        if len(tok) < 10:
            raise UserError(f"{path}: malformed image line {lines[i]!r}")
        try:
            out.append(ColmapImage(
                name=" ".join(tok[9:]),
                qvec=np.array([float(x) for x in tok[1:5]]),
                tvec=np.array([float(x) for x in tok[5:8]]),
                camera_id=int(tok[8]),
            ))
        except ValueError:
            raise UserError(f"{path}: malformed image line {lines[i]!r}") from None
        i += 2
    if not out:
        raise UserError(f"{path}: no registered images")
    return out


def read_colmap_points(path: Path) -> tuple[np.ndarray, np.ndarray]:
    xyz, rgb = [], []
    for ln in _data_lines(path):
        tok = ln.split()
        try:
            xyz.append([float(t) for t in tok[1:4]])
            rgb.append([int(t) for t in tok[4:7]])
        except (IndexError, ValueError):
            raise UserError(f"{path}: malformed point line {ln[:80]!r}") from None
    return np.asarray(xyz, dtype=np.float64).reshape(-1, 3), np.asarray(rgb, dtype=np.uint8).reshape(-1, 3)


def colmap_intrinsics(cam: ColmapCamera, where: str) -> tuple[np.ndarray, np.ndarray | None]:
    """(K [3, 3], OpenCV distortion coefficients or None) for a COLMAP camera model.

    COLMAP's pixel convention (pixel centres at +0.5) is cogs' own, so K is used as is.
    Fisheye and other models without an OpenCV equivalent are refused.
    """
    p = cam.params
    n = {"SIMPLE_PINHOLE": 3, "PINHOLE": 4, "SIMPLE_RADIAL": 4, "RADIAL": 5, "OPENCV": 8, "FULL_OPENCV": 12}
    if cam.model not in n:
        raise UserError(
            f"{where}: camera model {cam.model} is not supported (supported: {', '.join(n)}); "
            "undistort the images with COLMAP's image_undistorter and import its PINHOLE output"
        )
    if len(p) != n[cam.model]:
        raise UserError(f"{where}: {cam.model} needs {n[cam.model]} parameters, got {len(p)}")
    if cam.model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
        fx = fy = p[0]
        cx, cy = p[1], p[2]
    else:
        fx, fy, cx, cy = p[:4]
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    dist = {
        "SIMPLE_PINHOLE": None,
        "PINHOLE": None,
        "SIMPLE_RADIAL": np.array([p[3], 0.0, 0.0, 0.0]) if len(p) > 3 else None,
        "RADIAL": np.array([p[3], p[4], 0.0, 0.0]) if len(p) > 4 else None,
        "OPENCV": p[4:8].copy(),
        # COLMAP: k1 k2 p1 p2 k3 k4 k5 k6; OpenCV: k1 k2 p1 p2 k3 k4 k5 k6.
        "FULL_OPENCV": p[4:12].copy(),
    }[cam.model]
    if dist is not None and not np.any(dist):
        dist = None
    return K, dist


# -- undistortion ---------------------------------------------------------------------


class Undistorter:
    """Remaps images and masks of one camera to the same K without distortion.

    `K` is in cogs' convention (pixel centres at +0.5); OpenCV puts them at integers, so
    its principal point is shifted by half a pixel for the remap and back.
    """

    def __init__(self, K: np.ndarray, dist: np.ndarray, width: int, height: int):
        import cv2

        Kcv = K.copy()
        Kcv[0, 2] -= 0.5
        Kcv[1, 2] -= 0.5
        self.map1, self.map2 = cv2.initUndistortRectifyMap(
            Kcv, np.asarray(dist, dtype=np.float64), None, Kcv, (width, height), cv2.CV_32FC1
        )

    def image(self, rgb: np.ndarray) -> np.ndarray:
        import cv2

        return cv2.remap(rgb, self.map1, self.map2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)

    def mask(self, mask: np.ndarray) -> np.ndarray:
        import cv2

        return cv2.remap(mask.astype(np.uint8), self.map1, self.map2, cv2.INTER_NEAREST,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=0) > 0


# -- splits -----------------------------------------------------------------------------


def neuman_split(n: int) -> tuple[list[int], list[int], list[int]]:
    """NeuMan's split of n frames in video order: (train, val, test).

    The benchmark's own rule (its `create_split_files`, also HUGS' `get_data_splits`):
    num_val = n // 5 held-out frames spaced `length = int(1 / num_val * n)` apart starting at
    `length // 2`; the first half of them (rounded down) is test, the rest val, and every
    other frame trains. For 25 <= n < 1245 this is every 5th frame from offset 2. The float
    expression is kept as is, since it is what defines the benchmark.
    """
    num_val = n // 5
    if num_val < 2:
        raise UserError(f"NeuMan's split needs at least 10 frames, the sequence has {n}")
    length = int(1 / (num_val) * n)
    held = list(range(n))[length // 2 :: length]
    test, val = held[: len(held) // 2], held[len(held) // 2 :]
    train = [i for i in range(n) if i not in set(held)]
    return train, val, test


def hosnerf16_split(n: int) -> tuple[list[int], list[int]]:
    """The hosnerf-16 protocol (train, test): every (n // 16)-th frame from 0, the first 16 of
    them, is test. Sequences under 32 frames (where that step is below 2) hold out every
    other frame from 0 instead, so that something is left to train on."""
    step = n // 16
    test = list(range(0, n, step))[:16] if step >= 2 else list(range(0, n, 2))
    held = set(test)
    return [i for i in range(n) if i not in held], test


# -- SMPL fits in a dataset's world ------------------------------------------------------


@dataclass
class SmplFits:
    """Per-frame SMPL parameters and how the dataset places them in its world.

    world point = scale[t] * rotation[t] @ x_body + translation[t], where x_body is SMPL's
    output for (global_orient, body_pose, betas) with zero translation, shifted so that the
    rest-pose pelvis J0 lands on `pelvis_in_body[t]` when that is given (HumanNeRF's "body"
    coordinates), or unshifted when it is None (NeuMan).
    """

    global_orient: np.ndarray  # [T, 3]
    body_pose: np.ndarray  # [T, 69]
    betas: np.ndarray | None  # [10]; None when the dataset does not store them
    scale: np.ndarray  # [T]
    rotation: np.ndarray  # [T, 3, 3]
    translation: np.ndarray  # [T, 3]
    joints: np.ndarray | None  # [T, 24, 3] SMPL joints in body coordinates
    pelvis_in_body: np.ndarray | None = None  # [T, 3]
    rest_joints: np.ndarray | None = None  # [24, 3] zero-pose joints (for shape), if known
    source: str = ""  # file(s) the fits come from, for messages

    def __len__(self) -> int:
        return len(self.global_orient)


def similarity_parts(M: np.ndarray, where: str) -> tuple[float, np.ndarray]:
    """(s, R) with M = s R for a 3x3 scaled rotation (NeuMan's alignment blocks)."""
    det = float(np.linalg.det(M))
    if not np.isfinite(det) or det <= 0:
        raise UserError(f"{where}: alignment is not a scaled rotation (det {det:g})")
    s = det ** (1.0 / 3.0)
    U, _, Vt = np.linalg.svd(M / s)
    R = U @ Vt
    if np.abs(M / s - R).max() > 1e-2:
        raise UserError(f"{where}: alignment is not a uniform scale times a rotation")
    return s, R


def fold_scale(fits: SmplFits, cam_centres: np.ndarray, world_scale: float) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame rigid placement (R [T, 3, 3], c [T, 3]) of the body in the imported world.

    The imported world is the dataset's divided by `world_scale` (chosen so the body is
    metric), and `cam_centres` [T, 3] are in it. A frame whose fit has another scale s_t is
    scaled about that frame's camera centre by world_scale / s_t, which leaves its image
    unchanged and the body metric: x_world = R_t x_body + t_t / s_t + C_t (1 - k / s_t).
    """
    s = fits.scale[:, None]
    c = fits.translation / s + cam_centres * (1.0 - world_scale / s)
    return fits.rotation, c


def smpl_joints_in_world(fits: SmplFits, R: np.ndarray, c: np.ndarray) -> np.ndarray:
    return np.einsum("tij,tkj->tki", R, fits.joints) + c[:, None, :]


def smpl_body_track(fits: SmplFits, R: np.ndarray, c: np.ndarray, model_path: Path | None) -> tuple[BodyTrack, dict]:
    """Keep SMPL: global rotation and translation folded into pose[:, 0] and transl."""
    from cogs.body.smpl_body import SmplBody

    body = SmplBody(model_path)
    info: dict = {"model_file": body.model_file.name}
    if fits.betas is not None:
        betas = torch.as_tensor(fits.betas, dtype=torch.float32)
        info["betas_from"] = "dataset"
    elif fits.rest_joints is not None:
        betas = body.betas_from_rest_joints(torch.as_tensor(fits.rest_joints))
        info["betas_from"] = "rest joints (least squares with the SMPL model)"
    else:
        raise UserError(f"{fits.source}: no SMPL shape (betas) and no rest-pose joints to recover it from")
    J0 = body.canonical(betas).joints[0].double().numpy()
    Rg = axis_angle_to_rotmat(torch.from_numpy(fits.global_orient)).numpy()
    root = np.einsum("tij,tjk->tik", R, Rg)
    delta = (fits.pelvis_in_body - J0) if fits.pelvis_in_body is not None else np.zeros_like(c)
    # x_world = R (Rg (v - J0) + J0 + delta) + c  =  (R Rg)(v - J0) + J0 + transl
    transl = np.einsum("tij,tj->ti", R, J0[None] + delta) + c - J0
    pose = np.concatenate([rotmat_to_axis_angle(torch.from_numpy(root)).numpy()[:, None],
                           fits.body_pose.reshape(-1, 23, 3)], axis=1)
    return BodyTrack("smpl", betas.numpy().astype(np.float32), pose.astype(np.float32), transl.astype(np.float32)), info


_NO_JOINTS = (
    "{src}: these SMPL fits carry pose parameters but no joint positions, and no SMPL model "
    "file was given. Either import with `--body-model smpl --smpl-model PATH` (licensed SMPL "
    "model), or add the 24 SMPL joints per frame to the fits (key `joints`, shape [T, 24, 3], "
    "in the same coordinates as the SMPL output the fits describe) so cogs can retarget them "
    "onto the free Anny model."
)


def anny_body_track(fits: SmplFits, R: np.ndarray, c: np.ndarray) -> tuple[BodyTrack, dict]:
    """Retarget the SMPL joints onto Anny (no SMPL licence needed)."""
    from cogs.body import load_body_model
    from cogs.body.retarget import retarget_smpl_joints

    if fits.joints is None:
        raise UserError(_NO_JOINTS.format(src=fits.source))
    targets = smpl_joints_in_world(fits, R, c)
    body = load_body_model("anny")
    log.info("retargeting %d frames of SMPL joints onto Anny", len(targets))
    res = retarget_smpl_joints(torch.from_numpy(targets), body)
    err = res.joint_error_m
    info = {
        "retargeted_from": "smpl joints",
        "mean_joint_error_m": round(float(err.mean()), 5),
        "max_joint_error_m": round(float(err.max()), 5),
        "seconds": round(res.seconds, 2),
    }
    log.info("retargeted in %.1f s: mean joint error %.1f mm (max %.1f mm)", res.seconds, 1e3 * float(err.mean()), 1e3 * float(err.max()))
    track = BodyTrack("anny", res.shape.numpy(), res.pose.numpy(), res.transl.numpy())
    return track, info


# -- object initial guess ---------------------------------------------------------------


def object_track_from_masks(masks: np.ndarray, cameras: CameraTrack, hand_joints: np.ndarray) -> ObjectTrack:
    """An initial rigid object track from its masks: per frame, the mask centroid back-
    projected to the depth of the hand joint nearest to it in the image, identity rotation.
    Frames with an empty mask take the nearest frame's position. (The trainer refines it.)

    masks [T, H, W] bool; hand_joints [T, 2, 3] world (left, right hand).
    """
    T = len(masks)
    centres = np.full((T, 3), np.nan)
    for t in range(T):
        ys, xs = np.nonzero(masks[t])
        if len(xs) == 0:
            continue
        uv = np.array([xs.mean() + 0.5, ys.mean() + 0.5])
        K, w2c = cameras.K[t], cameras.world_to_camera[t]
        pix, depth = project_points(hand_joints[t], w2c, K)
        k = int(np.argmin(np.linalg.norm(pix - uv, axis=1)))
        z = max(float(depth[k]), 1e-3)
        ray = np.linalg.solve(K, np.array([uv[0], uv[1], 1.0]))
        p_cam = ray * z
        c2w = np.linalg.inv(w2c)
        centres[t] = c2w[:3, :3] @ p_cam + c2w[:3, 3]
    have = np.flatnonzero(np.isfinite(centres[:, 0]))
    if len(have) == 0:
        raise UserError("the object masks are empty in every frame")
    for t in range(T):
        if not np.isfinite(centres[t, 0]):
            centres[t] = centres[have[np.argmin(np.abs(have - t))]]
    quats = np.tile([1.0, 0.0, 0.0, 0.0], (T, 1))
    return ObjectTrack(centre=np.zeros(3), quats=quats, translations=centres)


# -- sparse points without SfM ------------------------------------------------------------


def ground_plane_points(
    images: np.ndarray, masks: np.ndarray, cameras: CameraTrack, joints: np.ndarray, spacing_m: float = 0.05
) -> tuple[np.ndarray, np.ndarray, str]:
    """A depth-free guess of static points: a grid on the ground plane under the feet.

    The plane's normal is the mean pelvis->neck direction, its height 3 cm below the lowest
    foot joint over the sequence. Grid points seen in some frame outside the human/object
    masks are kept and coloured by the median of what those frames show there. When the
    ground is never visible (close-up shots), a fronto-parallel backdrop at twice the body's
    distance from the first camera is used instead. Returns (xyz, rgb, how).

    joints [T, 24, 3] SMPL-order world joints; masks [T, H, W] bool (anything dynamic).
    """
    T, H, W = masks.shape
    up = (joints[:, 12] - joints[:, 0]).mean(0)
    up /= max(np.linalg.norm(up), 1e-9)
    feet = joints[:, [7, 8, 10, 11]].reshape(-1, 3)
    height = float((feet @ up).min()) - 0.03
    centre = joints[:, 0].mean(0)
    centre = centre - (centre @ up - height) * up
    extent = float(np.linalg.norm(joints[:, 0] - joints[:, 0].mean(0), axis=1).max())
    radius = max(3.0, 2.0 * extent)
    a = np.cross(up, [1.0, 0.0, 0.0])
    if np.linalg.norm(a) < 1e-3:
        a = np.cross(up, [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(up, a)
    g = np.arange(-radius, radius + 1e-9, spacing_m)
    u, v = np.meshgrid(g, g)
    keep = u**2 + v**2 <= radius**2
    pts = centre + u[keep, None] * a + v[keep, None] * b
    xyz, rgb = _visible_colours(pts, images, masks, cameras)
    if len(xyz) >= 50:
        return xyz, rgb, f"ground plane under the feet ({len(xyz)} points, {spacing_m} m grid)"
    # Backdrop: a plane facing the first camera behind the person.
    w2c = cameras.world_to_camera[0]
    K = cameras.K[0]
    depth = 2.0 * float(np.median((joints[0] @ w2c[:3, :3].T + w2c[:3, 3])[:, 2]))
    xs, ys = np.meshgrid(np.linspace(0, W, 48), np.linspace(0, H, 36))
    rays = np.linalg.solve(K, np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)]))
    p_cam = (rays * depth).T
    c2w = np.linalg.inv(w2c)
    pts = p_cam @ c2w[:3, :3].T + c2w[:3, 3]
    xyz, rgb = _visible_colours(pts, images, masks, cameras)
    if len(xyz) == 0:
        xyz, rgb = pts, np.full((len(pts), 3), 128, np.uint8)
    return xyz, rgb, f"backdrop plane at {depth:.2f} m from the first camera ({len(xyz)} points; ground never visible)"


def _visible_colours(pts, images, masks, cameras) -> tuple[np.ndarray, np.ndarray]:
    T, H, W = masks.shape
    samples = [[] for _ in range(len(pts))]
    for t in range(T):
        pix, depth = project_points(pts, cameras.world_to_camera[t], cameras.K[t])
        x = np.floor(pix[:, 0]).astype(np.int64)
        y = np.floor(pix[:, 1]).astype(np.int64)
        ok = (depth > 1e-3) & (x >= 0) & (x < W) & (y >= 0) & (y < H)
        idx = np.flatnonzero(ok)
        idx = idx[~masks[t, y[idx], x[idx]]]
        for i, c in zip(idx, images[t, y[idx], x[idx]]):
            samples[i].append(c)
    seen = [i for i, s in enumerate(samples) if s]
    if not seen:
        return np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
    rgb = np.array([np.median(np.array(samples[i]), axis=0) for i in seen]).astype(np.uint8)
    return pts[seen], rgb


# -- writing ------------------------------------------------------------------------------


@dataclass
class ImportedFrames:
    """Everything an importer read, in the imported world (metres, OpenCV cameras)."""

    name: str
    frame_ids: list[str]
    images: np.ndarray  # [T, H, W, 3] uint8
    human_masks: np.ndarray  # [T, H, W] bool
    object_masks: np.ndarray | None
    cameras: CameraTrack
    fits: SmplFits
    body_R: np.ndarray  # [T, 3, 3] body placement (see fold_scale)
    body_c: np.ndarray  # [T, 3]
    split: dict[str, list[int]]
    points_xyz: np.ndarray | None  # None: guess them from the body (ground plane)
    points_rgb: np.ndarray | None
    fps: float = 30.0
    source: dict = field(default_factory=dict)


@dataclass(frozen=True)
class FrameSelection:
    """Which frames an import keeps and at what size: every `stride`-th frame from `start`,
    at most `limit` of them; the longer side at most `max_side` pixels."""

    start: int = 0
    stride: int = 1
    limit: int | None = None
    max_side: int | None = None

    def check(self) -> "FrameSelection":
        """Before any work: every value legal (UserError naming the option)."""
        for name, value, low in (("--start", self.start, 0), ("--stride", self.stride, 1),
                                 ("--limit", self.limit, 1), ("--max-side", self.max_side, 32)):
            if value is not None and value < low:
                raise UserError(f"{name} must be at least {low}, got {value}")
        return self

    @property
    def identity(self) -> bool:
        return self.start == 0 and self.stride == 1 and self.limit is None and self.max_side is None

    def indices(self, n: int, where: str) -> list[int]:
        idx = list(range(self.start, n, self.stride))[: self.limit]
        if len(idx) < 2:
            raise UserError(f"{where}: --start {self.start} --stride {self.stride} keeps {len(idx)} of its {n} frames; "
                            "a scene needs at least 2")
        return idx


def select_frames(frames: ImportedFrames, sel: FrameSelection, split_rule, where: str) -> ImportedFrames:
    """The imported frames `sel` keeps, resized to its `max_side` (intrinsics scaled), with
    the dataset's split rule applied to the frames kept. Unchanged for the identity."""
    if sel.identity:
        return frames
    from dataclasses import replace

    from cogs.data.scene import reduced_size, resize_image, resize_mask, scale_intrinsics

    idx = sel.indices(len(frames.frame_ids), where)
    pick = lambda a: None if a is None else np.asarray(a)[idx]  # noqa: E731
    f = frames.fits
    fits = replace(f, global_orient=pick(f.global_orient), body_pose=pick(f.body_pose), scale=pick(f.scale),
                   rotation=pick(f.rotation), translation=pick(f.translation), joints=pick(f.joints),
                   pelvis_in_body=pick(f.pelvis_in_body))
    images, human, obj = pick(frames.images), pick(frames.human_masks), pick(frames.object_masks)
    K = frames.cameras.K[idx]
    H, W = images.shape[1:3]
    w, h = reduced_size(W, H, sel.max_side)
    if (w, h) != (W, H):
        images = np.stack([resize_image(im, w, h) for im in images])
        human = np.stack([resize_mask(m, w, h) for m in human])
        obj = None if obj is None else np.stack([resize_mask(m, w, h) for m in obj])
        K = scale_intrinsics(K, w / W, h / H)
    source = {**frames.source, "selection": {"start": sel.start, "stride": sel.stride, "limit": sel.limit,
                                             "max_side": sel.max_side, "frames_of_the_sequence": idx,
                                             "size_of_the_sequence": [W, H],
                                             "split": "the dataset's rule applied to the frames kept"}}
    return replace(frames, frame_ids=[frames.frame_ids[i] for i in idx], images=images, human_masks=human,
                   object_masks=obj, cameras=CameraTrack(K=K, world_to_camera=frames.cameras.world_to_camera[idx]),
                   fits=fits, body_R=pick(frames.body_R), body_c=pick(frames.body_c), split=split_rule(len(idx)),
                   source=source)


def write_scene(frames: ImportedFrames, out: Path, body_model: str, smpl_model: Path | None,
                overwrite: bool = False) -> Path:
    """Convert the body, guess what is missing (points, object pose) and save the scene:
    into a temporary folder, put in place as `out` once `cogs check` accepts it (an existing
    `out` is replaced only with `overwrite`)."""
    if body_model == "smpl":
        body, body_info = smpl_body_track(frames.fits, frames.body_R, frames.body_c, smpl_model)
    elif body_model == "anny":
        body, body_info = anny_body_track(frames.fits, frames.body_R, frames.body_c)
    else:
        raise UserError(f"unknown body model {body_model!r} (anny or smpl)")
    source = dict(frames.source)
    source["body"] = {"model": body_model, **body_info}
    world_joints = smpl_joints_in_world(frames.fits, frames.body_R, frames.body_c) if frames.fits.joints is not None else None
    if world_joints is None and (frames.points_xyz is None or frames.object_masks is not None):
        world_joints = _joints_from_track(body, smpl_model)
    obj = None
    human = frames.human_masks
    if frames.object_masks is not None:
        # A pixel both masks claim is the object's: a held object covers the hand, and
        # HOSNeRF-style human masks include the object.
        human = human & ~frames.object_masks
        obj = object_track_from_masks(frames.object_masks, frames.cameras, world_joints[:, [22, 23]])
        source["object_pose"] = "initial guess: object-mask centroid at the nearest hand's depth, identity rotation"
    if frames.points_xyz is None:
        dynamic = human if frames.object_masks is None else human | frames.object_masks
        xyz, rgb, how = ground_plane_points(frames.images, dynamic, frames.cameras, world_joints)
        source["points"] = how
    else:
        xyz, rgb = frames.points_xyz, frames.points_rgb
    if len(xyz) == 0:
        raise UserError(f"{source.get('path', frames.name)}: no sparse points to initialise the static scene")
    T, H, W = human.shape
    scene = Scene(
        root=None, name=frames.name, width=W, height=H, fps=frames.fps, frame_ids=frames.frame_ids,
        split=frames.split, cameras=frames.cameras, body=body, object=obj,
        points_xyz=np.asarray(xyz, np.float32), points_rgb=np.asarray(rgb, np.uint8), source=source,
    )
    scene.set_pixels(frames.images, human, frames.object_masks)
    out = Path(out)
    check_out_folder(out, overwrite=overwrite)
    with staged(out, accept=_accept_imported) as st:
        save_scene(scene, st.path)
    scene.root = out
    if st.replaced:
        log.info("replaced %s in %s", st.replaced, out)
    log.info("wrote %s: %d frames %dx%d, train/test %d/%d, body %s",
             out, T, W, H, len(frames.split["train"]), len(frames.split["test"]), body.model)
    return out


def _accept_imported(folder: Path) -> None:
    from cogs.data.validate import check_scene

    problems = check_scene(folder)
    if problems:
        lines = "\n".join(f"  - {p}" for p in problems[:20])
        raise UserError(f"the imported scene fails cogs check, so it was not written ({len(problems)} problem(s)):\n{lines}")


def _joints_from_track(body: BodyTrack, smpl_model: Path | None) -> np.ndarray:
    """SMPL-order world joints [T, 24, 3] of a converted body track."""
    from cogs.body import load_body_model
    from cogs.body.retarget import anny_bone_indices

    if body.model == "smpl":
        from cogs.body.smpl_body import SmplBody

        model = SmplBody(smpl_model)
    else:
        model = load_body_model(body.model)
    with torch.no_grad():
        _, J = model.bone_transforms(torch.from_numpy(body.pose).float(), torch.from_numpy(body.transl).float(),
                                     torch.from_numpy(body.shape).float())
    J = J.double().numpy()
    return J if body.model == "smpl" else J[:, anny_bone_indices(model)]


def camera_centres(cameras: CameraTrack) -> np.ndarray:
    return camera_center(cameras.world_to_camera)
