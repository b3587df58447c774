"""Triangle meshes of the synthetic scene: a container and the box/quad builders.

Every mesh carries, per vertex, a normal and a 3-vector of texture coordinates, and per
face a material id (see `cogs.data.synth.textures`) and a label (static / human /
object) from which the ground-truth masks are made. Flat surfaces get their own
vertices per face so normals and texture coordinates do not blend across edges.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

STATIC, HUMAN, OBJECT = 0, 1, 2
LABEL_NAMES = {STATIC: "static", HUMAN: "human", OBJECT: "object"}


@dataclass
class Mesh:
    vertices: np.ndarray  # [V, 3] float64
    faces: np.ndarray  # [F, 3] int64
    normals: np.ndarray  # [V, 3] float64 unit (outward / into the room)
    texcoords: np.ndarray  # [V, 3] float64; meaning depends on the material
    material: np.ndarray  # [F] int32
    label: np.ndarray  # [F] int8 (STATIC, HUMAN, OBJECT)

    @property
    def n_faces(self) -> int:
        return len(self.faces)

    def transformed(self, R: np.ndarray, t: np.ndarray) -> "Mesh":
        """The mesh moved rigidly: x -> R x + t (normals rotated, texcoords kept)."""
        return Mesh(self.vertices @ R.T + t, self.faces, self.normals @ R.T, self.texcoords, self.material, self.label)


def concat(meshes: list[Mesh]) -> Mesh:
    offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
    return Mesh(
        vertices=np.concatenate([m.vertices for m in meshes]),
        faces=np.concatenate([m.faces + o for m, o in zip(meshes, offsets)]),
        normals=np.concatenate([m.normals for m in meshes]),
        texcoords=np.concatenate([m.texcoords for m in meshes]),
        material=np.concatenate([m.material for m in meshes]).astype(np.int32),
        label=np.concatenate([m.label for m in meshes]).astype(np.int8),
    )


def quad(corner: np.ndarray, edge_u: np.ndarray, edge_v: np.ndarray, normal: np.ndarray, material: int,
         label: int = STATIC, uv_origin=(0.0, 0.0), face_id: float = 0.0) -> Mesh:
    """Rectangle corner + a edge_u + b edge_v (a, b in [0, 1]), two triangles.

    Texture coordinates are (u, v) in metres along the edges from `uv_origin`, and a
    constant third value `face_id` (lets one material tell faces apart).
    """
    corner, edge_u, edge_v = (np.asarray(a, dtype=np.float64) for a in (corner, edge_u, edge_v))
    lu, lv = np.linalg.norm(edge_u), np.linalg.norm(edge_v)
    v = np.array([corner, corner + edge_u, corner + edge_u + edge_v, corner + edge_v])
    uv = np.array([[0, 0], [lu, 0], [lu, lv], [0, lv]], dtype=np.float64) + np.asarray(uv_origin, dtype=np.float64)
    n = np.asarray(normal, dtype=np.float64)
    n = n / np.linalg.norm(n)
    return Mesh(
        vertices=v,
        faces=np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int64),
        normals=np.tile(n, (4, 1)),
        texcoords=np.concatenate([uv, np.full((4, 1), face_id)], axis=1),
        material=np.full(2, material, dtype=np.int32),
        label=np.full(2, label, dtype=np.int8),
    )


# Face order of `box`: +x, -x, +y, -y, +z, -z (face_id 0..5 in texcoords[:, 2]).
BOX_FACES = ("+x", "-x", "+y", "-y", "+z", "-z")


def box(lo, hi, material, label: int = STATIC, inward: bool = False) -> Mesh:
    """Axis-aligned box [lo, hi] as 6 quads with outward normals (inward for a room).

    `material` is one id for all faces or a sequence of 6 (order of BOX_FACES). Texture
    (u, v) are metres on each face, measured from the face's low corner.
    """
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    d = hi - lo
    mats = [material] * 6 if np.isscalar(material) else list(material)
    ex, ey, ez = np.array([d[0], 0, 0]), np.array([0, d[1], 0]), np.array([0, 0, d[2]])
    s = -1.0 if inward else 1.0
    quads = [
        quad(lo + ex, ey, ez, s * np.array([1.0, 0, 0]), mats[0], label, face_id=0),
        quad(lo, ey, ez, s * np.array([-1.0, 0, 0]), mats[1], label, face_id=1),
        quad(lo + ey, ex, ez, s * np.array([0, 1.0, 0]), mats[2], label, face_id=2),
        quad(lo, ex, ez, s * np.array([0, -1.0, 0]), mats[3], label, face_id=3),
        quad(lo + ez, ex, ey, s * np.array([0, 0, 1.0]), mats[4], label, face_id=4),
        quad(lo, ex, ey, s * np.array([0, 0, -1.0]), mats[5], label, face_id=5),
    ]
    return concat(quads)


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals of a closed, consistently wound mesh [V, 3]."""
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    fn = np.cross(b - a, c - a)
    n = np.zeros_like(vertices)
    for k in range(3):
        for ax in range(3):
            n[:, ax] += np.bincount(faces[:, k], weights=fn[:, ax], minlength=len(vertices))
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)


def point_triangle_distance(points: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """Distance from each point [P, 3] to the nearest triangle of tris [F, 3, 3] -> [P].

    Exact (Ericson's closest-point regions), vectorised over triangles per point chunk.
    """
    best = np.full(len(points), np.inf)
    a, b, c = tris[:, 0], tris[:, 1], tris[:, 2]
    ab, ac = b - a, c - a
    for s in range(0, len(points), 256):
        p = points[s:s + 256, None, :]  # [P, 1, 3]
        ap = p - a
        d1, d2 = (ab * ap).sum(-1), (ac * ap).sum(-1)
        bp = p - b
        d3, d4 = (ab * bp).sum(-1), (ac * bp).sum(-1)
        cp = p - c
        d5, d6 = (ab * cp).sum(-1), (ac * cp).sum(-1)
        va = d3 * d6 - d5 * d4
        vb = d5 * d2 - d1 * d6
        vc = d1 * d4 - d3 * d2
        denom = va + vb + vc
        denom = np.where(np.abs(denom) < 1e-30, 1e-30, denom)
        v = vb / denom
        w = vc / denom
        q = a + ab * v[..., None] + ac * w[..., None]  # interior
        # Vertex and edge regions override the interior solution.
        e_ab = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
        t_ab = d1 / np.where(d1 - d3 == 0, 1e-30, d1 - d3)
        q = np.where(e_ab[..., None], a + ab * t_ab[..., None], q)
        e_ac = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
        t_ac = d2 / np.where(d2 - d6 == 0, 1e-30, d2 - d6)
        q = np.where(e_ac[..., None], a + ac * t_ac[..., None], q)
        e_bc = (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0)
        t_bc = (d4 - d3) / np.where((d4 - d3) + (d5 - d6) == 0, 1e-30, (d4 - d3) + (d5 - d6))
        q = np.where(e_bc[..., None], b + (c - b) * t_bc[..., None], q)
        q = np.where(((d1 <= 0) & (d2 <= 0))[..., None], a, q)
        q = np.where(((d3 >= 0) & (d4 <= d3))[..., None], b, q)
        q = np.where(((d6 >= 0) & (d5 <= d6))[..., None], c, q)
        best[s:s + 256] = np.linalg.norm(p - q, axis=-1).min(axis=1)
    return best
