"""The static room of the synthetic scene: walls, floor, ceiling and furniture.

World frame: z up, floor at z = 0, metres. The room spans x in [-3.5, 3.5], y in
[-3, 3], z in [0, 2.7]; it is closed (four walls and a ceiling) so every camera ray hits
a surface. Furniture are textured boxes: a bookshelf against the back wall, a sideboard
against the left wall, a cabinet against the right wall, and the low table the object
rests on before it is picked up.

The room's planes (floor, walls, ceiling) are exact and returned as `PlaneSpec`s with
normals pointing into the room (n . x + offset = 0).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cogs.data.scene import PlaneSpec
from cogs.data.synth import textures as tx
from cogs.data.synth.mesh import Mesh, box, concat, quad

ROOM_LO = np.array([-3.5, -3.0, 0.0])
ROOM_HI = np.array([3.5, 3.0, 2.7])

# The low table the box rests on: top surface height and footprint (world x, y).
TABLE_TOP_Z = 0.50
TABLE_XY_LO = np.array([0.30, -0.35])
TABLE_XY_HI = np.array([0.95, 0.45])


@dataclass
class Room:
    mesh: Mesh
    planes: list[PlaneSpec]
    obstacles: list[tuple[np.ndarray, np.ndarray]]  # furniture boxes (lo, hi) cameras must avoid


def _shell() -> Mesh:
    (x0, y0, z0), (x1, y1, z1) = ROOM_LO, ROOM_HI
    W, D, H = x1 - x0, y1 - y0, z1 - z0
    return concat([
        # Texture (u, v) of each wall: metres from its low corner (see textures.py).
        quad([x0, y0, z0], [W, 0, 0], [0, D, 0], [0, 0, 1], tx.FLOOR),
        quad([x0, y0, z1], [W, 0, 0], [0, D, 0], [0, 0, -1], tx.CEILING),
        quad([x0, y1, z0], [W, 0, 0], [0, 0, H], [0, -1, 0], tx.WALL_BACK),
        quad([x0, y0, z0], [W, 0, 0], [0, 0, H], [0, 1, 0], tx.WALL_FRONT),
        quad([x0, y0, z0], [0, D, 0], [0, 0, H], [1, 0, 0], tx.WALL_LEFT),
        quad([x1, y0, z0], [0, D, 0], [0, 0, H], [-1, 0, 0], tx.WALL_RIGHT),
    ])


def _table(lo_xy, hi_xy, top_z, thickness=0.04, leg=0.05) -> list[tuple[np.ndarray, np.ndarray, object]]:
    lo_xy, hi_xy = np.asarray(lo_xy, float), np.asarray(hi_xy, float)
    parts = [(np.r_[lo_xy, top_z - thickness], np.r_[hi_xy, top_z], tx.WOOD)]
    for cx in (lo_xy[0] + 0.03, hi_xy[0] - 0.03 - leg):
        for cy in (lo_xy[1] + 0.03, hi_xy[1] - 0.03 - leg):
            parts.append((np.array([cx, cy, 0.0]), np.array([cx + leg, cy + leg, top_z - thickness]), tx.WOOD_DARK))
    return parts


def _furniture() -> list[tuple[np.ndarray, np.ndarray, object]]:
    W = tx.WOOD_DARK
    # Face order of mesh.box: +x, -x, +y, -y, +z, -z.
    return [
        (np.array([-0.9, 2.62, 0.0]), np.array([0.5, 3.0, 1.75]), [W, W, W, tx.BOOKS, W, W]),
        (np.array([-3.5, 0.2, 0.0]), np.array([-3.05, 1.8, 0.80]), [tx.DRAWERS, W, W, W, tx.WOOD, W]),
        (np.array([3.05, -1.9, 0.0]), np.array([3.5, -0.7, 1.05]), [W, tx.DRAWERS, W, W, tx.WOOD, W]),
        *_table(TABLE_XY_LO, TABLE_XY_HI, TABLE_TOP_Z),
    ]


def build_room() -> Room:
    parts = _furniture()
    meshes = [_shell()] + [box(lo, hi, mat) for lo, hi, mat in parts]
    (x0, y0, z0), (x1, y1, z1) = ROOM_LO, ROOM_HI
    planes = [
        PlaneSpec(np.array([0.0, 0.0, 1.0]), -z0, "floor"),
        PlaneSpec(np.array([0.0, 0.0, -1.0]), z1, "ceiling"),
        PlaneSpec(np.array([0.0, -1.0, 0.0]), y1, "wall_back"),
        PlaneSpec(np.array([0.0, 1.0, 0.0]), -y0, "wall_front"),
        PlaneSpec(np.array([1.0, 0.0, 0.0]), -x0, "wall_left"),
        PlaneSpec(np.array([-1.0, 0.0, 0.0]), x1, "wall_right"),
    ]
    return Room(mesh=concat(meshes), planes=planes, obstacles=[(lo, hi) for lo, hi, _ in parts])


def inside_free_space(points: np.ndarray, room: Room, margin: float = 0.3) -> np.ndarray:
    """[N] bool: point inside the room, at least `margin` from walls and furniture."""
    p = np.atleast_2d(points)
    ok = np.all((p > ROOM_LO + margin) & (p < ROOM_HI - margin), axis=1)
    for lo, hi in room.obstacles:
        ok &= ~np.all((p > lo - margin) & (p < hi + margin), axis=1)
    return ok
