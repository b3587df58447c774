"""A z-buffer triangle rasterizer for the synthetic scene's ground truth.

This renderer exists so that the benchmark's ground truth is independent of the Gaussian
renderer it is used to judge. It draws triangle meshes with:

- perspective projection through a pinhole K (OpenCV camera, pixel (i, j) covers
  [j, j+1) x [i, i+1), so samples sit at (j + 0.5, i + 0.5));
- near-plane clipping in camera space (the camera is inside the room: walls and floor
  pass behind it), each clipped piece keeping barycentric coordinates of its source
  triangle;
- a top-left fill rule, so a pixel centre on an edge shared by two triangles is drawn
  exactly once (no cracks, no double coverage);
- per sample: nearest depth (camera z, metres), the source triangle id, and
  perspective-correct barycentric coordinates of the source triangle.

Shading, anti-aliasing and labels are done by the caller on these buffers (see
`cogs.data.synth.render`): render at `ss` times the output resolution with
`scale_intrinsics`, shade every sample, then average ss x ss blocks.

`rasterize` is the fast numba kernel (triangles binned into tiles, tiles drawn in
parallel, deterministic because each tile draws its triangles in index order);
`rasterize_reference` is a plain numpy version, one triangle at a time over the whole
image, that the tests compare it against.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np

TILE = 16  # samples per tile side


@dataclass
class Raster:
    """Per-sample buffers of one rendered view, [H, W] at the rasterized resolution."""

    depth: np.ndarray  # [H, W] float64 camera z in metres, inf where nothing was drawn
    tri: np.ndarray  # [H, W] int32 source triangle index, -1 where nothing was drawn
    bary: np.ndarray  # [H, W, 3] float32 perspective-correct barycentrics of `tri`

    @property
    def hit(self) -> np.ndarray:
        return self.tri >= 0


def scale_intrinsics(K: np.ndarray, ss: int) -> np.ndarray:
    """K of the same camera sampled `ss` times more finely in x and y.

    Pixel edges map to pixel edges (u' = ss u), so sample (j', i') of the fine image has
    its centre at ((j' + 0.5) / ss, (i' + 0.5) / ss) in the coarse image; for odd ss the
    middle sample of each ss x ss block is exactly the coarse pixel centre.
    """
    S = np.diag([float(ss), float(ss), 1.0])
    return S @ np.asarray(K, dtype=np.float64)


# -- clipping and projection ----------------------------------------------------------------


@nb.njit(cache=True, inline="always")
def _clip_near(p, b, near, out_p, out_b):
    """Clip polygon (3 vertices p [3,3], barycentrics b [3,3]) to z >= near.

    Writes up to 4 vertices into out_p/out_b and returns their count (0, 3 or 4).
    """
    n = 0
    for k in range(3):
        k1 = (k + 1) % 3
        za = p[k, 2]
        zb = p[k1, 2]
        ina = za >= near
        inb = zb >= near
        if ina:
            for c in range(3):
                out_p[n, c] = p[k, c]
                out_b[n, c] = b[k, c]
            n += 1
        if ina != inb:
            s = (near - za) / (zb - za)
            for c in range(3):
                out_p[n, c] = p[k, c] + s * (p[k1, c] - p[k, c])
                out_b[n, c] = b[k, c] + s * (b[k1, c] - b[k, c])
            out_p[n, 2] = near
            n += 1
    return n


@nb.njit(cache=True, parallel=True)
def _clip_project(verts_cam, faces, fx, fy, cx, cy, near, sxy, sinvz, sbary, svalid):
    """Each source triangle -> up to two screen-space pieces in slots 2f and 2f+1."""
    F = faces.shape[0]
    for f in nb.prange(F):
        p = np.empty((3, 3))
        b = np.zeros((3, 3))
        for k in range(3):
            for c in range(3):
                p[k, c] = verts_cam[faces[f, k], c]
            b[k, k] = 1.0
        svalid[2 * f] = False
        svalid[2 * f + 1] = False
        if p[0, 2] < near and p[1, 2] < near and p[2, 2] < near:
            continue
        qp = np.empty((4, 3))
        qb = np.empty((4, 3))
        n = _clip_near(p, b, near, qp, qb)
        if n < 3:
            continue
        for piece in range(n - 2):
            slot = 2 * f + piece
            idx = (0, piece + 1, piece + 2)
            for k in range(3):
                v = idx[k]
                z = qp[v, 2]
                sxy[slot, k, 0] = fx * qp[v, 0] / z + cx
                sxy[slot, k, 1] = fy * qp[v, 1] / z + cy
                sinvz[slot, k] = 1.0 / z
                for c in range(3):
                    sbary[slot, k, c] = qb[v, c]
            svalid[slot] = True


@nb.njit(cache=True, inline="always")
def _sample_range(lo, hi, n):
    """Integer samples s with s + 0.5 in [lo, hi], clamped to [0, n - 1]."""
    a = int(np.ceil(lo - 0.5))
    b = int(np.floor(hi - 0.5))
    if a < 0:
        a = 0
    if b > n - 1:
        b = n - 1
    return a, b


@nb.njit(cache=True)
def _bin(sxy, svalid, width, height, tiles_x, tiles_y):
    """Triangle-piece lists per tile (CSR: offsets [n_tiles + 1], items), in index order."""
    n_tiles = tiles_x * tiles_y
    counts = np.zeros(n_tiles + 1, dtype=np.int64)
    S = sxy.shape[0]
    boxes = np.full((S, 4), -1, dtype=np.int64)
    for s in range(S):
        if not svalid[s]:
            continue
        x0 = min(sxy[s, 0, 0], sxy[s, 1, 0], sxy[s, 2, 0])
        x1 = max(sxy[s, 0, 0], sxy[s, 1, 0], sxy[s, 2, 0])
        y0 = min(sxy[s, 0, 1], sxy[s, 1, 1], sxy[s, 2, 1])
        y1 = max(sxy[s, 0, 1], sxy[s, 1, 1], sxy[s, 2, 1])
        if x1 < 0.0 or y1 < 0.0 or x0 > width or y0 > height:
            continue
        j0, j1 = _sample_range(x0, x1, width)
        i0, i1 = _sample_range(y0, y1, height)
        if j0 > j1 or i0 > i1:
            continue
        boxes[s, 0] = j0
        boxes[s, 1] = j1
        boxes[s, 2] = i0
        boxes[s, 3] = i1
        for ty in range(i0 // TILE, i1 // TILE + 1):
            for tx in range(j0 // TILE, j1 // TILE + 1):
                counts[ty * tiles_x + tx + 1] += 1
    for t in range(n_tiles):
        counts[t + 1] += counts[t]
    items = np.empty(counts[n_tiles], dtype=np.int64)
    fill = counts[:-1].copy()
    for s in range(S):
        if boxes[s, 0] < 0:
            continue
        for ty in range(boxes[s, 2] // TILE, boxes[s, 3] // TILE + 1):
            for tx in range(boxes[s, 0] // TILE, boxes[s, 1] // TILE + 1):
                t = ty * tiles_x + tx
                items[fill[t]] = s
                fill[t] += 1
    return counts, items, boxes


@nb.njit(cache=True, inline="always")
def _top_left(ax, ay, bx, by):
    """Edge a->b of a positively oriented triangle owns the pixels exactly on it."""
    dy = by - ay
    return dy > 0.0 or (dy == 0.0 and bx < ax)


@nb.njit(cache=True, parallel=True)
def _draw_tiles(sxy, sinvz, sbary, counts, items, boxes, width, height, tiles_x, depth, tri, bary):
    n_tiles = counts.shape[0] - 1
    for t in nb.prange(n_tiles):
        tx = t % tiles_x
        ty = t // tiles_x
        tj0 = tx * TILE
        ti0 = ty * TILE
        tj1 = min(tj0 + TILE, width) - 1
        ti1 = min(ti0 + TILE, height) - 1
        for k in range(counts[t], counts[t + 1]):
            s = items[k]
            ax = sxy[s, 0, 0]
            ay = sxy[s, 0, 1]
            bx = sxy[s, 1, 0]
            by = sxy[s, 1, 1]
            cx = sxy[s, 2, 0]
            cy = sxy[s, 2, 1]
            area = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
            if area == 0.0:
                continue
            # Orient positively: swap vertices 1 and 2 when the area is negative.
            i1v = 1
            i2v = 2
            if area < 0.0:
                bx, by, cx, cy = cx, cy, bx, by
                i1v = 2
                i2v = 1
                area = -area
            inv_area = 1.0 / area
            tl0 = _top_left(bx, by, cx, cy)
            tl1 = _top_left(cx, cy, ax, ay)
            tl2 = _top_left(ax, ay, bx, by)
            iz0 = sinvz[s, 0]
            iz1 = sinvz[s, i1v]
            iz2 = sinvz[s, i2v]
            j0 = max(boxes[s, 0], tj0)
            j1 = min(boxes[s, 1], tj1)
            i0 = max(boxes[s, 2], ti0)
            i1 = min(boxes[s, 3], ti1)
            for i in range(i0, i1 + 1):
                py = i + 0.5
                for j in range(j0, j1 + 1):
                    px = j + 0.5
                    w0 = (cx - bx) * (py - by) - (cy - by) * (px - bx)
                    w1 = (ax - cx) * (py - cy) - (ay - cy) * (px - cx)
                    w2 = (bx - ax) * (py - ay) - (by - ay) * (px - ax)
                    if w0 < 0.0 or w1 < 0.0 or w2 < 0.0:
                        continue
                    if (w0 == 0.0 and not tl0) or (w1 == 0.0 and not tl1) or (w2 == 0.0 and not tl2):
                        continue
                    q0 = w0 * inv_area * iz0
                    q1 = w1 * inv_area * iz1
                    q2 = w2 * inv_area * iz2
                    sq = q0 + q1 + q2
                    z = 1.0 / sq
                    if z < depth[i, j]:
                        depth[i, j] = z
                        tri[i, j] = s // 2
                        q0 *= z
                        q1 *= z
                        q2 *= z
                        for c in range(3):
                            bary[i, j, c] = q0 * sbary[s, 0, c] + q1 * sbary[s, i1v, c] + q2 * sbary[s, i2v, c]


def rasterize(verts_cam: np.ndarray, faces: np.ndarray, K: np.ndarray, width: int, height: int,
              near: float = 0.05) -> Raster:
    """Rasterize a triangle mesh given in camera coordinates.

    verts_cam: [V, 3] float, OpenCV camera frame (z forward, metres).
    faces: [F, 3] int vertex indices (either winding; nothing is culled).
    K: [3, 3] intrinsics at the rasterized resolution (no skew).
    Returns per-sample nearest depth, triangle id and perspective-correct barycentrics.
    """
    verts_cam = np.ascontiguousarray(verts_cam, dtype=np.float64)
    faces = np.ascontiguousarray(faces, dtype=np.int64)
    assert abs(K[0, 1]) < 1e-12, "skewed intrinsics are not supported"
    F = len(faces)
    sxy = np.empty((2 * F, 3, 2))
    sinvz = np.empty((2 * F, 3))
    sbary = np.empty((2 * F, 3, 3))
    svalid = np.zeros(2 * F, dtype=np.bool_)
    _clip_project(verts_cam, faces, float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]),
                  float(near), sxy, sinvz, sbary, svalid)
    tiles_x = (width + TILE - 1) // TILE
    tiles_y = (height + TILE - 1) // TILE
    counts, items, boxes = _bin(sxy, svalid, width, height, tiles_x, tiles_y)
    depth = np.full((height, width), np.inf)
    tri = np.full((height, width), -1, dtype=np.int32)
    bary = np.zeros((height, width, 3), dtype=np.float32)
    _draw_tiles(sxy, sinvz, sbary, counts, items, boxes, width, height, tiles_x, depth, tri, bary)
    return Raster(depth=depth, tri=tri, bary=bary)


@nb.njit(cache=True, parallel=True)
def _interpolate(tri, bary, faces, attrs, out):
    H, W = tri.shape
    A = attrs.shape[1]
    for i in nb.prange(H):
        for j in range(W):
            t = tri[i, j]
            if t < 0:
                continue
            a = faces[t, 0]
            b = faces[t, 1]
            c = faces[t, 2]
            l0 = bary[i, j, 0]
            l1 = bary[i, j, 1]
            l2 = bary[i, j, 2]
            for k in range(A):
                out[i, j, k] = l0 * attrs[a, k] + l1 * attrs[b, k] + l2 * attrs[c, k]


def interpolate(r: Raster, faces: np.ndarray, attrs: np.ndarray) -> np.ndarray:
    """Per-vertex attributes [V, A] -> per-sample [H, W, A] float32 (0 where empty)."""
    attrs = np.ascontiguousarray(attrs, dtype=np.float32)
    out = np.zeros(r.tri.shape + (attrs.shape[1],), dtype=np.float32)
    _interpolate(r.tri, r.bary, np.ascontiguousarray(faces, dtype=np.int64), attrs, out)
    return out


def warmup() -> None:
    """Compile (or load from numba's cache) every kernel on a tiny mesh."""
    v = np.array([[-1.0, -1.0, 2.0], [1.0, -1.0, 2.0], [0.0, 1.0, 0.01]])
    f = np.array([[0, 1, 2]])
    r = rasterize(v, f, np.array([[8.0, 0, 8], [0, 8.0, 8], [0, 0, 1]]), 16, 16)
    interpolate(r, f, np.ones((3, 2)))


# -- reference -------------------------------------------------------------------------------


def rasterize_reference(verts_cam: np.ndarray, faces: np.ndarray, K: np.ndarray, width: int, height: int,
                        near: float = 0.05) -> Raster:
    """Plain numpy rasterizer with the same conventions, for tests (slow: O(F * H * W))."""
    verts_cam = np.asarray(verts_cam, dtype=np.float64)
    depth = np.full((height, width), np.inf)
    tri = np.full((height, width), -1, dtype=np.int32)
    bary = np.zeros((height, width, 3), dtype=np.float32)
    jj, ii = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    for f, face in enumerate(np.asarray(faces)):
        p = verts_cam[face]
        b = np.eye(3)
        # Clip to z >= near (Sutherland-Hodgman on one plane).
        poly: list[tuple[np.ndarray, np.ndarray]] = []
        for k in range(3):
            k1 = (k + 1) % 3
            ina, inb = p[k, 2] >= near, p[k1, 2] >= near
            if ina:
                poly.append((p[k], b[k]))
            if ina != inb:
                s = (near - p[k, 2]) / (p[k1, 2] - p[k, 2])
                q = p[k] + s * (p[k1] - p[k])
                q[2] = near
                poly.append((q, b[k] + s * (b[k1] - b[k])))
        for piece in range(len(poly) - 2):
            verts = [poly[0], poly[piece + 1], poly[piece + 2]]
            P = np.array([v[0] for v in verts])
            B = np.array([v[1] for v in verts])
            x = K[0, 0] * P[:, 0] / P[:, 2] + K[0, 2]
            y = K[1, 1] * P[:, 1] / P[:, 2] + K[1, 2]
            area = (x[1] - x[0]) * (y[2] - y[0]) - (y[1] - y[0]) * (x[2] - x[0])
            if area == 0:
                continue
            order = [0, 1, 2] if area > 0 else [0, 2, 1]
            x, y, P, B = x[order], y[order], P[order], B[order]
            area = abs(area)
            ws = []
            inside = np.ones_like(jj, dtype=bool)
            for e in range(3):
                a, c = (e + 1) % 3, (e + 2) % 3
                w = (x[c] - x[a]) * (ii - y[a]) - (y[c] - y[a]) * (jj - x[a])
                dy, dx = y[c] - y[a], x[c] - x[a]
                tl = dy > 0 or (dy == 0 and dx < 0)
                inside &= (w > 0) | ((w == 0) & tl)
                ws.append(w / area)
            q = np.stack([ws[k] / P[k, 2] for k in range(3)], -1)
            z = 1.0 / q.sum(-1)
            closer = inside & (z < depth)
            depth[closer] = z[closer]
            tri[closer] = f
            pb = q[closer] * z[closer][:, None]
            bary[closer] = (pb @ B).astype(np.float32)
    return Raster(depth=depth, tri=tri, bary=bary)
