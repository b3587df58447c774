"""Read the pickles public datasets ship, without letting them run code.

A pickle is a program: loading one with `pickle.load` (or `joblib.load`, or `np.load(...,
allow_pickle=True)`) calls whatever functions it names, so a doctored `mesh_infos.pkl` could
run `os.system`. The benchmarks cogs imports only ever store plain containers and numpy
arrays, so this module loads pickles through an unpickler that resolves exactly the globals
those need and refuses every other one with a `UserError` naming the file and the global.

Accepted:
    * builtins containers and scalars (dict, list, tuple, set, frozenset, bytearray, complex,
      `collections.OrderedDict`), and `_codecs.encode`, which protocol-0..2 pickles written by
      Python 3 use to spell `bytes`;
    * numpy arrays, dtypes and scalars, under both the numpy 1.x (`numpy.core.*`) and the
      numpy 2.x (`numpy._core.*`) module paths, including protocol-5 `_frombuffer` arrays;
    * Python 2 pickles (str payloads decoded as latin-1, `__builtin__`/`copy_reg` names
      mapped to their Python 3 homes);
    * joblib's uncompressed, zlib- or gzip-compressed files (NeuMan's
      `smpl_output_optimized.pkl` is one): joblib writes each array's bytes right after a
      `NumpyArrayWrapper` record, which is read here as data, never by importing joblib;
    * `.npy` files whose payload is a pickled object array (NeuMan's `alignments.npy`).

Refused: everything else, e.g. `os.system`, `subprocess.Popen`, `builtins.eval`,
`builtins.getattr`, arbitrary classes, and chumpy arrays (`chumpy.ch.Ch`), for which the
message says how to convert the file.
"""

from __future__ import annotations

import _compat_pickle
import gzip
import io
import pickle
import zlib
from pathlib import Path
from typing import Any

import numpy as np

from cogs.errors import UserError

__all__ = ["load_pickle", "load_npy", "RefusedGlobal"]


class RefusedGlobal(pickle.UnpicklingError):
    """A pickle named a global outside the allow-list."""

    def __init__(self, module: str, name: str):
        self.module, self.name = module, name
        super().__init__(f"{module}.{name}")


def _numpy_core(sub: str):
    """numpy's private core module `sub` (numpy 2.x: numpy._core.sub; 1.x: numpy.core.sub)."""
    import importlib

    try:
        return importlib.import_module(f"numpy._core.{sub}")
    except ImportError:  # numpy 1.x
        return importlib.import_module(f"numpy.core.{sub}")


class _JoblibArray:
    """Stand-in for joblib's NumpyArrayWrapper: only its state (shape, dtype, order) is used."""


def _allowed_globals() -> dict[tuple[str, str], Any]:
    import collections
    import _codecs

    multiarray = _numpy_core("multiarray")
    numeric = _numpy_core("numeric")
    table: dict[tuple[str, str], Any] = {
        ("builtins", "dict"): dict,
        ("builtins", "list"): list,
        ("builtins", "tuple"): tuple,
        ("builtins", "set"): set,
        ("builtins", "frozenset"): frozenset,
        ("builtins", "bytearray"): bytearray,
        ("builtins", "complex"): complex,
        ("collections", "OrderedDict"): collections.OrderedDict,
        # Python 3 writes `bytes` as _codecs.encode(str, 'latin1') under protocols 0-2.
        ("_codecs", "encode"): _codecs.encode,
        ("numpy", "ndarray"): np.ndarray,
        ("numpy", "dtype"): np.dtype,
        ("joblib.numpy_pickle", "NumpyArrayWrapper"): _JoblibArray,
    }
    for prefix in ("numpy.core", "numpy._core"):
        table[(f"{prefix}.multiarray", "_reconstruct")] = multiarray._reconstruct
        table[(f"{prefix}.multiarray", "scalar")] = multiarray.scalar
        table[(f"{prefix}.numeric", "_frombuffer")] = numeric._frombuffer
    # numpy scalar and dtype classes (`numpy.float64`, `numpy.dtypes.Float64DType`) appear as
    # globals in some pickles; they are plain data types.
    for name in ("bool_", "int8", "int16", "int32", "int64", "uint8", "uint16", "uint32", "uint64",
                 "float16", "float32", "float64", "complex64", "complex128", "str_", "bytes_"):
        table[("numpy", name)] = getattr(np, name)
    return table


_ALLOWED: dict[tuple[str, str], Any] | None = None

_CONVERT_HINT = {
    "chumpy": (
        "it holds chumpy objects (the format of the original SMPL release); convert them to "
        "numpy arrays first, in an environment that has chumpy: load the file, replace every "
        "chumpy value v by numpy.array(v) (recursively), and pickle the result again"
    ),
    "joblib": (
        "this joblib record type is not supported; load the file with joblib in a trusted "
        "environment and save its arrays with numpy.savez"
    ),
    "torch": "it holds torch objects; save plain numpy arrays (tensor.numpy()) instead",
}


class _SafeUnpickler(pickle._Unpickler):  # the pure-Python unpickler: its dispatch table is extensible
    dispatch = dict(pickle._Unpickler.dispatch)

    def __init__(self, file, *, encoding: str = "ASCII"):
        super().__init__(file, encoding=encoding, errors="strict")
        self._file = file

    def find_class(self, module: str, name: str):
        global _ALLOWED
        if _ALLOWED is None:
            _ALLOWED = _allowed_globals()
        if self.proto < 3:  # Python 2 names: __builtin__.set, copy_reg._reconstructor, ...
            if (module, name) in _compat_pickle.NAME_MAPPING:
                module, name = _compat_pickle.NAME_MAPPING[(module, name)]
            elif module in _compat_pickle.IMPORT_MAPPING:
                module = _compat_pickle.IMPORT_MAPPING[module]
        try:
            return _ALLOWED[(module, name)]
        except KeyError:
            raise RefusedGlobal(module, name) from None

    def persistent_load(self, pid):
        raise pickle.UnpicklingError(f"persistent id {pid!r} (not plain data)")

    def _load_build(self):
        if isinstance(self.stack[-2] if len(self.stack) > 1 else None, type):
            # BUILD on a class would set attributes on it (e.g. on the joblib stand-in).
            raise pickle.UnpicklingError("BUILD applied to a class")
        pickle._Unpickler.load_build(self)
        top = self.stack[-1]
        if isinstance(top, _JoblibArray):
            self.stack[-1] = self._read_joblib_array(top)

    dispatch[pickle.BUILD[0]] = _load_build

    def _read_joblib_array(self, wrapper: _JoblibArray) -> np.ndarray:
        state = wrapper.__dict__
        try:
            shape = tuple(int(s) for s in state["shape"])
            dtype = np.dtype(state["dtype"])
            order = state.get("order", "C")
        except (KeyError, TypeError, ValueError) as e:
            raise pickle.UnpicklingError(f"malformed joblib array record ({e})") from None
        # The array's bytes follow the record directly in the file, outside any pickle frame.
        raw = self._file
        if dtype.hasobject:
            inner = _SafeUnpickler(raw, encoding=self.encoding)
            return np.asarray(inner.load(), dtype=object).reshape(shape)
        if state.get("numpy_array_alignment_bytes") is not None:
            pad = raw.read(1)
            if len(pad) != 1:
                raise pickle.UnpicklingError("truncated joblib array padding")
            raw.read(pad[0])
        count = int(np.prod(shape, dtype=np.int64)) if shape else 1
        nbytes = count * dtype.itemsize
        data = raw.read(nbytes)
        if len(data) != nbytes:
            raise pickle.UnpicklingError(f"truncated joblib array: wanted {nbytes} bytes, got {len(data)}")
        arr = np.frombuffer(data, dtype=dtype, count=count).copy()
        arr = arr.reshape(shape[::-1]).T if order == "F" else arr.reshape(shape)
        if not arr.dtype.isnative:
            arr = arr.astype(arr.dtype.newbyteorder("="))
        return arr


def _refusal(path: Path, e: RefusedGlobal) -> UserError:
    top = e.module.split(".")[0]
    hint = _CONVERT_HINT.get(top, "only numpy arrays and plain containers are accepted")
    return UserError(
        f"{path}: refusing to load this pickle: it names the global `{e.module}.{e.name}`, "
        f"which cogs does not run ({hint})"
    )


def _unpickle_bytes(data: bytes, path: Path) -> Any:
    # ASCII first (Python 3 pickles never need a decode); latin-1 is the documented way to
    # read Python 2 pickles that hold numpy arrays (their buffers are py2 `str`).
    last: Exception | None = None
    for encoding in ("ASCII", "latin1"):
        try:
            return _SafeUnpickler(io.BytesIO(data), encoding=encoding).load()
        except RefusedGlobal as e:
            raise _refusal(path, e) from None
        except UnicodeDecodeError as e:
            last = e
            continue
        except (pickle.UnpicklingError, EOFError, ValueError, TypeError, IndexError, KeyError,
                AttributeError, OverflowError, MemoryError) as e:
            raise UserError(f"{path}: not a readable pickle ({type(e).__name__}: {e})") from None
    raise UserError(f"{path}: not a readable pickle ({type(last).__name__}: {last})")


def load_pickle(path: str | Path) -> Any:
    """Load a pickle (plain, Python 2, or joblib; optionally zlib/gzip-compressed) restricted
    to numpy arrays and builtins containers. Raises `UserError` naming the file on a missing,
    unreadable or refused file."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: file not found")
    data = path.read_bytes()
    if data[:2] == b"\x1f\x8b":  # gzip (joblib compress='gzip')
        data = _decompress(path, lambda: gzip.decompress(data))
    elif data[:1] == b"\x78":  # zlib (joblib's default compressor)
        data = _decompress(path, lambda: zlib.decompress(data))
    elif data[:2] == b"ZF":  # joblib < 0.10's own zlib container
        raise UserError(f"{path}: written by joblib < 0.10, which cogs cannot read; re-save it with a recent joblib")
    return _unpickle_bytes(data, path)


def _decompress(path: Path, fn) -> bytes:
    try:
        return fn()
    except (OSError, zlib.error, EOFError) as e:
        raise UserError(f"{path}: compressed data is corrupt ({e})") from None


def load_npy(path: str | Path) -> Any:
    """Load a `.npy` file. Plain arrays load as with `np.load(allow_pickle=False)`; an object
    array's pickled payload goes through the restricted unpickler. A 0-d object array (what
    `np.save(path, some_dict)` writes) is returned as the object itself."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: file not found")
    fmt = np.lib.format
    try:
        with open(path, "rb") as f:
            version = fmt.read_magic(f)
            if version == (1, 0):
                shape, fortran, dtype = fmt.read_array_header_1_0(f)
            else:
                shape, fortran, dtype = fmt.read_array_header_2_0(f)
            if not dtype.hasobject:
                f.seek(0)
                return np.load(f, allow_pickle=False)
            payload = f.read()
    except (ValueError, OSError, EOFError) as e:
        raise UserError(f"{path}: not a readable .npy file ({e})") from None
    arr = _unpickle_bytes(payload, path)
    if not isinstance(arr, np.ndarray):
        raise UserError(f"{path}: its pickled payload is a {type(arr).__name__}, not an array")
    return arr.item() if arr.shape == () else arr
