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

Body-model files (`load_model_pickle`: SMPL / SMPL-X `.pkl`, the user's own licensed copy)
additionally hold what the official releases store besides arrays: plain chumpy arrays
(`chumpy.ch.Ch`, read as the numpy array they wrap; chumpy is never imported) and scipy
sparse matrices (`csc_matrix`/`csr_matrix`, e.g. SMPL's `J_regressor`, rebuilt from their
data, indices and index pointers through scipy's own checked constructor). Chumpy
expressions (any other chumpy class) are refused: their value would have to be computed.

This module sits low (cogs.data) so that both the body models and the dataset importers
can use it.
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

__all__ = ["load_pickle", "load_model_pickle", "load_npy", "RefusedGlobal"]


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


class _ChumpyArray:
    """Stand-in for a plain `chumpy.ch.Ch`: its pickled state holds the wrapped array as `x`."""


class _SparseMatrix:
    """Stand-in for a scipy sparse matrix: its state (data, indices, indptr, shape) is used."""

    format = "csc"


class _CsrMatrix(_SparseMatrix):
    format = "csr"


def _reconstructor(cls, base, state):
    """`copyreg._reconstructor` (protocol 0/1 pickles of plain objects), limited to the
    stand-ins: it creates an empty instance and nothing else."""
    if cls not in (_ChumpyArray, _SparseMatrix, _CsrMatrix) or base is not object or state is not None:
        raise pickle.UnpicklingError(f"copyreg._reconstructor({getattr(cls, '__name__', cls)!r}, ...) is not plain data")
    return object.__new__(cls)


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


def _model_globals() -> dict[tuple[str, str], Any]:
    """What body-model pickles need on top of `_allowed_globals`."""
    table: dict[tuple[str, str], Any] = {
        ("chumpy.ch", "Ch"): _ChumpyArray,
        ("copyreg", "_reconstructor"): _reconstructor,
        ("builtins", "object"): object,
    }
    # scipy's module path moved (scipy.sparse.csc -> scipy.sparse._csc in 1.8).
    for mod in ("scipy.sparse.csc", "scipy.sparse._csc", "scipy.sparse"):
        table[(mod, "csc_matrix")] = _SparseMatrix
    for mod in ("scipy.sparse.csr", "scipy.sparse._csr", "scipy.sparse"):
        table[(mod, "csr_matrix")] = _CsrMatrix
    return table


_ALLOWED: dict[tuple[str, str], Any] | None = None
_MODEL_ALLOWED: dict[tuple[str, str], Any] | None = None

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

    def __init__(self, file, *, encoding: str = "ASCII", model: bool = False):
        super().__init__(file, encoding=encoding, errors="strict")
        self._file = file
        self._model = model

    def find_class(self, module: str, name: str):
        global _ALLOWED, _MODEL_ALLOWED
        if _ALLOWED is None:
            _ALLOWED = _allowed_globals()
            _MODEL_ALLOWED = {**_ALLOWED, **_model_globals()}
        if self.proto < 3:  # Python 2 names: __builtin__.set, copy_reg._reconstructor, ...
            if (module, name) in _compat_pickle.NAME_MAPPING:
                module, name = _compat_pickle.NAME_MAPPING[(module, name)]
            elif module in _compat_pickle.IMPORT_MAPPING:
                module = _compat_pickle.IMPORT_MAPPING[module]
        try:
            return (_MODEL_ALLOWED if self._model else _ALLOWED)[(module, name)]
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
        elif isinstance(top, (_ChumpyArray, _SparseMatrix)):
            value = _chumpy_value(top) if isinstance(top, _ChumpyArray) else _sparse_value(top)
            self.stack[-1] = value
            # The memo still holds the stand-in: later references to it get the value too.
            for k, v in self.memo.items():
                if v is top:
                    self.memo[k] = value

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


def _chumpy_value(ch: _ChumpyArray) -> np.ndarray:
    x = ch.__dict__.get("x")
    if not isinstance(x, np.ndarray) or x.dtype.hasobject:
        raise pickle.UnpicklingError("a chumpy array whose state holds no numeric array `x` (a chumpy expression?)")
    return np.array(x, dtype=np.float64)


def _sparse_value(m: _SparseMatrix):
    import scipy.sparse as sp

    state = m.__dict__
    try:
        shape = tuple(int(n) for n in state.get("_shape", state.get("shape")))
        parts = tuple(np.asarray(state[k]) for k in ("data", "indices", "indptr"))
        if any(p.dtype.hasobject for p in parts):
            raise TypeError("object arrays")
        cls = sp.csc_matrix if m.format == "csc" else sp.csr_matrix
        return cls(parts, shape=shape)  # scipy checks that the parts agree
    except (KeyError, TypeError, ValueError) as e:
        raise pickle.UnpicklingError(f"malformed sparse matrix record ({type(e).__name__}: {e})") from None


def _refusal(path: Path, e: RefusedGlobal) -> UserError:
    top = e.module.split(".")[0]
    hint = _CONVERT_HINT.get(top, "only numpy arrays and plain containers are accepted")
    return UserError(
        f"{path}: refusing to load this pickle: it names the global `{e.module}.{e.name}`, "
        f"which cogs does not run ({hint})"
    )


def _unpickle_bytes(data: bytes, path: Path, model: bool = False) -> Any:
    # ASCII first (Python 3 pickles never need a decode); latin-1 is the documented way to
    # read Python 2 pickles that hold numpy arrays (their buffers are py2 `str`).
    last: Exception | None = None
    for encoding in ("ASCII", "latin1"):
        try:
            return _SafeUnpickler(io.BytesIO(data), encoding=encoding, model=model).load()
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
    return _unpickle_bytes(_read_pickle_bytes(path), path)


def load_model_pickle(path: str | Path) -> Any:
    """Load a body-model pickle (SMPL / SMPL-X `.pkl`): what `load_pickle` accepts, plus plain
    chumpy arrays (returned as float64 numpy arrays) and scipy csc/csr sparse matrices.
    Nothing in the file is run; `UserError` naming the file otherwise."""
    path = Path(path)
    return _unpickle_bytes(_read_pickle_bytes(path), path, model=True)


def _read_pickle_bytes(path: Path) -> bytes:
    if not path.is_file():
        raise UserError(f"{path}: file not found" if not path.exists() else f"{path}: not a file")
    try:
        data = path.read_bytes()
    except OSError as e:
        raise UserError(f"{path}: cannot be read ({e.strerror or e})") from None
    if data[:2] == b"\x1f\x8b":  # gzip (joblib compress='gzip')
        data = _decompress(path, lambda: gzip.decompress(data))
    elif data[:1] == b"\x78":  # zlib (joblib's default compressor)
        data = _decompress(path, lambda: zlib.decompress(data))
    elif data[:2] == b"ZF":  # joblib < 0.10's own zlib container
        raise UserError(f"{path}: written by joblib < 0.10, which cogs cannot read; re-save it with a recent joblib")
    return data


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
