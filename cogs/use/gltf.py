"""A small glTF 2.0 binary (.glb) writer: one buffer, accessors over numpy arrays.

Only what the export needs (float, unsigned byte/short accessors, nodes, meshes, skins,
animations); the JSON is assembled by the caller through `add_accessor` and the lists
in `doc`. Layout of a .glb (glTF 2.0 spec, "Binary glTF Layout"): a 12-byte header
(magic "glTF", version 2, total length), a JSON chunk padded with spaces and a BIN chunk
padded with zeros, each to 4 bytes.
"""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np

FLOAT, UNSIGNED_BYTE, UNSIGNED_SHORT = 5126, 5121, 5123
ARRAY_BUFFER = 34962
_TYPES = {1: "SCALAR", 2: "VEC2", 3: "VEC3", 4: "VEC4", 16: "MAT4"}
_DTYPES = {FLOAT: np.float32, UNSIGNED_BYTE: np.uint8, UNSIGNED_SHORT: np.uint16}


class GlbBuilder:
    """Collects binary data and the glTF JSON document; `write` emits the .glb."""

    def __init__(self, generator: str = "cogs"):
        self.doc: dict = {"asset": {"version": "2.0", "generator": generator}, "buffers": [], "bufferViews": [],
                          "accessors": [], "nodes": [], "meshes": [], "scenes": [], "scene": 0}
        self._bin = bytearray()

    def add_accessor(self, array: np.ndarray, component: int = FLOAT, *, vertex: bool = False,
                     minmax: bool = False, normalized: bool = False) -> int:
        """One accessor (and its buffer view) over `array` [count] or [count, n] (n in 1, 2,
        3, 4, 16); `vertex` marks a vertex attribute (bufferView target ARRAY_BUFFER);
        `minmax` records min and max (required for POSITION and animation times)."""
        a = np.ascontiguousarray(array, dtype=_DTYPES[component])
        count = a.shape[0]
        n = 1 if a.ndim == 1 else int(np.prod(a.shape[1:]))
        assert n in _TYPES, a.shape
        if component == FLOAT:
            assert np.isfinite(a).all(), "non-finite values in a glTF accessor"
        while len(self._bin) % 4:
            self._bin.append(0)
        view = {"buffer": 0, "byteOffset": len(self._bin), "byteLength": a.nbytes}
        if vertex:
            view["target"] = ARRAY_BUFFER
            # Vertex attribute strides must be multiples of 4: pad 1- and 2-byte elements.
            elem = a.dtype.itemsize * n
            if elem % 4:
                width = 4 // a.dtype.itemsize
                padded = np.zeros((count, width), a.dtype)
                padded[:, :n] = a.reshape(count, n)
                a = padded
                view["byteLength"] = a.nbytes
                view["byteStride"] = 4
        self._bin += a.tobytes()
        self.doc["bufferViews"].append(view)
        acc = {"bufferView": len(self.doc["bufferViews"]) - 1, "componentType": component, "count": count,
               "type": _TYPES[n]}
        if normalized:
            acc["normalized"] = True
        if minmax:
            flat = np.asarray(array, np.float64).reshape(count, n)
            acc["min"] = flat.min(0).tolist()
            acc["max"] = flat.max(0).tolist()
        self.doc["accessors"].append(acc)
        return len(self.doc["accessors"]) - 1

    def add_node(self, node: dict) -> int:
        self.doc["nodes"].append(node)
        return len(self.doc["nodes"]) - 1

    def add_mesh(self, mesh: dict) -> int:
        self.doc["meshes"].append(mesh)
        return len(self.doc["meshes"]) - 1

    def write(self, path: str | Path) -> None:
        while len(self._bin) % 4:
            self._bin.append(0)
        doc = dict(self.doc)
        doc["buffers"] = [{"byteLength": len(self._bin)}]
        for key in ("skins", "animations", "extensionsUsed"):
            if key in doc and not doc[key]:
                del doc[key]
        js = json.dumps(doc, separators=(",", ":")).encode()
        js += b" " * (-len(js) % 4)
        total = 12 + 8 + len(js) + 8 + len(self._bin)
        out = struct.pack("<4sII", b"glTF", 2, total)
        out += struct.pack("<I4s", len(js), b"JSON") + js
        out += struct.pack("<I4s", len(self._bin), b"BIN\x00") + bytes(self._bin)
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        Path(path).write_bytes(out)


def trs(matrix: np.ndarray) -> dict:
    """A rigid 4x4 as a glTF node's translation and rotation (xyzw)."""
    from cogs.geometry.rotations import rotmat_to_quat
    import torch

    q = rotmat_to_quat(torch.from_numpy(np.asarray(matrix[:3, :3], np.float64))).numpy()
    return {"translation": matrix[:3, 3].tolist(), "rotation": [q[1], q[2], q[3], q[0]]}
