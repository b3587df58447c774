"""The native scene format: every dataset enters cogs through it.

A scene is a folder (documented in docs/scene-format.md):

    scene.json            metadata, frame ids, split, body-model name
    images/<id>.png       RGB frames
    masks/human/<id>.png  human masks (0/255)
    masks/object/<id>.png object masks (0/255), when the scene has an object
    cameras.json          per-frame K [3x3] and world_to_camera [4x4] (OpenCV, metres)
    body.npz              body-model shape [S], per-frame pose [T, J, 3] (axis-angle), transl [T, 3]
    object.json           object centre c [3] and per-frame pose (quat_wxyz, translation):
                          x_world = R(q) (x_canonical - c) + t; optionally a per-frame
                          mask confidence in [0, 1] (absent: every frame trusted)
    points.ply            sparse coloured points of the static scene
    planes.json           optional planar primitives
    gt/                   optional ground truth (synthetic scenes), same formats

`load_scene` validates first (see `cogs.data.validate`) and raises `SceneError` listing
every problem; `save_scene` writes a complete folder.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cogs.data.io import (
    read_image,
    read_json,
    read_mask,
    read_points_ply,
    write_image,
    write_json,
    write_mask,
    write_points_ply,
)
from cogs.data.validate import FORMAT, VERSION, check_scene
from cogs.errors import UserError
from cogs.geometry.camera import Camera


class SceneError(UserError):
    """A scene folder that cannot be used; `problems` lists each one."""

    def __init__(self, root, problems):
        self.root = Path(root)
        self.problems = list(problems)
        lines = "\n".join(f"  - {p}" for p in self.problems)
        super().__init__(f"scene {self.root} has {len(self.problems)} problem(s):\n{lines}")


@dataclass
class CameraTrack:
    K: np.ndarray  # [T, 3, 3] float64, pixels
    world_to_camera: np.ndarray  # [T, 4, 4] float64

    def __len__(self) -> int:
        return len(self.K)

    def to_json(self, frame_ids: list[str]) -> dict:
        return {
            "frames": [
                {"id": fid, "K": self.K[i].tolist(), "world_to_camera": self.world_to_camera[i].tolist()}
                for i, fid in enumerate(frame_ids)
            ]
        }

    @classmethod
    def from_json(cls, obj: dict) -> "CameraTrack":
        frames = obj["frames"]
        return cls(
            K=np.array([f["K"] for f in frames], dtype=np.float64).reshape(-1, 3, 3),
            world_to_camera=np.array([f["world_to_camera"] for f in frames], dtype=np.float64).reshape(-1, 4, 4),
        )


@dataclass
class BodyTrack:
    model: str  # registry name, e.g. "anny"
    shape: np.ndarray  # [S]
    pose: np.ndarray  # [T, J, 3] axis-angle, radians
    transl: np.ndarray  # [T, 3] metres

    def __len__(self) -> int:
        return len(self.pose)

    def save(self, path: Path) -> None:
        np.savez_compressed(
            path,
            model=np.array(self.model),
            shape=self.shape.astype(np.float32),
            pose=self.pose.astype(np.float32),
            transl=self.transl.astype(np.float32),
        )

    @classmethod
    def load(cls, path: Path) -> "BodyTrack":
        with np.load(path, allow_pickle=False) as z:
            return cls(model=str(z["model"]), shape=z["shape"].astype(np.float32), pose=z["pose"].astype(np.float32),
                       transl=z["transl"].astype(np.float32))


@dataclass
class ObjectTrack:
    centre: np.ndarray  # [3] rotation pivot c, canonical coordinates
    quats: np.ndarray  # [T, 4] wxyz
    translations: np.ndarray  # [T, 3] world position of the centre
    confidence: np.ndarray | None = None
    """[T] in [0, 1]: how far each frame's object mask can be trusted (0 = the object was
    lost there); None = every frame fully trusted (scenes written before it existed)."""

    def __len__(self) -> int:
        return len(self.quats)

    def to_json(self, frame_ids: list[str]) -> dict:
        frames = [{"id": fid, "quat_wxyz": self.quats[i].tolist(), "translation": self.translations[i].tolist()}
                  for i, fid in enumerate(frame_ids)]
        if self.confidence is not None:
            assert len(self.confidence) == len(frame_ids) and np.isfinite(self.confidence).all()
            for f, c in zip(frames, self.confidence):
                f["confidence"] = float(c)
        return {
            "centre": self.centre.tolist(),
            "convention": "x_world = R(quat_wxyz) (x_canonical - centre) + translation",
            "frames": frames,
        }

    @classmethod
    def from_json(cls, obj: dict) -> "ObjectTrack":
        frames = obj["frames"]
        has_conf = bool(frames) and all("confidence" in f for f in frames)  # all or none (the check says so)
        return cls(
            centre=np.array(obj["centre"], dtype=np.float64).reshape(3),
            quats=np.array([f["quat_wxyz"] for f in frames], dtype=np.float64).reshape(-1, 4),
            translations=np.array([f["translation"] for f in frames], dtype=np.float64).reshape(-1, 3),
            confidence=np.array([f["confidence"] for f in frames], dtype=np.float64) if has_conf else None,
        )

    def rotation_matrices(self) -> np.ndarray:
        import torch

        from cogs.geometry.rotations import quat_to_rotmat

        return quat_to_rotmat(torch.from_numpy(self.quats)).numpy()

    def transform(self, t: int, points: np.ndarray) -> np.ndarray:
        """Canonical points [N, 3] -> world at frame t."""
        R = self.rotation_matrices()[t]
        return (points - self.centre) @ R.T + self.translations[t]


@dataclass
class PlaneSpec:
    normal: np.ndarray  # [3] unit
    offset: float  # n . x + offset = 0
    label: str = ""


@dataclass
class NovelViews:
    """Ground-truth renders from cameras off the training path (synthetic scenes)."""

    frames: np.ndarray  # [V] frame index whose body/object state is shown
    cameras: CameraTrack  # [V]
    images: np.ndarray  # [V, H, W, 3] uint8
    human_masks: np.ndarray  # [V, H, W] bool
    object_masks: np.ndarray  # [V, H, W] bool
    depth: np.ndarray  # [V, H, W] float32, 0 = background


@dataclass
class GroundTruth:
    cameras: CameraTrack
    body: BodyTrack
    object: ObjectTrack | None
    human_masks: np.ndarray  # [T, H, W] bool
    object_masks: np.ndarray | None  # [T, H, W] bool
    depth: np.ndarray  # [T, H, W] float32 metres, 0 where nothing was hit
    planes: list[PlaneSpec] = field(default_factory=list)
    novel: NovelViews | None = None


@dataclass
class Scene:
    root: Path | None
    name: str
    width: int
    height: int
    fps: float
    frame_ids: list[str]
    split: dict[str, list[int]]
    cameras: CameraTrack
    body: BodyTrack
    object: ObjectTrack | None
    points_xyz: np.ndarray  # [P, 3] float32
    points_rgb: np.ndarray  # [P, 3] uint8
    planes: list[PlaneSpec] | None = None
    gt: GroundTruth | None = None
    source: dict = field(default_factory=dict)
    # In-memory pixels; filled lazily from `root` when None.
    _images: np.ndarray | None = None  # [T, H, W, 3] uint8
    _human_masks: np.ndarray | None = None  # [T, H, W] bool
    _object_masks: np.ndarray | None = None
    full_size: tuple[int, int] | None = None
    """(width, height) of the files on disk when the scene was loaded at a reduced size
    (`load_scene(max_side=...)`): frames are resized as they are read; None: as on disk."""

    # -- frames ----------------------------------------------------------------------
    @property
    def n_frames(self) -> int:
        return len(self.frame_ids)

    @property
    def has_object(self) -> bool:
        return self.object is not None

    @property
    def object_confidence(self) -> np.ndarray:
        """[T] float64 in [0, 1]: the object masks' per-frame confidence (object.json);
        ones when the scene records none, or has no object."""
        c = None if self.object is None else self.object.confidence
        return np.ones(self.n_frames) if c is None else np.asarray(c, dtype=np.float64)

    def object_trusted(self, min_confidence: float) -> np.ndarray:
        """[T] bool: frames whose object mask may supervise the object branch (confidence
        at least `min_confidence`)."""
        return self.object_confidence >= min_confidence

    def camera(self, t: int) -> Camera:
        return Camera(self.cameras.K[t], self.cameras.world_to_camera[t], self.width, self.height)

    def image_path(self, t: int) -> Path:
        return self.root / "images" / f"{self.frame_ids[t]}.png"

    def mask_path(self, kind: str, t: int) -> Path:
        return self.root / "masks" / kind / f"{self.frame_ids[t]}.png"

    @property
    def images(self) -> np.ndarray:
        """[T, H, W, 3] uint8, loaded once (frame by frame into one array)."""
        if self._images is None:
            self._images = _read_all([self.image_path(t) for t in range(self.n_frames)], read_image,
                                     (self.height, self.width, 3), np.uint8, self._resize_image)
        return self._images

    @property
    def human_masks(self) -> np.ndarray:
        if self._human_masks is None:
            self._human_masks = _read_all([self.mask_path("human", t) for t in range(self.n_frames)], read_mask,
                                          (self.height, self.width), bool, self._resize_mask)
        return self._human_masks

    @property
    def object_masks(self) -> np.ndarray:
        """[T, H, W] bool; all False when the scene has no object."""
        if self._object_masks is None:
            if not self.has_object:
                self._object_masks = np.zeros((self.n_frames, self.height, self.width), dtype=bool)
            else:
                self._object_masks = _read_all([self.mask_path("object", t) for t in range(self.n_frames)], read_mask,
                                               (self.height, self.width), bool, self._resize_mask)
        return self._object_masks

    def _resize_image(self, a: np.ndarray) -> np.ndarray:
        return a if self.full_size is None else resize_image(a, self.width, self.height)

    def _resize_mask(self, a: np.ndarray) -> np.ndarray:
        return a if self.full_size is None else resize_mask(a, self.width, self.height)

    def set_pixels(self, images: np.ndarray, human_masks: np.ndarray, object_masks: np.ndarray | None) -> None:
        self._images, self._human_masks, self._object_masks = images, human_masks, object_masks

    def metadata(self) -> dict:
        return {
            "format": FORMAT,
            "version": VERSION,
            "name": self.name,
            "width": int(self.width),
            "height": int(self.height),
            "fps": float(self.fps),
            "frames": list(self.frame_ids),
            "split": {k: [int(i) for i in v] for k, v in self.split.items()},
            "body_model": self.body.model,
            "has_object": self.has_object,
            "has_planes": self.planes is not None,
            "has_ground_truth": self.gt is not None,
            "source": self.source,
        }


def _read_all(paths: list[Path], read, shape: tuple, dtype, resize) -> np.ndarray:
    """Every file into one preallocated array (no second copy of the clip while stacking)."""
    out = np.empty((len(paths), *shape), dtype)
    for t, p in enumerate(paths):
        out[t] = resize(read(p))
    return out


def resize_image(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """[H, W, 3] uint8 to width x height by pixel-area averaging."""
    import cv2

    return cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)


def resize_mask(mask: np.ndarray, width: int, height: int) -> np.ndarray:
    """[H, W] bool to width x height: inside where most of the new pixel's area was."""
    import cv2

    return cv2.resize(mask.astype(np.float32), (width, height), interpolation=cv2.INTER_AREA) > 0.5


def reduced_size(width: int, height: int, max_side: int | None) -> tuple[int, int]:
    """(width, height) scaled so the longer side is at most `max_side` (unchanged when it
    already is, or when max_side is None)."""
    if max_side is None or max(width, height) <= max_side:
        return width, height
    s = max_side / max(width, height)
    return max(1, round(width * s)), max(1, round(height * s))


def scale_intrinsics(K: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """K [..., 3, 3] for an image resized by (sx, sy): pixel centres sit at i + 0.5 (the
    rasterizer's convention), so focal lengths and principal point scale alike."""
    K = np.array(K, dtype=np.float64, copy=True)
    K[..., 0, :] *= sx
    K[..., 1, :] *= sy
    return K


def default_frame_ids(n: int) -> list[str]:
    return [f"{i:06d}" for i in range(n)]


# -- saving ---------------------------------------------------------------------------


def _planes_json(planes: list[PlaneSpec]) -> dict:
    return {"planes": [{"normal": p.normal.tolist(), "offset": float(p.offset), "label": p.label} for p in planes]}


def _planes_from_json(obj: dict) -> list[PlaneSpec]:
    return [
        PlaneSpec(np.array(p["normal"], dtype=np.float64), float(p["offset"]), p.get("label", ""))
        for p in obj["planes"]
    ]


def save_scene(scene: Scene, root: str | Path) -> Path:
    """Write every file of `scene` under `root` (pixels must be loaded or set)."""
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    ids = scene.frame_ids
    images, hmasks = scene.images, scene.human_masks
    omasks = scene.object_masks if scene.has_object else None
    for t, fid in enumerate(ids):
        write_image(root / "images" / f"{fid}.png", images[t])
        write_mask(root / "masks" / "human" / f"{fid}.png", hmasks[t])
        if omasks is not None:
            write_mask(root / "masks" / "object" / f"{fid}.png", omasks[t])
    write_json(root / "cameras.json", scene.cameras.to_json(ids))
    scene.body.save(root / "body.npz")
    if scene.object is not None:
        write_json(root / "object.json", scene.object.to_json(ids))
    write_points_ply(root / "points.ply", scene.points_xyz, scene.points_rgb)
    if scene.planes is not None:
        write_json(root / "planes.json", _planes_json(scene.planes))
    if scene.gt is not None:
        _save_gt(scene.gt, root / "gt", ids)
    write_json(root / "scene.json", scene.metadata())  # last: its presence marks a complete scene
    scene.root = root
    return root


def _save_gt(gt: GroundTruth, root: Path, ids: list[str]) -> None:
    write_json(root / "cameras.json", gt.cameras.to_json(ids))
    gt.body.save(root / "body.npz")
    if gt.object is not None:
        write_json(root / "object.json", gt.object.to_json(ids))
    for t, fid in enumerate(ids):
        write_mask(root / "masks" / "human" / f"{fid}.png", gt.human_masks[t])
        if gt.object_masks is not None:
            write_mask(root / "masks" / "object" / f"{fid}.png", gt.object_masks[t])
    np.savez_compressed(root / "depth.npz", depth=gt.depth.astype(np.float16))
    write_json(root / "planes.json", _planes_json(gt.planes))
    if gt.novel is not None:
        nv = gt.novel
        vids = [f"v{i:03d}" for i in range(len(nv.frames))]
        cams = nv.cameras.to_json(vids)
        for i, f in enumerate(cams["frames"]):
            f["frame"] = int(nv.frames[i])
        write_json(root / "novel" / "cameras.json", cams)
        for i, vid in enumerate(vids):
            write_image(root / "novel" / "images" / f"{vid}.png", nv.images[i])
            write_mask(root / "novel" / "masks" / "human" / f"{vid}.png", nv.human_masks[i])
            write_mask(root / "novel" / "masks" / "object" / f"{vid}.png", nv.object_masks[i])
        np.savez_compressed(root / "novel" / "depth.npz", depth=nv.depth.astype(np.float16))


# -- loading --------------------------------------------------------------------------


def load_scene(root: str | Path, validate: bool = True, ground_truth: bool = True,
               max_side: int | None = None) -> Scene:
    """Load a scene folder; with `validate`, raise SceneError listing every problem.

    `ground_truth=False` leaves gt/ unread (training never looks at it); `max_side` loads
    the scene at a reduced size (the longer side at most that many pixels): every frame,
    mask and ground-truth map is resized as it is read and the intrinsics are scaled."""
    root = Path(root)
    if validate:

        problems = check_scene(root)
        if problems:
            raise SceneError(root, problems)
    meta = read_json(root / "scene.json")
    ids = list(meta["frames"])
    cameras = CameraTrack.from_json(read_json(root / "cameras.json"))
    body = BodyTrack.load(root / "body.npz")
    obj = ObjectTrack.from_json(read_json(root / "object.json")) if meta.get("has_object", False) else None
    xyz, rgb = read_points_ply(root / "points.ply")
    planes = _planes_from_json(read_json(root / "planes.json")) if (root / "planes.json").exists() else None
    W, H = int(meta["width"]), int(meta["height"])
    w, h = reduced_size(W, H, max_side)
    size = None if (w, h) == (W, H) else (w, h)
    gt = None
    if ground_truth and (root / "gt" / "cameras.json").exists():
        gt = _load_gt(root / "gt", ids, meta.get("has_object", False), size)
    if size is not None:
        cameras = CameraTrack(K=scale_intrinsics(cameras.K, w / W, h / H), world_to_camera=cameras.world_to_camera)
    return Scene(
        root=root,
        name=meta.get("name", root.name),
        width=w,
        height=h,
        fps=float(meta.get("fps", 10.0)),
        frame_ids=ids,
        split={k: list(v) for k, v in meta["split"].items()},
        cameras=cameras,
        body=body,
        object=obj,
        points_xyz=xyz,
        points_rgb=rgb,
        planes=planes,
        gt=gt,
        source=meta.get("source", {}),
        full_size=None if size is None else (W, H),
    )


def _load_gt(root: Path, ids: list[str], has_object: bool, size: tuple[int, int] | None = None) -> GroundTruth:
    """The ground truth; at `size` (width, height) when given, resized as it is read."""
    import cv2

    def fit_mask(a: np.ndarray) -> np.ndarray:
        return a if size is None else resize_mask(a, *size)

    def read_depth(path: Path) -> tuple[np.ndarray, int, int]:
        """Depth maps [N, h, w] at the loading size, and the (width, height) of the file's."""
        with np.load(path, allow_pickle=False) as z:
            d = z["depth"].astype(np.float32)
        H, W = d.shape[1:3]
        if size is not None:  # nearest: no depth between a surface and what is behind it
            d = np.stack([cv2.resize(x, size, interpolation=cv2.INTER_NEAREST) for x in d])
        return d, W, H

    def masks(kind: str, names: list[str], base: Path, shape: tuple[int, int]) -> np.ndarray:
        return _read_all([base / "masks" / kind / f"{n}.png" for n in names], read_mask, shape, bool, fit_mask)

    def scaled(track: CameraTrack, W: int, H: int) -> CameraTrack:
        if size is None:
            return track
        return CameraTrack(K=scale_intrinsics(track.K, size[0] / W, size[1] / H), world_to_camera=track.world_to_camera)

    depth, depth_full_w, depth_full_h = read_depth(root / "depth.npz")
    novel = None
    if (root / "novel" / "cameras.json").exists():
        cams_json = read_json(root / "novel" / "cameras.json")
        vids = [f["id"] for f in cams_json["frames"]]
        ndepth, full_w, full_h = read_depth(root / "novel" / "depth.npz")
        shape = ndepth.shape[1:3]
        img_paths = [root / "novel" / "images" / f"{v}.png" for v in vids]
        novel = NovelViews(
            frames=np.array([f["frame"] for f in cams_json["frames"]], dtype=np.int64),
            cameras=scaled(CameraTrack.from_json(cams_json), full_w, full_h),
            images=_read_all(img_paths, read_image, (*shape, 3), np.uint8,
                             (lambda a: a) if size is None else (lambda a: resize_image(a, *size))),
            human_masks=masks("human", vids, root / "novel", shape),
            object_masks=masks("object", vids, root / "novel", shape),
            depth=ndepth,
        )
    return GroundTruth(
        cameras=scaled(CameraTrack.from_json(read_json(root / "cameras.json")), depth_full_w, depth_full_h),
        body=BodyTrack.load(root / "body.npz"),
        object=ObjectTrack.from_json(read_json(root / "object.json")) if has_object else None,
        human_masks=masks("human", ids, root, depth.shape[1:3]),
        object_masks=masks("object", ids, root, depth.shape[1:3]) if has_object else None,
        depth=depth,
        planes=_planes_from_json(read_json(root / "planes.json")) if (root / "planes.json").exists() else [],
        novel=novel,
    )
