"""Scene validation: find every problem in a scene folder at once, never raise.

Each problem names the file (relative to the scene root) and, where it applies, the
frame. `cogs check --scene DIR` prints them and exits non-zero when there are any;
`load_scene` refuses a scene with problems.

The check is total: every file `load_scene` reads (ground truth and novel views included)
is read here first, from its bytes, and whatever can be wrong with it — missing, a folder
or a pipe where a file belongs, a symbolic link loop, no permission, truncated, not the
format, wrong shape or dtype, non-numeric or non-finite values — becomes a listed problem,
never an exception. A scene with no problems therefore loads without surprises.
"""

from __future__ import annotations

import errno
import io
import json
import math
import os
import stat
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from cogs.body import MODELS
from cogs.data.io import mask_from_values, mask_values, read_points_ply

FORMAT = "cogs-scene"
VERSION = 1
"""The scene format's name and newest version (scene.json `format`, `version`)."""

_PIXEL_MODES = {"1", "L", "LA", "P", "PA", "RGB", "RGBA"}  # 8-bit (or 1-bit) images PIL converts losslessly


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
    issue = _folder_issue(root)
    if issue is not None:
        rep.add(root, "scene folder does not exist" if issue == "missing" else issue)
        return rep.problems

    meta = _check_meta(root, rep)
    ids: list[str] = meta.get("frames") or _infer_frame_ids(root)
    width, height = meta.get("width"), meta.get("height")
    if (width is None or height is None) and ids:
        size = _image_size(root / "images" / f"{ids[0]}.png")
        if size:
            width, height = size
    has_object = bool(meta.get("has_object", False))
    model = meta.get("body_model")

    _check_images(root, rep, ids, width, height)
    _check_masks(root, rep, ids, width, height, "human", person_somewhere=True)
    if has_object:
        _check_masks(root, rep, ids, width, height, "object")
    _check_cameras(root / "cameras.json", rep, ids, width, height)
    _check_body(root / "body.npz", rep, ids, model)
    if has_object:
        _check_object(root / "object.json", rep, ids)
    _check_points(root / "points.ply", rep)
    if _exists(root / "planes.json"):
        _check_planes(root / "planes.json", rep)
    if _exists(root / "gt"):
        issue = _folder_issue(root / "gt")
        if issue is not None:
            rep.add(root / "gt", f"{issue} (the optional ground truth is a folder)")
        else:
            _check_ground_truth(root / "gt", rep, ids, width, height, has_object, model)
    return rep.problems


# -- reading any file safely ----------------------------------------------------------


def _exists(path: Path) -> bool:
    """True when anything (even a broken link or a loop) sits at `path`."""
    try:
        os.lstat(path)
        return True
    except (OSError, ValueError):
        return False


def _stat_issue(path: Path) -> tuple[os.stat_result | None, str | None]:
    try:
        return os.stat(path), None
    except FileNotFoundError:
        return None, "a symbolic link to nothing" if os.path.islink(path) else "missing"
    except NotADirectoryError:
        return None, "missing (a file stands where one of its folders should be)"
    except PermissionError:
        return None, "cannot be reached (permission denied on a folder above it)"
    except OSError as e:
        if e.errno == errno.ELOOP:
            return None, "a symbolic link loop"
        return None, f"unreadable ({e.strerror or e})"
    except ValueError as e:  # a NUL byte in the name
        return None, f"not a usable file name ({e})"


def _file_issue(path: Path) -> str | None:
    """Why `path` cannot be read as a regular file, or None."""
    st, issue = _stat_issue(path)
    if issue is not None:
        return issue
    if stat.S_ISDIR(st.st_mode):
        return "is a folder, expected a file"
    if not stat.S_ISREG(st.st_mode):
        return "not a regular file (a pipe, socket or device?)"
    return None


def _folder_issue(path: Path) -> str | None:
    """Why `path` cannot be listed as a folder, or None."""
    st, issue = _stat_issue(path)
    if issue is not None:
        return issue
    if not stat.S_ISDIR(st.st_mode):
        return "not a folder"
    try:
        with os.scandir(path):
            pass
    except OSError as e:
        return f"folder cannot be read ({e.strerror or e})"
    return None


def _read_bytes(path: Path, rep: _Report, frame: str | None = None, missing: str = "missing") -> bytes | None:
    issue = _file_issue(path)
    if issue is None:
        try:
            with open(path, "rb") as f:
                return f.read()
        except OSError as e:
            issue = f"unreadable ({e.strerror or e})"
    rep.add(path, missing if issue == "missing" else issue, frame)
    return None


def _load_json(path: Path, rep: _Report, missing: str = "missing"):
    data = _read_bytes(path, rep, missing=missing)
    if data is None:
        return None
    try:
        return json.loads(data)
    except (ValueError, RecursionError) as e:  # JSONDecodeError and UnicodeDecodeError are ValueErrors
        rep.add(path, f"not valid JSON: {e}")
        return None


def _load_npz(path: Path, rep: _Report, missing: str = "missing") -> dict[str, np.ndarray] | None:
    data = _read_bytes(path, rep, missing=missing)
    if data is None:
        return None
    try:
        z = np.load(io.BytesIO(data), allow_pickle=False)
        if not isinstance(z, np.lib.npyio.NpzFile):
            rep.add(path, "not an .npz archive (a single array?); expected named arrays")
            return None
        with z:
            return {k: z[k] for k in z.files}
    except Exception as e:  # numpy and zipfile raise many unrelated types on damaged archives
        rep.add(path, f"unreadable npz ({type(e).__name__}: {e})")
        return None


def _numeric(arr: np.ndarray) -> bool:
    return arr.dtype.kind in "fiu"


# -- scene.json -----------------------------------------------------------------------


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def frame_id_issue(fid) -> str | None:
    """Why `fid` cannot name a frame's files (`images/<id>.png`), or None."""
    if not isinstance(fid, str) or not fid:
        return "frame ids must be non-empty strings"
    if any(c in fid for c in "/\\\0") or fid in (".", ".."):
        return f"frame id {fid!r} cannot be a file name (no '/', '\\', NUL, '.' or '..')"
    return None


def _check_meta(root: Path, rep: _Report) -> dict:
    path = root / "scene.json"
    meta = _load_json(path, rep, missing="missing (every scene needs its metadata file)")
    if meta is None:
        return {}
    if not isinstance(meta, dict):
        rep.add(path, "must hold a JSON object")
        return {}
    out: dict = {}
    if "format" in meta and meta["format"] != FORMAT:
        rep.add(path, f"`format` is {meta['format']!r}, expected {FORMAT!r}")
    if "version" in meta and (not _is_int(meta["version"]) or meta["version"] > VERSION or meta["version"] < 1):
        rep.add(path, f"`version` {meta['version']!r} is not one this cogs reads (1..{VERSION}); "
                      "was the scene written by a newer cogs?")
    for key in ("width", "height"):
        v = meta.get(key)
        if not _is_int(v) or v <= 0:
            rep.add(path, f"`{key}` must be a positive integer, got {v!r}")
        else:
            out[key] = v
    if "fps" in meta:
        fps = meta["fps"]
        if not _is_number(fps) or not math.isfinite(fps) or fps <= 0:
            rep.add(path, f"`fps` must be a positive number (frames per second), got {fps!r}")
    for key in ("name",):
        if key in meta and not isinstance(meta[key], str):
            rep.add(path, f"`{key}` must be a string, got {meta[key]!r}")
    if "source" in meta and not isinstance(meta["source"], dict):
        rep.add(path, f"`source` must be an object, got {type(meta['source']).__name__}")
    frames = meta.get("frames")
    if not isinstance(frames, list) or not frames:
        rep.add(path, "`frames` must be a non-empty list of frame ids (strings)")
    else:
        bad = [frame_id_issue(f) for f in frames]
        bad = [b for b in bad if b]
        if bad:
            rep.add(path, f"`frames`: {bad[0]}" + (f" (and {len(bad) - 1} more)" if len(bad) > 1 else ""))
        elif len(set(frames)) != len(frames):
            rep.add(path, "`frames` holds duplicate ids")
        else:
            out["frames"] = frames
    model = meta.get("body_model")
    if not isinstance(model, str) or model not in MODELS:
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
        for part, idx in split.items():
            if not isinstance(idx, list) or not all(_is_int(i) for i in idx):
                rep.add(path, f"`split.{part}` must be a list of integer frame indices")
                continue
            bad = [i for i in idx if n and not 0 <= i < n]
            if bad:
                rep.add(path, f"`split.{part}` has indices outside 0..{n - 1}: {bad[:5]}")
            if part in ("train", "test"):
                both = [i for i in idx if i in seen and seen[i] != part]
                if both:
                    rep.add(path, f"frames {both[:5]} are in both train and test")
                seen.update({i: part for i in idx})
        if isinstance(split.get("train"), list) and not split["train"]:
            rep.add(path, "`split.train` is empty: nothing to train on")
    return out


def _infer_frame_ids(root: Path) -> list[str]:
    try:
        return sorted(p.stem for p in (root / "images").glob("*.png"))
    except OSError:
        return []


def _image_size(path: Path) -> tuple[int, int] | None:
    try:
        if _file_issue(path) is not None:
            return None
        with Image.open(path) as im:
            return im.size
    except Exception:  # only a hint for later checks: the image's own check names its problem
        return None


# -- pixels ---------------------------------------------------------------------------


def _open_image(path: Path, rep: _Report, fid: str) -> Image.Image | None:
    """The decoded image (pixels loaded), or None after adding the problem."""
    data = _read_bytes(path, rep, fid)
    if data is None:
        return None
    try:
        im = Image.open(io.BytesIO(data))
        im.load()
    except Exception as e:  # PIL raises OSError, SyntaxError, ValueError, struct.error, ... on bad files
        rep.add(path, f"corrupt or unreadable image ({type(e).__name__}: {e})", fid)
        return None
    if im.mode not in _PIXEL_MODES:
        rep.add(path, f"expected an 8-bit image, got PIL mode {im.mode} (16-bit or float?)", fid)
        return None
    return im


def _check_size(path: Path, rep: _Report, fid: str, im: Image.Image, width, height) -> bool:
    w, h = im.size
    if width is not None and height is not None and (w, h) != (width, height):
        rep.add(path, f"image is {w}x{h}, expected {width}x{height}", fid)
        return False
    return True


def _folder_ok(folder: Path, rep: _Report, ids, what: str) -> bool:
    if not ids:
        return False
    issue = _folder_issue(folder)
    if issue is not None:
        rep.add(folder, f"folder missing ({what})" if issue == "missing" else issue)
        return False
    return True


def _check_images(root: Path, rep: _Report, ids, width, height, folder: Path | None = None) -> None:
    folder = folder or root / "images"
    if not _folder_ok(folder, rep, ids, "one PNG per frame expected"):
        return
    for fid in ids:
        path = folder / f"{fid}.png"
        im = _open_image(path, rep, fid)
        if im is not None:
            _check_size(path, rep, fid, im, width, height)


def _check_masks(root: Path, rep: _Report, ids, width, height, kind: str, person_somewhere: bool = False) -> None:
    folder = root / "masks" / kind
    if not _folder_ok(folder, rep, ids, f"one {kind} mask per frame expected"):
        return
    n_read = n_nonempty = 0
    for fid in ids:
        path = folder / f"{fid}.png"
        im = _open_image(path, rep, fid)
        if im is None or not _check_size(path, rep, fid, im, width, height):
            continue
        if im.mode in ("RGB", "RGBA", "P", "PA"):
            rgb = np.asarray(im.convert("RGB"))
            if not (np.array_equal(rgb[..., 0], rgb[..., 1]) and np.array_equal(rgb[..., 0], rgb[..., 2])):
                rep.add(path, "mask has colour; expected a single-channel 0/255 image", fid)
                continue
        values = mask_values(im)
        distinct = set(np.unique(values).tolist())
        if not (distinct <= {0, 255} or distinct <= {0, 1}):
            rep.add(path, f"mask is not binary: {len(distinct)} distinct values (expected only 0 and 255, or 0 and 1)", fid)
            continue
        n_read += 1
        n_nonempty += bool(mask_from_values(values).any())
    if person_somewhere and n_read == len(ids) and n_nonempty == 0:
        rep.add(folder, f"every {kind} mask is empty: no person in any of the {len(ids)} frames "
                        "(the person is 255, or 1, in these masks)")


# -- arrays ---------------------------------------------------------------------------


def _as_array(value, shape: tuple[int, ...]) -> np.ndarray | None:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        return None
    return arr if arr.shape == shape else None


def _frames_list(obj, path: Path, rep: _Report, n_expected: int | None, what: str = "images") -> list | None:
    frames = obj.get("frames") if isinstance(obj, dict) else None
    if not isinstance(frames, list):
        rep.add(path, "must hold an object with a `frames` list")
        return None
    if n_expected and len(frames) != n_expected:
        rep.add(path, f"has {len(frames)} frames but the scene has {n_expected} {what}")
    return frames


def _check_cameras(path: Path, rep: _Report, ids, width, height, novel_frames: int | None = None) -> list[str] | None:
    """Checks a cameras.json; for novel views (`novel_frames` = the scene's frame count) also
    each entry's `id` and `frame`, and returns the view ids."""
    obj = _load_json(path, rep)
    if obj is None:
        return None
    frames = _frames_list(obj, path, rep, None if novel_frames is not None else len(ids))
    if frames is None:
        return None
    if novel_frames is not None and not frames:
        rep.add(path, "lists no views (remove the novel/ folder if there are none)")
        return None
    view_ids: list[str] = []
    for i, f in enumerate(frames):
        fid = ids[i] if novel_frames is None and i < len(ids) else str(i)
        if not isinstance(f, dict):
            rep.add(path, "camera entry must be an object", fid)
            continue
        if novel_frames is not None:
            issue = frame_id_issue(f.get("id"))
            if issue:
                rep.add(path, f"`id`: {issue}", fid)
            elif f["id"] in view_ids:
                rep.add(path, f"`id` {f['id']!r} is used twice", fid)
            else:
                view_ids.append(f["id"])
                fid = f["id"]
            t = f.get("frame")
            if not _is_int(t) or not 0 <= t < novel_frames:
                rep.add(path, f"`frame` must be the index of the scene frame the view shows (0..{novel_frames - 1}), got {t!r}", fid)
        elif "id" in f and f["id"] != fid:
            rep.add(path, f"entry {i} has id {f['id']!r} but scene.json's frame {i} is {fid!r}", fid)
        K = _as_array(f.get("K"), (3, 3))
        if K is None:
            rep.add(path, "`K` must be a 3x3 matrix of numbers", fid)
        elif not np.isfinite(K).all():
            rep.add(path, "`K` has non-finite numbers", fid)
        elif K[0, 0] <= 0 or K[1, 1] <= 0:
            rep.add(path, f"focal lengths must be positive, got fx={K[0, 0]:g}, fy={K[1, 1]:g}", fid)
        elif np.abs(K[2] - [0, 0, 1]).max() > 1e-6:
            rep.add(path, "`K` last row must be [0, 0, 1]", fid)
        T = _as_array(f.get("world_to_camera"), (4, 4))
        if T is None:
            rep.add(path, "`world_to_camera` must be a 4x4 matrix of numbers", fid)
        elif not np.isfinite(T).all():
            rep.add(path, "`world_to_camera` has non-finite numbers", fid)
        else:
            R = T[:3, :3]
            if np.abs(R @ R.T - np.eye(3)).max() > 1e-3 or np.linalg.det(R) < 0:
                rep.add(path, "`world_to_camera` rotation block is not a rotation", fid)
            if np.abs(T[3] - [0, 0, 0, 1]).max() > 1e-9:
                rep.add(path, "`world_to_camera` last row must be [0, 0, 0, 1]", fid)
    return view_ids if len(view_ids) == len(frames) else None


def _nonfinite_frames(arr: np.ndarray, ids) -> list[str]:
    bad = ~np.isfinite(arr.reshape(len(arr), -1)).all(axis=1)
    return [ids[i] if i < len(ids) else str(i) for i in np.flatnonzero(bad)]


def _check_body(path: Path, rep: _Report, ids, model_in_meta) -> None:
    data = _load_npz(path, rep, missing="missing (per-frame body-model poses are required)")
    if data is None:
        return
    missing = [k for k in ("model", "shape", "pose", "transl") if k not in data]
    if missing:
        rep.add(path, f"missing arrays: {', '.join(missing)}")
        return
    m = data["model"]
    model = str(m) if m.ndim == 0 and m.dtype.kind == "U" else None
    if model not in MODELS:
        rep.add(path, f"`model` must name a body model ({', '.join(sorted(MODELS))}), got {m!r}")
        return
    if model_in_meta is not None and model != model_in_meta:
        rep.add(path, f"body model {model!r} differs from scene.json's {model_in_meta!r}")
    info = MODELS[model]
    T = len(ids)
    for key in ("pose", "transl", "shape"):
        if not _numeric(data[key]):
            rep.add(path, f"`{key}` must hold numbers, got dtype {data[key].dtype}")
    pose, transl, shape = data["pose"], data["transl"], data["shape"]
    for key, arr, tail, form in (("pose", pose, (info.n_bones, 3), f"[T, {info.n_bones}, 3] for {model}"),
                                 ("transl", transl, (3,), "[T, 3]")):
        if not _numeric(arr):
            continue
        if arr.ndim != 1 + len(tail) or arr.shape[1:] != tail:
            rep.add(path, f"`{key}` must be {form}, got {list(arr.shape)}")
        elif T and len(arr) != T:
            rep.add(path, f"`{key}` has {len(arr)} frames but the scene has {T} images")
        else:
            for fid in _nonfinite_frames(arr, ids):
                rep.add(path, f"`{key}` has non-finite numbers", fid)
    if _numeric(shape):
        if shape.shape != (info.n_shape,):
            rep.add(path, f"`shape` must have {info.n_shape} values for {model}, got {list(shape.shape)}")
        elif not np.isfinite(shape).all():
            rep.add(path, "`shape` has non-finite numbers")


def _check_object(path: Path, rep: _Report, ids) -> None:
    obj = _load_json(path, rep, missing="missing (scene.json says the scene has an object)")
    if obj is None:
        return
    c = _as_array(obj.get("centre") if isinstance(obj, dict) else None, (3,))
    if c is None or not np.isfinite(c).all():
        rep.add(path, "`centre` must be 3 finite numbers")
    frames = _frames_list(obj, path, rep, len(ids))
    with_conf = sum(1 for f in frames or [] if isinstance(f, dict) and "confidence" in f)
    for i, f in enumerate(frames or []):
        fid = ids[i] if i < len(ids) else str(i)
        if with_conf and isinstance(f, dict):
            _check_confidence(path, rep, f, fid, with_conf, len(frames))
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


def _check_confidence(path: Path, rep: _Report, f: dict, fid: str, with_conf: int, n_frames: int) -> None:
    """The optional per-frame `confidence`: all frames or none, each a number in [0, 1]."""
    if "confidence" not in f:
        rep.add(path, f"`confidence` is missing here but given on {with_conf} of the {n_frames} frames "
                      "(give it on every frame, or on none)", fid)
        return
    c = f["confidence"]
    if not _is_number(c):
        rep.add(path, f"`confidence` must be a number in [0, 1], got {c!r}", fid)
    elif not math.isfinite(c):
        rep.add(path, f"`confidence` must be finite, got {c!r}", fid)
    elif not 0.0 <= c <= 1.0:
        rep.add(path, f"`confidence` must be in [0, 1] (0 = object lost, 1 = mask trusted), got {c:g}", fid)


def _check_points(path: Path, rep: _Report) -> None:
    data = _read_bytes(path, rep, missing="missing (sparse points initialise the static scene)")
    if data is None:
        return
    try:
        xyz, _ = read_points_ply(io.BytesIO(data))
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
        if not isinstance(p, dict):
            rep.add(path, f"plane {i}: must be an object with `normal` and `offset`")
            continue
        n = _as_array(p.get("normal"), (3,))
        d = _as_array(p.get("offset"), ())
        if n is None or not np.isfinite(n).all():
            rep.add(path, f"plane {i}: needs a finite `normal` [3]")
        elif abs(np.linalg.norm(n) - 1.0) > 1e-3:
            rep.add(path, f"plane {i}: normal is not unit length ({np.linalg.norm(n):.4f})")
        if "offset" not in p:
            rep.add(path, f"plane {i}: `offset` is missing (the plane is n . x + offset = 0)")
        elif d is None or not np.isfinite(d).all():
            rep.add(path, f"plane {i}: `offset` must be a finite number, got {p['offset']!r}")
        if "label" in p and not isinstance(p["label"], str):
            rep.add(path, f"plane {i}: `label` must be a string")


def _check_depth(path: Path, rep: _Report, n: int, width, height) -> None:
    data = _load_npz(path, rep)
    if data is None:
        return
    depth = data.get("depth")
    if depth is None:
        rep.add(path, "has no `depth` array")
    elif not _numeric(depth):
        rep.add(path, f"`depth` must hold numbers, got dtype {depth.dtype}")
    elif depth.shape != (n, height, width):
        rep.add(path, f"depth must be [{n}, {height}, {width}], got {list(depth.shape)}")
    elif not np.isfinite(depth).all():
        rep.add(path, "depth has non-finite values")


def _check_ground_truth(root: Path, rep: _Report, ids, width, height, has_object, model) -> None:
    _check_cameras(root / "cameras.json", rep, ids, width, height)
    _check_body(root / "body.npz", rep, ids, model)
    if has_object:
        _check_object(root / "object.json", rep, ids)
        _check_masks(root, rep, ids, width, height, "object")
    _check_masks(root, rep, ids, width, height, "human")
    _check_depth(root / "depth.npz", rep, len(ids), width, height)
    if _exists(root / "planes.json"):
        _check_planes(root / "planes.json", rep)
    novel = root / "novel"
    if _exists(novel):
        issue = _folder_issue(novel)
        if issue is not None:
            rep.add(novel, issue)
            return
        vids = _check_cameras(novel / "cameras.json", rep, ids, width, height, novel_frames=len(ids))
        if vids is None:
            return
        _check_images(novel, rep, vids, width, height, folder=novel / "images")
        _check_masks(novel, rep, vids, width, height, "human")
        _check_masks(novel, rep, vids, width, height, "object")
        _check_depth(novel / "depth.npz", rep, len(vids), width, height)
