"""Rendering one view of the synthetic scene: rasterize, shade, anti-alias, label.

The scene at one instant is a `SceneMesh` in world coordinates (room + posed body + posed
box) with per-vertex normals, texture coordinates and body-part weights. A view is
rasterized at `ss` x `ss` samples per output pixel; every sample is shaded (albedo x
Lambert light: baked texels for the static room, procedural textures evaluated per sample
for the body and the box), and the output pixel is the mean of its samples. Labels and
depth come from the same samples:

- label: the most frequent sample label in the pixel (static, human, object, or none),
  ties broken by the pixel-centre sample; the ground-truth masks are `label == HUMAN`
  and `label == OBJECT`;
- depth: camera z of the surface seen through the pixel centre (the middle sample, which
  for odd ss sits exactly on the pixel centre), 0 where nothing was hit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np

from cogs.data.synth import textures as tx
from cogs.data.synth.mesh import Mesh
from cogs.data.synth.raster import Raster, interpolate, rasterize, scale_intrinsics
from cogs.geometry.camera import transform_points

NONE = 3  # label of pixels where nothing was drawn (never inside the closed room)


@dataclass
class SceneMesh:
    mesh: Mesh  # world coordinates
    parts: np.ndarray  # [V, P] body-part one-hots (zero rows off the body)
    layout: tx.BodyLayout
    baked: tx.BakedTextures  # face_tex covers every face; -1 = shade procedurally


@dataclass
class View:
    rgb: np.ndarray  # [H, W, 3] uint8
    label: np.ndarray  # [H, W] int8 (STATIC, HUMAN, OBJECT, NONE)
    depth: np.ndarray  # [H, W] float32 metres, 0 = nothing
    centre_label: np.ndarray  # [H, W] int8 label of the pixel-centre sample (the one depth is from)
    centre_tri: np.ndarray  # [H, W] int32 triangle seen through the pixel centre (-1 = none)
    raster: Raster | None = None  # the supersampled buffers, when asked for


_LIGHT = np.array([tx.AMBIENT, tx.KEY, *tx.KEY_DIR, tx.FILL, *tx.FILL_DIR])


@nb.njit(cache=True, inline="always")
def _light(nx, ny, nz, L):
    norm = np.sqrt(nx * nx + ny * ny + nz * nz) + 1e-12
    k = (nx * L[2] + ny * L[3] + nz * L[4]) / norm
    f = (nx * L[6] + ny * L[7] + nz * L[8]) / norm
    return L[0] + L[1] * max(k, 0.0) + L[5] * max(f, 0.0)


@nb.njit(cache=True, parallel=True)
def _shade_baked(tri, buf, face_tex, data, meta, L, out, todo):
    """Baked-texture samples: bilinear texel lookup x light into out; others flagged in todo."""
    H, W = tri.shape
    for i in nb.prange(H):
        for j in range(W):
            t = tri[i, j]
            if t < 0:
                continue
            k = face_tex[t]
            if k < 0:
                todo[i, j] = True
                continue
            off = int(meta[k, 0])
            nu = int(meta[k, 1])
            nv = int(meta[k, 2])
            fu = (buf[i, j, 3] - meta[k, 3]) / meta[k, 5]
            fv = (buf[i, j, 4] - meta[k, 4]) / meta[k, 5]
            fu = min(max(fu, 0.0), nu - 1.000001)
            fv = min(max(fv, 0.0), nv - 1.000001)
            u0 = int(fu)
            v0 = int(fv)
            a = fu - u0
            b = fv - v0
            p00 = off + v0 * nu + u0
            p10 = p00 + 1
            p01 = p00 + nu
            p11 = p01 + 1
            s = _light(buf[i, j, 0], buf[i, j, 1], buf[i, j, 2], L)
            for c in range(3):
                v = (1 - b) * ((1 - a) * data[p00, c] + a * data[p10, c]) + b * ((1 - a) * data[p01, c] + a * data[p11, c])
                out[i, j, c] = v * s


@nb.njit(cache=True, parallel=True)
def _resolve(rgb_s, lab_s, depth_s, ss, rgb, label, depth):
    """Box-filter colours, majority labels (ties: centre sample) and centre-sample depth."""
    H, W = label.shape
    c = ss // 2
    inv = 1.0 / (ss * ss)
    for i in nb.prange(H):
        for j in range(W):
            counts = np.zeros(4)
            acc0 = 0.0
            acc1 = 0.0
            acc2 = 0.0
            for di in range(ss):
                for dj in range(ss):
                    y = i * ss + di
                    x = j * ss + dj
                    acc0 += rgb_s[y, x, 0]
                    acc1 += rgb_s[y, x, 1]
                    acc2 += rgb_s[y, x, 2]
                    counts[lab_s[y, x]] += 1.0
            centre = lab_s[i * ss + c, j * ss + c]
            counts[centre] += 0.5
            best = 0
            for k in range(1, 4):
                if counts[k] > counts[best]:
                    best = k
            label[i, j] = best
            rgb[i, j, 0] = min(max(acc0 * inv, 0.0), 1.0) * 255.0 + 0.5
            rgb[i, j, 1] = min(max(acc1 * inv, 0.0), 1.0) * 255.0 + 0.5
            rgb[i, j, 2] = min(max(acc2 * inv, 0.0), 1.0) * 255.0 + 0.5
            d = depth_s[i * ss + c, j * ss + c]
            depth[i, j] = d if np.isfinite(d) else 0.0


def render_view(scene: SceneMesh, K: np.ndarray, world_to_camera: np.ndarray, width: int, height: int,
                ss: int = 3, near: float = 0.05, keep_raster: bool = False) -> View:
    """Render RGB, labels and depth of `scene` seen by one camera (see the module doc)."""
    assert ss % 2 == 1, "odd supersampling keeps a sample on every pixel centre"
    m = scene.mesh
    vc = transform_points(world_to_camera, m.vertices)
    r = rasterize(vc, m.faces, scale_intrinsics(K, ss), width * ss, height * ss, near)
    attrs = np.concatenate([m.normals, m.texcoords, scene.parts], axis=1)
    buf = interpolate(r, m.faces, attrs)  # [Hs, Ws, A]
    rgb_s = np.zeros(r.tri.shape + (3,), dtype=np.float32)
    todo = np.zeros(r.tri.shape, dtype=np.bool_)
    _shade_baked(r.tri, buf, scene.baked.face_tex, scene.baked.data, scene.baked.meta, _LIGHT, rgb_s, todo)
    if todo.any():
        vals = buf[todo]
        col = tx.albedo(m.material[r.tri[todo]], vals[:, 3:6], vals[:, 6:], scene.layout)
        rgb_s[todo] = tx.shade(col, vals[:, 0:3])
    lab_s = np.where(r.tri >= 0, m.label[np.maximum(r.tri, 0)], NONE).astype(np.int8)
    rgb = np.empty((height, width, 3), dtype=np.uint8)
    label = np.empty((height, width), dtype=np.int8)
    depth = np.empty((height, width), dtype=np.float32)
    _resolve(rgb_s, lab_s, r.depth, ss, rgb, label, depth)
    c = ss // 2
    return View(rgb=rgb, label=label, depth=depth, centre_label=lab_s[c::ss, c::ss].copy(),
                centre_tri=r.tri[c::ss, c::ss].copy(),
                raster=r if keep_raster else None)


def majority_label(sample_labels: np.ndarray, ss: int) -> np.ndarray:
    """Reference of the label rule: [H*ss, W*ss] labels -> [H, W] (numpy, for tests)."""
    from cogs.data.synth.mesh import HUMAN, OBJECT, STATIC

    Hs, Ws = sample_labels.shape
    H, W = Hs // ss, Ws // ss
    blocks = sample_labels.reshape(H, ss, W, ss)
    classes = np.array([STATIC, HUMAN, OBJECT, NONE])
    counts = np.stack([(blocks == k).sum(axis=(1, 3)) for k in classes], -1).astype(np.float64)
    centre = blocks[:, ss // 2, :, ss // 2]
    counts += 0.5 * (centre[..., None] == classes)
    return classes.astype(np.int8)[np.argmax(counts, axis=-1)]


def warmup() -> None:
    """Compile (or load from numba's cache) the rasterizer's and the shading kernels."""
    from cogs.data.synth.raster import warmup as raster_warmup

    raster_warmup()
    tri = np.zeros((3, 3), np.int32)
    buf = np.zeros((3, 3, 16), np.float32)
    out = np.zeros((3, 3, 3), np.float32)
    _shade_baked(tri, buf, np.zeros(1, np.int32), np.ones((4, 3), np.float32),
                 np.array([[0, 2, 2, 0, 0, 1.0]]), _LIGHT, out, np.zeros((3, 3), np.bool_))
    _resolve(out, np.zeros((3, 3), np.int8), np.ones((3, 3)), 3, np.empty((1, 1, 3), np.uint8),
             np.empty((1, 1), np.int8), np.empty((1, 1), np.float32))
