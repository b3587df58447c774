"""Reading and writing the files a scene is made of: PNG images and masks, PLY points,
JSON. One loader per kind of file, used by the scene format, the synthetic generator,
the preprocessors and the evaluators alike."""

from __future__ import annotations

import json
import os
import uuid
from contextlib import contextmanager
from pathlib import Path

import numpy as np
from PIL import Image


def read_image(path: str | Path) -> np.ndarray:
    """[H, W, 3] uint8 RGB (alpha dropped, grey expanded)."""
    with Image.open(path) as im:
        return np.asarray(im.convert("RGB"))


def write_image(path: str | Path, rgb: np.ndarray) -> None:
    """Write [H, W, 3] uint8, or float in [0, 1] (rounded), as PNG."""
    rgb = np.asarray(rgb)
    if rgb.dtype != np.uint8:
        rgb = (np.clip(rgb, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(rgb).save(path, optimize=False, compress_level=3)


def mask_values(im: Image.Image) -> np.ndarray:
    """[H, W] uint8 grey values of a mask image (colour and palette images as grey)."""
    return np.asarray(im.convert("L"))


def mask_from_values(values: np.ndarray) -> np.ndarray:
    """[H, W] bool from a mask's grey values: 0/255 masks count > 127 as inside, masks
    stored as 0/1 (their largest value is 1) count 1 as inside."""
    values = np.asarray(values)
    if values.dtype == bool:
        return values
    return values > (0 if values.size and values.max() <= 1 else 127)


def read_mask(path: str | Path) -> np.ndarray:
    """[H, W] bool from an 8-bit mask PNG, stored as 0/255 or as 0/1 (see `mask_from_values`)."""
    with Image.open(path) as im:
        return mask_from_values(mask_values(im))


def write_mask(path: str | Path, mask: np.ndarray) -> None:
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray((np.asarray(mask) > 0).astype(np.uint8) * 255).save(path, compress_level=3)


def read_json(path: str | Path):
    """The JSON value in `path` (UTF-8, -16 or -32, as `json.loads` detects it)."""
    with open(path, "rb") as f:
        return json.loads(f.read())


@contextmanager
def atomic_writer(path: str | Path, mode: str = "w", fsync: bool = False):
    """Open a temporary file beside `path` for writing and rename it onto `path` when the
    block ends without an error (a reader never sees half a file; on an error the temporary
    file is removed and `path` is left as it was).

    The file gets the permissions any new file of the user gets (0666 less the umask), like
    the images beside it: `tempfile.mkstemp` would make it 0600."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.parent / f".{path.name}.{uuid.uuid4().hex[:12]}.tmp"
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    try:
        with os.fdopen(fd, mode) as f:
            yield f
            if fsync:
                f.flush()
                os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_json(path: str | Path, obj) -> None:
    """Write atomically (temp file + rename) with stable formatting."""
    with atomic_writer(path) as f:
        json.dump(obj, f, indent=1, default=_json_default)
        f.write("\n")


def _json_default(x):
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, (np.floating, np.integer, np.bool_)):
        return x.item()
    raise TypeError(f"not JSON serialisable: {type(x).__name__}")


def write_points_ply(path: str | Path, xyz: np.ndarray, rgb: np.ndarray) -> None:
    """Coloured point cloud: float32 x, y, z and uchar red, green, blue (binary LE)."""
    from plyfile import PlyData, PlyElement

    xyz = np.asarray(xyz, dtype=np.float32)
    rgb = np.asarray(rgb)
    if rgb.dtype != np.uint8:
        rgb = (np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8)
    v = np.empty(len(xyz), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"),
                                  ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    v["x"], v["y"], v["z"] = xyz.T
    v["red"], v["green"], v["blue"] = rgb.T
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    PlyData([PlyElement.describe(v, "vertex")], byte_order="<").write(str(path))


def read_points_ply(path) -> tuple[np.ndarray, np.ndarray]:
    """(xyz [P, 3] float32, rgb [P, 3] uint8) from a PLY path or binary stream; colour
    defaults to grey when absent."""
    from plyfile import PlyData

    v = PlyData.read(path if hasattr(path, "read") else str(path))["vertex"]
    xyz = np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float32)
    names = v.data.dtype.names
    if all(c in names for c in ("red", "green", "blue")):
        rgb = np.stack([v["red"], v["green"], v["blue"]], axis=1).astype(np.uint8)
    else:
        rgb = np.full_like(xyz, 128, dtype=np.uint8)
    return xyz, rgb
