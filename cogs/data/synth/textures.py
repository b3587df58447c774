"""Procedural textures and lighting of the synthetic scene.

Every surface colour is a pure function of per-sample texture coordinates, evaluated at
each supersample by `albedo`; nothing is stored as an image. Feature sizes are kept at
several output pixels (stripes and tiles of 10-40 cm, seen from 2-4 m at 256x192 with a
55 degree field of view: about 60 px per metre at 3 m) so that a Gaussian-splatting model
trained briefly on CPU can reproduce them; edges are softened over ~1 cm so the 3x3
supersampling does not alias.

Body: texture coordinates are canonical (zero-pose) vertex positions plus per-vertex
body-part weights (see `body_part_weights`); the clothing is laid out relative to the
canonical joints (`BodyLayout`). It is deliberately asymmetric: short red left sleeve and
long green right sleeve, a chest logo on the left, stripes on the front and checks on the
back, a knee patch on the right leg and a back pocket on the left.

Object: a box whose six faces each have their own colour and mark (rotation observable).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# Material ids (per face). Room/furniture texture coordinates are metres on the face.
BODY = 1
OBJECT_BOX = 2
FLOOR = 10
WALL_BACK = 11
WALL_LEFT = 12
WALL_RIGHT = 13
WALL_FRONT = 14
CEILING = 15
WOOD = 20
WOOD_DARK = 21
BOOKS = 22
DRAWERS = 23

# Body part groups: bone-name prefixes per group (suffix .L/.R matched separately).
PART_GROUPS = ("torso", "head", "arm.L", "arm.R", "hand.L", "hand.R", "leg.L", "leg.R", "foot.L", "foot.R")
_GROUP_PREFIXES = {
    "head": ("neck", "head", "eye"),
    "arm": ("upperarm", "lowerarm"),
    "hand": ("wrist", "finger", "metacarpal"),
    "leg": ("upperleg", "lowerleg"),
    "foot": ("foot", "toe"),
}

# Light, fixed in the world: ambient + two Lambert terms (a key from the upper front-left
# of the room, a weak fill from the opposite side). No shadows.
AMBIENT = 0.42
KEY_DIR = np.array([0.35, -0.55, 0.76]) / np.linalg.norm([0.35, -0.55, 0.76])
KEY = 0.50
FILL_DIR = np.array([-0.6, 0.5, 0.3]) / np.linalg.norm([-0.6, 0.5, 0.3])
FILL = 0.16


def shade(albedo: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Lambert shading of albedo [N, 3] with world normals [N, 3] (need not be unit)."""
    n = normals / np.maximum(np.linalg.norm(normals, axis=-1, keepdims=True), 1e-9)
    light = AMBIENT + KEY * np.clip(n @ KEY_DIR, 0.0, None) + FILL * np.clip(n @ FILL_DIR, 0.0, None)
    return albedo * light[:, None]


# -- small pattern helpers (vectorised over samples) -------------------------------------------


def _smooth(edge0, edge1, x):
    t = np.clip((x - edge0) / (edge1 - edge0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _band(x, period, duty, soft=0.01, phase=0.0):
    """1 inside the first `duty` fraction of each period, 0 elsewhere, soft edges (same units)."""
    f = np.mod(x / period + phase, 1.0) * period
    w = duty * period
    return _smooth(0.0, soft, f) * (1.0 - _smooth(w - soft, w, f))


def _inside_rect(u, v, u0, u1, v0, v1, soft=0.008):
    return _smooth(u0 - soft, u0 + soft, u) * (1 - _smooth(u1 - soft, u1 + soft, u)) * \
        _smooth(v0 - soft, v0 + soft, v) * (1 - _smooth(v1 - soft, v1 + soft, v))


def _inside_disc(u, v, cu, cv, r, soft=0.008):
    return 1.0 - _smooth(r - soft, r + soft, np.hypot(u - cu, v - cv))


def _hash(*ints) -> np.ndarray:
    """Deterministic pseudo-random value in [0, 1) per integer cell."""
    h = np.zeros(np.broadcast(*ints).shape, dtype=np.uint64)
    with np.errstate(over="ignore"):
        return _hash_mix(h, ints)


def _hash_mix(h, ints):
    for k, a in enumerate(ints):
        h ^= (np.asarray(a).astype(np.int64).astype(np.uint64) + np.uint64(0x9E3779B97F4A7C15 + k)) * np.uint64(0xBF58476D1CE4E5B9)
        h ^= h >> np.uint64(31)
        h *= np.uint64(0x94D049BB133111EB)
        h ^= h >> np.uint64(29)
    return (h >> np.uint64(11)).astype(np.float64) / float(1 << 53)


def _mix(a, b, t):
    """Blend colours a -> b by t ([N] in [0, 1]); a, b are [3] or [N, 3]."""
    return np.asarray(a, dtype=np.float64) * (1.0 - t[:, None]) + np.asarray(b, dtype=np.float64) * t[:, None]


def _col(c, n):
    return np.broadcast_to(np.asarray(c, dtype=np.float64), (n, 3)).copy()


# -- room -------------------------------------------------------------------------------------


def _floor(u, v):
    """Oak boards 20 cm wide along x, staggered joints, a red rug with a border and a motif."""
    n = len(u)
    board = np.floor(v / 0.20)
    shift = _hash(board, 1) * 1.4
    plank = np.floor((u + shift) / 1.4)
    tone = 0.82 + 0.3 * _hash(board, plank)
    grain = 0.06 * np.sin(2 * np.pi * (u + shift) / 0.37 + 3.0 * _hash(board, plank, 2))
    base = _col([0.66, 0.47, 0.30], n) * (tone + grain)[:, None]
    seam = 1.0 - 0.35 * (1.0 - _smooth(0.0, 0.015, np.minimum(np.mod(v, 0.20), 0.20 - np.mod(v, 0.20))))
    joint_d = np.minimum(np.mod(u + shift, 1.4), 1.4 - np.mod(u + shift, 1.4))
    seam *= 1.0 - 0.3 * (1.0 - _smooth(0.0, 0.015, joint_d))
    col = base * seam[:, None]
    # Rug (u, v = world x + 3.5, y + 3.0): x in [-1.4, 1.0], y in [-1.9, -0.5].
    x, y = u - 3.5, v - 3.0
    rug = _inside_rect(x, y, -1.4, 1.0, -1.9, -0.5, soft=0.01)
    border = 1.0 - _inside_rect(x, y, -1.28, 0.88, -1.78, -0.62, soft=0.01)
    diamond = 1.0 - _smooth(0.30, 0.32, np.abs(x + 0.2) / 1.0 + np.abs(y + 1.2) / 0.55)
    rug_col = _mix(_mix([0.62, 0.16, 0.15], [0.90, 0.84, 0.66], border), [0.16, 0.22, 0.45], diamond * (1 - border))
    return _mix(col, rug_col, rug)


def _wall_back(u, v):
    """Striped wallpaper above a dado rail, panelled wainscot below, two pictures."""
    n = len(u)
    stripes = _band(u, 0.30, 0.5, soft=0.012)
    col = _mix([0.86, 0.80, 0.66], [0.72, 0.64, 0.52], stripes)
    wains = _mix([0.50, 0.36, 0.28], [0.42, 0.30, 0.23], 1 - _smooth(0.0, 0.02, np.minimum(np.mod(u, 0.6), 0.6 - np.mod(u, 0.6))))
    col = _mix(col, wains, 1 - _smooth(0.88, 0.90, v))
    rail = _inside_rect(u, v, -1, 99, 0.88, 0.96)
    col = _mix(col, [0.30, 0.20, 0.14], rail)
    # Landscape painting: u in [0.9, 2.1] (world x -2.6..-1.4), v in [1.2, 2.0].
    x0, x1, z0, z1 = 0.9, 2.1, 1.20, 2.00
    frame = _inside_rect(u, v, x0, x1, z0, z1)
    inner = _inside_rect(u, v, x0 + 0.05, x1 - 0.05, z0 + 0.05, z1 - 0.05)
    hills = v < z0 + 0.30 + 0.10 * np.sin((u - x0) * 5.0)
    pic = _mix(_col([0.45, 0.68, 0.90], n), [0.28, 0.58, 0.22], hills.astype(np.float64))
    pic = _mix(pic, [0.98, 0.82, 0.20], _inside_disc(u, v, x0 + 0.85, z0 + 0.58, 0.10))
    pic = _mix(pic, [0.80, 0.22, 0.18], _inside_rect(u, v, x0 + 0.25, x0 + 0.45, z0 + 0.18, z0 + 0.38))
    col = _mix(col, _mix(_col([0.25, 0.16, 0.10], n), pic, inner), frame)
    # Block-colour print: u in [5.0, 5.9] (world x 1.5..2.4), v in [1.1, 1.9].
    a0, a1, b0, b1 = 5.0, 5.9, 1.10, 1.90
    print_ = _inside_rect(u, v, a0, a1, b0, b1)
    cell_u = np.clip(np.floor((u - a0) / 0.3), 0, 2)
    cell_v = np.clip(np.floor((v - b0) / 0.4), 0, 1)
    palette = np.array([[0.85, 0.15, 0.12], [0.95, 0.95, 0.92], [0.12, 0.25, 0.65],
                        [0.98, 0.82, 0.15], [0.95, 0.95, 0.92], [0.85, 0.15, 0.12]])
    blocks = palette[(cell_u + 3 * cell_v).astype(np.int64) % 6]
    lines = (1 - _smooth(0.0, 0.025, np.minimum(np.mod(u - a0, 0.3), 0.3 - np.mod(u - a0, 0.3)))) + \
        (1 - _smooth(0.0, 0.025, np.minimum(np.mod(v - b0, 0.4), 0.4 - np.mod(v - b0, 0.4))))
    blocks = _mix(blocks, [0.08, 0.08, 0.08], np.clip(lines, 0, 1))
    return _mix(col, blocks, print_)


def _wall_left(u, v):
    """Sage wallpaper with a diamond lattice, and a dark door (u = world y + 3)."""
    a = np.mod(u / 0.40 + v / 0.40, 1.0)
    b = np.mod(u / 0.40 - v / 0.40, 1.0)
    line = np.clip((1 - _smooth(0.0, 0.07, np.minimum(a, 1 - a))) + (1 - _smooth(0.0, 0.07, np.minimum(b, 1 - b))), 0, 1)
    col = _mix([0.70, 0.78, 0.64], [0.44, 0.55, 0.42], line)
    door = _inside_rect(u, v, 4.1, 5.0, -1.0, 2.05)
    panel = _inside_rect(u, v, 4.22, 4.88, 1.10, 1.90) + _inside_rect(u, v, 4.22, 4.88, 0.15, 0.95)
    door_col = _mix(_col([0.36, 0.22, 0.14], len(u)), [0.46, 0.30, 0.19], np.clip(panel, 0, 1))
    door_col = _mix(door_col, [0.85, 0.72, 0.30], _inside_disc(u, v, 4.92, 1.0, 0.025, soft=0.005))
    return _mix(col, door_col, door)


def _wall_right(u, v):
    """Painted brick: 40 x 15 cm bricks, staggered rows, per-brick tone (u = world y + 3)."""
    row = np.floor(v / 0.15)
    uu = u + 0.2 * np.mod(row, 2)
    brick = np.floor(uu / 0.40)
    tone = 0.85 + 0.25 * _hash(row, brick, 7)
    col = _col([0.74, 0.42, 0.33], len(u)) * tone[:, None]
    mortar = np.maximum(1 - _smooth(0.0, 0.018, np.minimum(np.mod(v, 0.15), 0.15 - np.mod(v, 0.15))),
                        1 - _smooth(0.0, 0.018, np.minimum(np.mod(uu, 0.40), 0.40 - np.mod(uu, 0.40))))
    return _mix(col, [0.85, 0.82, 0.76], mortar)


def _wall_front(u, v):
    """Pale blue with large white dots on a staggered grid (u = world x + 3.5)."""
    row = np.floor(v / 0.45)
    uu = u + 0.225 * np.mod(row, 2)
    du = np.mod(uu, 0.45) - 0.225
    dv = np.mod(v, 0.45) - 0.225
    dots = 1 - _smooth(0.08, 0.095, np.hypot(du, dv))
    return _mix([0.62, 0.74, 0.86], [0.95, 0.95, 0.92], dots)


def _ceiling(u, v):
    grid = np.maximum(1 - _smooth(0.0, 0.02, np.minimum(np.mod(u, 0.6), 0.6 - np.mod(u, 0.6))),
                      1 - _smooth(0.0, 0.02, np.minimum(np.mod(v, 0.6), 0.6 - np.mod(v, 0.6))))
    return _mix([0.93, 0.92, 0.88], [0.70, 0.70, 0.68], grid)


def _wood(u, v, dark=False):
    base = [0.42, 0.27, 0.16] if dark else [0.66, 0.44, 0.26]
    g = 0.10 * np.sin(2 * np.pi * u / 0.09 + 1.5 * np.sin(2 * np.pi * v / 0.5)) + 0.05 * np.sin(2 * np.pi * u / 0.23)
    return _col(base, len(u)) * (1.0 + g)[:, None]


def _books(u, v):
    """Bookshelf front: shelf boards every 40 cm, books of varied width, height and colour."""
    n = len(u)
    shelf = np.floor(v / 0.40)
    local = v - shelf * 0.40
    book = np.floor(u / 0.09 + 0.6 * _hash(shelf, 3))
    h = 0.22 + 0.12 * _hash(shelf, book, 5)
    palette = np.array([[0.70, 0.15, 0.15], [0.15, 0.35, 0.65], [0.85, 0.70, 0.20], [0.20, 0.55, 0.30],
                        [0.55, 0.25, 0.55], [0.90, 0.88, 0.80], [0.20, 0.20, 0.25], [0.85, 0.45, 0.15]])
    books = palette[(_hash(shelf, book, 11) * 8).astype(np.int64) % 8]
    present = (_hash(shelf, book, 13) > 0.15).astype(np.float64)
    in_book = (local > 0.03) & (local < 0.03 + h)
    back = _col([0.30, 0.20, 0.13], n)
    col = _mix(back, books, in_book * present)
    board = local < 0.03
    return _mix(col, _wood(u, v, dark=True), board.astype(np.float64))


def _drawers(u, v):
    """Sideboard front: three drawers with dark gaps and round brass knobs."""
    col = _wood(u, v)
    row = np.floor(v / 0.25)
    lv = v - row * 0.25
    gap = 1 - _smooth(0.0, 0.012, np.minimum(lv, 0.25 - lv))
    col = _mix(col, [0.20, 0.13, 0.08], gap)
    knob = _inside_disc(np.mod(u, 0.6), lv, 0.30, 0.125, 0.03, soft=0.006)
    return _mix(col, [0.85, 0.70, 0.30], knob)


# -- object -----------------------------------------------------------------------------------

BOX_SIZE = np.array([0.30, 0.22, 0.18])  # metres along the box's local x, y, z


def _object_box(u, v, face):
    """Each face its own colour and mark; (u, v) in metres from the face's low corner."""
    n = len(u)
    out = np.zeros((n, 3))
    f = np.rint(face).astype(np.int64)
    specs = {
        0: ([0.85, 0.18, 0.15], "band"),  # +x: red, white band
        1: ([0.10, 0.55, 0.55], "disc"),  # -x: teal, yellow disc
        2: ([0.95, 0.80, 0.15], "diag"),  # +y: yellow, blue diagonal
        3: ([0.15, 0.30, 0.75], "check"),  # -y: blue, white 2x2 checks
        4: ([0.20, 0.62, 0.25], "cross"),  # +z: green, white cross
        5: ([0.60, 0.42, 0.25], "square"),  # -z: cardboard, dark square
    }
    for k, (base, mark) in specs.items():
        sel = f == k
        if not sel.any():
            continue
        uu, vv = u[sel], v[sel]
        du, dv = _face_extent(k)
        cu, cv = du / 2, dv / 2
        c = _col(base, len(uu))
        if mark == "band":
            c = _mix(c, [0.95, 0.95, 0.92], _inside_rect(uu, vv, -1, 9, cv - 0.03, cv + 0.03))
        elif mark == "disc":
            c = _mix(c, [0.98, 0.85, 0.20], _inside_disc(uu, vv, cu, cv, 0.06))
        elif mark == "diag":
            c = _mix(c, [0.15, 0.25, 0.70], 1 - _smooth(0.025, 0.035, np.abs((uu - cu) - (vv - cv))))
        elif mark == "check":
            c = _mix(c, [0.95, 0.95, 0.92], ((uu > cu) ^ (vv > cv)).astype(np.float64))
        elif mark == "cross":
            cross = np.maximum(_inside_rect(uu, vv, cu - 0.025, cu + 0.025, -1, 9), _inside_rect(uu, vv, -1, 9, cv - 0.025, cv + 0.025))
            c = _mix(c, [0.95, 0.95, 0.92], cross)
        elif mark == "square":
            c = _mix(c, [0.25, 0.18, 0.12], _inside_rect(uu, vv, cu - 0.05, cu + 0.05, cv - 0.05, cv + 0.05))
        out[sel] = c
    return out


def _face_extent(face: int) -> tuple[float, float]:
    """(u, v) extent in metres of box face `face` (edges as built by `mesh.box`)."""
    sx, sy, sz = BOX_SIZE
    return {0: (sy, sz), 1: (sy, sz), 2: (sx, sz), 3: (sx, sz), 4: (sx, sy), 5: (sx, sy)}[face]


# -- body -------------------------------------------------------------------------------------


def body_part_weights(bone_names: list[str], weights: np.ndarray) -> np.ndarray:
    """Skinning weights [V, J] -> per-vertex one-hot body-part groups [V, len(PART_GROUPS)].

    Each vertex goes to the group holding most of its skinning weight; interpolating the
    one-hot rows and taking the argmax per sample gives smooth part boundaries.
    """
    G = np.zeros((weights.shape[1], len(PART_GROUPS)))
    for j, name in enumerate(bone_names):
        base, _, side = name.partition(".")
        group = "torso"
        for g, prefixes in _GROUP_PREFIXES.items():
            if base.startswith(prefixes):
                group = g if g == "head" else f"{g}.{side}"
                break
        G[j, PART_GROUPS.index(group)] = 1.0
    summed = weights @ G
    return np.eye(len(PART_GROUPS))[np.argmax(summed, axis=1)]


@dataclass
class BodyLayout:
    """Canonical-space landmarks (metres) the clothing is laid out against."""

    belt_top: float
    belt_bottom: float
    hem: float  # trouser hem (above the ankle)
    sole: float  # top of the shoe sole
    chest: float
    spine_y: float
    head: np.ndarray  # [3]
    eye_z: float
    neck_z: float
    shoulder_l: np.ndarray
    wrist_l: np.ndarray
    shoulder_r: np.ndarray
    wrist_r: np.ndarray
    knee_r: np.ndarray

    @classmethod
    def from_joints(cls, bone_names: list[str], joints: np.ndarray, vertices: np.ndarray) -> "BodyLayout":
        j = {n: joints[i] for i, n in enumerate(bone_names)}
        hip = j["upperleg01.L"][2]
        return cls(
            belt_top=hip + 0.035,
            belt_bottom=hip - 0.01,
            hem=j["foot.L"][2] + 0.09,
            sole=vertices[:, 2].min() + 0.025,
            chest=0.5 * (j["spine01"][2] + j["spine02"][2]),
            spine_y=j["spine02"][1],
            head=j["head"],
            eye_z=j["eye.L"][2],
            neck_z=j["neck02"][2],
            shoulder_l=j["upperarm01.L"],
            wrist_l=j["wrist.L"],
            shoulder_r=j["upperarm01.R"],
            wrist_r=j["wrist.R"],
            knee_r=j["lowerleg01.R"],
        )


SKIN = np.array([0.88, 0.66, 0.52])
HAIR = np.array([0.20, 0.12, 0.07])


def _arm_param(p, shoulder, wrist):
    d = wrist - shoulder
    return ((p - shoulder) @ d) / (d @ d)


def _body(xyz, parts, L: BodyLayout):
    n = len(xyz)
    x, y, z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    g = np.argmax(parts, axis=1)
    gi = {name: i for i, name in enumerate(PART_GROUPS)}
    out = np.zeros((n, 3))

    def put(mask, colours):
        out[mask] = colours[mask] if np.ndim(colours) == 2 else colours

    # Shirt: front horizontal stripes + logo on the left chest; back: two-tone checks.
    front = y < L.spine_y
    stripes = _band(z, 0.14, 0.5, soft=0.012)
    shirt_front = _mix([0.13, 0.18, 0.40], [0.92, 0.88, 0.76], stripes)
    logo = _inside_disc(x, z, 0.085, L.chest, 0.055)
    shirt_front = _mix(shirt_front, [0.98, 0.80, 0.10], logo)
    shirt_front = _mix(shirt_front, [0.85, 0.15, 0.12], _inside_disc(x, z, 0.085, L.chest, 0.025))
    checks = (np.floor(x / 0.13) + np.floor(z / 0.13)) % 2
    shirt_back = _mix([0.78, 0.50, 0.16], [0.40, 0.46, 0.16], checks)
    shirt = np.where(front[:, None], shirt_front, shirt_back)
    # Trousers: denim with a light tartan, an orange right-knee patch, a left back pocket.
    tart = np.clip(_band(z, 0.11, 0.25, soft=0.01) + _band(x, 0.11, 0.25, soft=0.01, phase=0.3), 0, 1)
    trousers = _mix([0.22, 0.30, 0.48], [0.42, 0.50, 0.66], 0.6 * tart)
    k = L.knee_r
    patch = _inside_rect(x, z, k[0] - 0.06, k[0] + 0.06, k[2] - 0.06, k[2] + 0.08) * (y < k[1])
    trousers = _mix(trousers, [0.92, 0.50, 0.12], patch)
    pocket = _inside_rect(x, z, 0.03, 0.14, L.belt_bottom - 0.14, L.belt_bottom - 0.03) * (y > L.spine_y + 0.02)
    trousers = _mix(trousers, [0.12, 0.16, 0.28], pocket)
    belt = _mix(_col([0.22, 0.14, 0.09], n), [0.90, 0.75, 0.25], _inside_rect(x, z, -0.03, 0.03, L.belt_bottom, L.belt_top) * front)
    # Shoes: charcoal, white soles; the left shoe has a white side stripe.
    shoe = _mix(_col([0.20, 0.20, 0.23], n), [0.92, 0.92, 0.90], (z < L.sole).astype(np.float64))
    shoe = _mix(shoe, [0.92, 0.92, 0.90], ((x > 0) & (np.abs(z - (L.sole + 0.03)) < 0.012)).astype(np.float64))

    torso = g == gi["torso"]
    put(torso & (z >= L.belt_top), shirt)
    put(torso & (z < L.belt_top) & (z >= L.belt_bottom), belt)
    put(torso & (z < L.belt_bottom), trousers)
    legs = (g == gi["leg.L"]) | (g == gi["leg.R"])
    put(legs & (z >= L.hem), trousers)
    put(legs & (z < L.hem), shoe)
    feet = (g == gi["foot.L"]) | (g == gi["foot.R"])
    put(feet, shoe)
    # Sleeves: short red on the left, long green with two cuff rings on the right.
    arm_l = g == gi["arm.L"]
    s_l = _arm_param(xyz, L.shoulder_l, L.wrist_l)
    sleeve_l = _mix(_col([0.80, 0.14, 0.14], n), [0.95, 0.93, 0.88], ((s_l > 0.34) & (s_l < 0.40)).astype(np.float64))
    put(arm_l & (s_l < 0.40), sleeve_l)
    put(arm_l & (s_l >= 0.40), SKIN)
    arm_r = g == gi["arm.R"]
    s_r = _arm_param(xyz, L.shoulder_r, L.wrist_r)
    cuffs = (np.abs(s_r - 0.78) < 0.03) | (np.abs(s_r - 0.86) < 0.03)
    sleeve_r = _mix(_col([0.16, 0.58, 0.30], n), [0.95, 0.93, 0.88], cuffs.astype(np.float64))
    put(arm_r & (s_r < 0.92), sleeve_r)
    put(arm_r & (s_r >= 0.92), SKIN)
    hands = (g == gi["hand.L"]) | (g == gi["hand.R"])
    put(hands, SKIN)
    # Head: skin face and neck, dark hair on top and at the back.
    head = g == gi["head"]
    hair = (z > L.eye_z + 0.035) | ((y > L.head[1] - 0.005) & (z > L.neck_z + 0.02))
    put(head & ~hair, SKIN)
    put(head & hair, HAIR * (1.0 + 0.15 * np.sin(x / 0.02))[:, None])
    return out


# -- dispatch ---------------------------------------------------------------------------------

_ROOM = {
    FLOOR: _floor,
    WALL_BACK: _wall_back,
    WALL_LEFT: _wall_left,
    WALL_RIGHT: _wall_right,
    WALL_FRONT: _wall_front,
    CEILING: _ceiling,
    WOOD: _wood,
    WOOD_DARK: lambda u, v: _wood(u, v, dark=True),
    BOOKS: _books,
    DRAWERS: _drawers,
}


def albedo(material: np.ndarray, texcoords: np.ndarray, parts: np.ndarray | None,
           layout: BodyLayout | None) -> np.ndarray:
    """Surface colour [N, 3] in [0, 1] of N samples.

    material: [N] int ids; texcoords: [N, 3] (room/objects: u, v metres and a face id;
    body: canonical xyz); parts: [N, len(PART_GROUPS)] interpolated part one-hots (body).
    """
    out = np.zeros((len(material), 3))
    for m in np.unique(material):
        sel = material == m
        tc = texcoords[sel].astype(np.float64)
        if m == BODY:
            out[sel] = _body(tc, parts[sel], layout)
        elif m == OBJECT_BOX:
            out[sel] = _object_box(tc[:, 0], tc[:, 1], tc[:, 2])
        elif m in _ROOM:
            out[sel] = _ROOM[int(m)](tc[:, 0], tc[:, 1])
        else:
            out[sel] = 0.5
    return np.clip(out, 0.0, 1.0)


# -- baking static textures -------------------------------------------------------------------


@dataclass
class BakedTextures:
    """Static surfaces' albedo sampled once on texel grids, looked up per sample.

    The room never changes, so its procedural textures are evaluated once per generation
    on a `texel`-metre grid per quad (bilinear lookup afterwards) instead of at every
    supersample of every frame.
    """

    face_tex: np.ndarray  # [F] int32 texture index per face, -1 = shade procedurally
    data: np.ndarray  # [N, 3] float32 texels of all textures, row-major per texture
    meta: np.ndarray  # [n_tex, 6] float64: offset, width, height, u0, v0, texel size


def bake(material: np.ndarray, texcoords: np.ndarray, faces: np.ndarray, texel: float = 0.01) -> BakedTextures:
    """Bake the textures of a mesh made of quads (face pairs 2k, 2k+1 share one texture)."""
    F = len(faces)
    assert F % 2 == 0, "static meshes are built from quads"
    face_tex = np.empty(F, dtype=np.int32)
    chunks, meta, offset = [], [], 0
    for q in range(F // 2):
        f0, f1 = 2 * q, 2 * q + 1
        assert material[f0] == material[f1]
        tc = texcoords[np.unique(faces[[f0, f1]])]
        u0, v0 = tc[:, 0].min(), tc[:, 1].min()
        nu = int(np.ceil((tc[:, 0].max() - u0) / texel)) + 2
        nv = int(np.ceil((tc[:, 1].max() - v0) / texel)) + 2
        vv, uu = np.meshgrid(v0 + texel * np.arange(nv), u0 + texel * np.arange(nu), indexing="ij")
        m = np.full(nu * nv, material[f0])
        tcs = np.stack([uu.ravel(), vv.ravel(), np.full(nu * nv, tc[0, 2])], axis=1)
        chunks.append(albedo(m, tcs, None, None).astype(np.float32))
        meta.append([offset, nu, nv, u0, v0, texel])
        face_tex[[f0, f1]] = q
        offset += nu * nv
    return BakedTextures(face_tex=face_tex, data=np.concatenate(chunks), meta=np.array(meta, dtype=np.float64))
