"""Scene validation: find every problem in a scene folder at once, never raise.

Each problem names the file (relative to the scene root) and, where it applies, the
frame. `cogs check --scene DIR` prints them and exits non-zero when there are any;
`load_scene` refuses a scene with problems.
"""

from __future__ import annotations

import json
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from cogs.body import MODELS


@dataclass(frozen=True)
class Problem:
    file: str
    message: str
    frame: str | None = None

    def __str__(self) -> str:
        where = self.file if self.frame is None else f"{self.file} (frame {self.frame})"
        return f"{where}: {self.message}"


class _Report:
    def __init__(self, root: Path):
        self.root = root
        self.problems: list[Problem] = []

    def add(self, path: Path | str, message: str, frame: str | None = None) -> None:
        path = Path(path)
        rel = path.relative_to(self.root) if path.is_relative_to(self.root) and path != self.root else path
        self.problems.append(Problem(str(rel), message, frame))


def check_scene(root: str | Path) -> list[Problem]:
    """All problems found in the scene folder `root` (empty list = valid)."""
    root = Path(root)
    rep = _Report(root)
    if not root.is_dir():
        rep.add(root, "scene folder does not exist" if not root.exists() else "not a folder")
        return rep.problems

    meta = _check_meta(root, rep)
    ids: list[str] = meta.get("frames") or _infer_frame_ids(root)
    width, height = meta.get("width"), meta.get("height")
    if (width is None or height is None) and ids:
        size = _image_size(root / "images" / f"{ids[0]}.png")
        if size:
            width, height = size
    has_object = bool(meta.get("has_object", (root / "object.json").exists()))
    model = meta.get("body_model")

    _check_images(root, rep, ids, width, height)
    _check_masks(root, rep, ids, width, height, "human")
    if has_object:
        _check_masks(root, rep, ids, width, height, "object")
    _check_cameras(root / "cameras.json", rep, ids, width, height)
    _check_body(root / "body.npz", rep, ids, model)
    if has_object:
        _check_object(root / "object.json", rep, ids)
    _check_points(root / "points.ply", rep)
    if (root / "planes.json").exists():
        _check_planes(root / "planes.json", rep)
    if (root / "gt").is_dir():
        _check_ground_truth(root / "gt", rep, ids, width, height, has_object, model)
    return rep.problems


# -- scene.json -----------------------------------------------------------------------


def _check_meta(root: Path, rep: _Report) -> dict:
    path = root / "scene.json"
    if not path.exists():
        rep.add(path, "missing (every scene needs its metadata file)")
        return {}
    try:
        meta = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        rep.add(path, f"not valid JSON: {e}")
        return {}
    if not isinstance(meta, dict):
        rep.add(path, "must hold a JSON object")
        return {}
    out: dict = {}
    for key in ("width", "height"):
        v = meta.get(key)
        if not isinstance(v, int) or isinstance(v, bool) or v <= 0:
            rep.add(path, f"`{key}` must be a positive integer, got {v!r}")
        else:
            out[key] = v
    frames = meta.get("frames")
    if not isinstance(frames, list) or not frames or not all(isinstance(f, str) and f for f in frames):
        rep.add(path, "`frames` must be a non-empty list of frame ids (strings)")
    elif len(set(frames)) != len(frames):
        rep.add(path, "`frames` holds duplicate ids")
    else:
        out["frames"] = frames
    model = meta.get("body_model")
    if model not in MODELS:
        rep.add(path, f"unknown body model {model!r}; known: {', '.join(sorted(MODELS))}")
    else:
        out["body_model"] = model
    if "has_object" in meta:
        if not isinstance(meta["has_object"], bool):
            rep.add(path, "`has_object` must be true or false")
        else:
            out["has_object"] = meta["has_object"]
    n = len(out.get("frames", []))
    split = meta.get("split")
    if not isinstance(split, dict) or "train" not in split or "test" not in split:
        rep.add(path, "`split` must be an object with `train` and `test` frame-index lists")
    else:
        seen: dict[int, str] = {}
        for part in ("train", "test"):
            idx = split[part]
            if not isinstance(idx, list) or not all(isinstance(i, int) and not isinstance(i, bool) for i in idx):
                rep.add(path, f"`split.{part}` must be a list of integer frame indices")
                continue
            bad = [i for i in idx if n and not 0 <= i < n]
            if bad:
                rep.add(path, f"`split.{part}` has indices outside 0..{n - 1}: {bad[:5]}")
            both = [i for i in idx if i in seen and seen[i] != part]
            if both:
                rep.add(path, f"frames {both[:5]} are in both train and test")
            seen.update({i: part for i in idx})
        if isinstance(split.get("train"), list) and not split["train"]:
            rep.add(path, "`split.train` is empty: nothing to train on")
    return out


def _infer_frame_ids(root: Path) -> list[str]:
    return sorted(p.stem for p in (root / "images").glob("*.png")) if (root / "images").is_dir() else []


def _image_size(path: Path) -> tuple[int, int] | None:
    try:
        with Image.open(path) as im:
            return im.size
    except Exception:
        return None


# -- pixels ---------------------------------------------------------------------------


def _open_png(path: Path, rep: _Report, fid: str) -> np.ndarray | None:
    if not path.exists():
        rep.add(path, "missing", fid)
        return None
    try:
        with Image.open(path) as im:
            im.load()
            return np.asarray(im)
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as e:
        rep.add(path, f"corrupt or unreadable image ({type(e).__name__}: {e})", fid)
        return None


def _check_size(path: Path, rep: _Report, fid: str, arr: np.ndarray, width, height) -> None:
    h, w = arr.shape[:2]
    if width is not None and height is not None and (w, h) != (width, height):
        rep.add(path, f"image is {w}x{h}, expected {width}x{height}", fid)


def _check_images(root: Path, rep: _Report, ids, width, height) -> None:
    if ids and not (root / "images").is_dir():
        rep.add(root / "images", "folder missing")
        return
    for fid in ids:
        path = root / "images" / f"{fid}.png"
        arr = _open_png(path, rep, fid)
        if arr is None:
            continue
        _check_size(path, rep, fid, arr, width, height)
        if arr.ndim == 3 and arr.shape[2] not in (3, 4):
            rep.add(path, f"expected RGB(A), got {arr.shape[2]} channels", fid)


def _check_masks(root: Path, rep: _Report, ids, width, height, kind: str) -> None:
    folder = root / "masks" / kind
    if ids and not folder.is_dir():
        rep.add(folder, f"folder missing (one {kind} mask per frame expected)")
        return
    for fid in ids:
        path = folder / f"{fid}.png"
        arr = _open_png(path, rep, fid)
        if arr is None:
            continue
        _check_size(path, rep, fid, arr, width, height)
        if arr.ndim == 3:
            if arr.shape[2] >= 3 and not (np.array_equal(arr[..., 0], arr[..., 1]) and np.array_equal(arr[..., 0], arr[..., 2])):
                rep.add(path, "mask has colour; expected a single-channel 0/255 image", fid)
                continue
            arr = arr[..., 0]
        values = np.unique(arr)
        if arr.dtype == bool or set(values.tolist()) <= {0, 255} or set(values.tolist()) <= {0, 1}:
            continue
        rep.add(path, f"mask is not binary: {len(values)} distinct values (expected only 0 and 255)", fid)


# -- arrays ---------------------------------------------------------------------------


def _load_json(path: Path, rep: _Report):
    if not path.exists():
        rep.add(path, "missing")
        return None
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        rep.add(path, f"not valid JSON: {e}")
        return None


def _as_array(value, shape: tuple[int, ...]) -> np.ndarray | None:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        return None
    return arr if arr.shape == shape else None


def _frames_list(obj, path: Path, rep: _Report, ids) -> list | None:
    frames = obj.get("frames") if isinstance(obj, dict) else None
    if not isinstance(frames, list):
        rep.add(path, "must hold an object with a `frames` list")
        return None
    if ids and len(frames) != len(ids):
        rep.add(path, f"has {len(frames)} frames but the scene has {len(ids)} images")
    return frames


def _check_cameras(path: Path, rep: _Report, ids, width, height) -> None:
    obj = _load_json(path, rep)
    if obj is None:
        return
    frames = _frames_list(obj, path, rep, ids)
    for i, f in enumerate(frames or []):
        fid = ids[i] if i < len(ids) else str(i)
        if not isinstance(f, dict):
            rep.add(path, "camera entry must be an object", fid)
            continue
        K = _as_array(f.get("K"), (3, 3))
        if K is None:
            rep.add(path, "`K` must be a 3x3 matrix", fid)
        elif not np.isfinite(K).all():
            rep.add(path, "`K` has non-finite numbers", fid)
        elif K[0, 0] <= 0 or K[1, 1] <= 0:
            rep.add(path, f"focal lengths must be positive, got fx={K[0, 0]:g}, fy={K[1, 1]:g}", fid)
        T = _as_array(f.get("world_to_camera"), (4, 4))
        if T is None:
            rep.add(path, "`world_to_camera` must be a 4x4 matrix", fid)
        elif not np.isfinite(T).all():
            rep.add(path, "`world_to_camera` has non-finite numbers", fid)
        else:
            R = T[:3, :3]
            if np.abs(R @ R.T - np.eye(3)).max() > 1e-3 or np.linalg.det(R) < 0:
                rep.add(path, "`world_to_camera` rotation block is not a rotation", fid)
            if np.abs(T[3] - [0, 0, 0, 1]).max() > 1e-9:
                rep.add(path, "`world_to_camera` last row must be [0, 0, 0, 1]", fid)


def _nonfinite_frames(arr: np.ndarray, ids) -> list[str]:
    bad = ~np.isfinite(arr.reshape(len(arr), -1)).all(axis=1)
    return [ids[i] if i < len(ids) else str(i) for i in np.flatnonzero(bad)]


def _check_body(path: Path, rep: _Report, ids, model_in_meta) -> None:
    if not path.exists():
        rep.add(path, "missing (per-frame body-model poses are required)")
        return
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as e:
        rep.add(path, f"unreadable npz ({type(e).__name__}: {e})")
        return
    missing = [k for k in ("model", "shape", "pose", "transl") if k not in data]
    if missing:
        rep.add(path, f"missing arrays: {', '.join(missing)}")
        return
    model = str(data["model"])
    if model not in MODELS:
        rep.add(path, f"unknown body model {model!r}; known: {', '.join(sorted(MODELS))}")
        return
    if model_in_meta is not None and model != model_in_meta:
        rep.add(path, f"body model {model!r} differs from scene.json's {model_in_meta!r}")
    info = MODELS[model]
    T = len(ids)
    pose, transl, shape = data["pose"], data["transl"], data["shape"]
    if pose.ndim != 3 or pose.shape[1:] != (info.n_bones, 3):
        rep.add(path, f"`pose` must be [T, {info.n_bones}, 3] for {model}, got {list(pose.shape)}")
    elif T and len(pose) != T:
        rep.add(path, f"`pose` has {len(pose)} frames but the scene has {T} images")
    else:
        for fid in _nonfinite_frames(pose, ids):
            rep.add(path, "`pose` has non-finite numbers", fid)
    if transl.ndim != 2 or transl.shape[1] != 3:
        rep.add(path, f"`transl` must be [T, 3], got {list(transl.shape)}")
    elif T and len(transl) != T:
        rep.add(path, f"`transl` has {len(transl)} frames but the scene has {T} images")
    else:
        for fid in _nonfinite_frames(transl, ids):
            rep.add(path, "`transl` has non-finite numbers", fid)
    if shape.shape != (info.n_shape,):
        rep.add(path, f"`shape` must have {info.n_shape} values for {model}, got {list(shape.shape)}")
    elif not np.isfinite(shape).all():
        rep.add(path, "`shape` has non-finite numbers")


def _check_object(path: Path, rep: _Report, ids) -> None:
    obj = _load_json(path, rep)
    if obj is None:
        return
    c = _as_array(obj.get("centre") if isinstance(obj, dict) else None, (3,))
    if c is None or not np.isfinite(c).all():
        rep.add(path, "`centre` must be 3 finite numbers")
    frames = _frames_list(obj, path, rep, ids)
    for i, f in enumerate(frames or []):
        fid = ids[i] if i < len(ids) else str(i)
        q = _as_array(f.get("quat_wxyz") if isinstance(f, dict) else None, (4,))
        t = _as_array(f.get("translation") if isinstance(f, dict) else None, (3,))
        if q is None:
            rep.add(path, "`quat_wxyz` must be 4 numbers", fid)
        elif not np.isfinite(q).all():
            rep.add(path, "`quat_wxyz` has non-finite numbers", fid)
        elif np.linalg.norm(q) < 1e-6:
            rep.add(path, "`quat_wxyz` is zero (no rotation)", fid)
        if t is None:
            rep.add(path, "`translation` must be 3 numbers", fid)
        elif not np.isfinite(t).all():
            rep.add(path, "`translation` has non-finite numbers", fid)


def _check_points(path: Path, rep: _Report) -> None:
    if not path.exists():
        rep.add(path, "missing (sparse points initialise the static scene)")
        return
    try:
        from cogs.data.io import read_points_ply

        xyz, _ = read_points_ply(path)
    except Exception as e:  # plyfile raises several unrelated types on bad files
        rep.add(path, f"unreadable PLY ({type(e).__name__}: {e})")
        return
    if len(xyz) == 0:
        rep.add(path, "holds no points")
    bad = int((~np.isfinite(xyz).all(axis=1)).sum())
    if bad:
        rep.add(path, f"{bad} points have non-finite coordinates")


def _check_planes(path: Path, rep: _Report) -> None:
    obj = _load_json(path, rep)
    if obj is None:
        return
    planes = obj.get("planes") if isinstance(obj, dict) else None
    if not isinstance(planes, list):
        rep.add(path, "must hold an object with a `planes` list")
        return
    for i, p in enumerate(planes):
        n = _as_array(p.get("normal") if isinstance(p, dict) else None, (3,))
        d = _as_array(p.get("offset") if isinstance(p, dict) else None, ())
        if n is None or d is None or not np.isfinite(n).all() or not np.isfinite(d).all():
            rep.add(path, f"plane {i}: needs a finite `normal` [3] and `offset`")
        elif abs(np.linalg.norm(n) - 1.0) > 1e-3:
            rep.add(path, f"plane {i}: normal is not unit length ({np.linalg.norm(n):.4f})")


def _check_ground_truth(root: Path, rep: _Report, ids, width, height, has_object, model) -> None:
    _check_cameras(root / "cameras.json", rep, ids, width, height)
    _check_body(root / "body.npz", rep, ids, model)
    if has_object:
        _check_object(root / "object.json", rep, ids)
        _check_masks(root, rep, ids, width, height, "object")
    _check_masks(root, rep, ids, width, height, "human")
    path = root / "depth.npz"
    if not path.exists():
        rep.add(path, "missing")
    else:
        try:
            with np.load(path, allow_pickle=False) as z:
                depth = z["depth"]
            if depth.shape != (len(ids), height, width):
                rep.add(path, f"depth must be [{len(ids)}, {height}, {width}], got {list(depth.shape)}")
            elif not np.isfinite(depth).all():
                rep.add(path, "depth has non-finite values")
        except Exception as e:
            rep.add(path, f"unreadable depth ({type(e).__name__}: {e})")
