"""The restricted unpickler: numpy data in, code out."""

from __future__ import annotations

import collections
import os
import pickle
import struct
import subprocess

import numpy as np
import pytest

from cogs.errors import UserError
from cogs.preprocess.safe_pickle import load_npy, load_pickle


def same(a, b) -> bool:
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(same(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)):
        return type(a) is type(b) and len(a) == len(b) and all(same(x, y) for x, y in zip(a, b))
    if isinstance(a, np.ndarray):
        return isinstance(b, np.ndarray) and a.dtype == b.dtype and np.array_equal(a, b)
    return a == b and type(a) is type(b)


DATA = {
    "Rh": np.array([0.1, -0.2, 0.3], dtype=np.float32),
    "poses": np.arange(72, dtype=np.float64).reshape(24, 3),
    "fortran": np.asfortranarray(np.arange(12.0).reshape(3, 4)),
    "ints": np.arange(5, dtype=np.int64),
    "scalar": np.float64(2.5),
    "list": [np.eye(3), 1, "frame_000001", None, True],
    "tuple": (1.5, b"raw"),
    "set": {1, 2},
    "ordered": collections.OrderedDict(a=np.zeros(2)),
}


@pytest.mark.parametrize("protocol", range(0, pickle.HIGHEST_PROTOCOL + 1))
def test_accepts_dicts_of_numpy_arrays_in_every_protocol(tmp_path, protocol):
    path = tmp_path / "data.pkl"
    path.write_bytes(pickle.dumps(DATA, protocol=protocol))
    assert same(load_pickle(path), DATA)


def test_accepts_numpy_1x_module_paths(tmp_path):
    # numpy 2 writes numpy._core.*, numpy 1 wrote numpy.core.*: both name the same functions.
    raw = pickle.dumps({"a": np.arange(4.0)}, protocol=0)
    old = raw.replace(b"numpy._core.", b"numpy.core.")
    assert b"numpy.core.multiarray" in old
    (tmp_path / "old.pkl").write_bytes(old)
    assert np.array_equal(load_pickle(tmp_path / "old.pkl")["a"], np.arange(4.0))


def python2_pickle_of(arr: np.ndarray) -> bytes:
    """Protocol-2 bytes as Python 2 + numpy 1 wrote them: `str` payloads, numpy.core paths."""

    def sbin(s: bytes) -> bytes:
        return b"U" + bytes([len(s)]) + s if len(s) < 256 else b"T" + struct.pack("<I", len(s)) + s

    dtype_state = b"(K\x03" + sbin(b"<") + b"NNNJ\xff\xff\xff\xffJ\xff\xff\xff\xffK\x00t"
    body = (
        b"\x80\x02}q\x00" + sbin(b"Th")
        + b"cnumpy.core.multiarray\n_reconstruct\ncnumpy\nndarray\nK\x00\x85" + sbin(b"b") + b"\x87R"
        + b"(K\x01K" + bytes([arr.size]) + b"\x85cnumpy\ndtype\n" + sbin(b"f8") + b"K\x00K\x01\x87R"
        + dtype_state + b"b\x89" + sbin(arr.astype("<f8").tobytes()) + b"tb"
        + b"s."
    )
    return body


def test_reads_python2_pickles_with_latin1(tmp_path):
    arr = np.array([1.0, -2.0, 3.5])
    path = tmp_path / "py2.pkl"
    path.write_bytes(python2_pickle_of(arr))
    got = load_pickle(path)
    assert list(got) == ["Th"] and np.array_equal(got["Th"], arr)


class _CallsSystem:
    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


class _CallsEval:
    def __reduce__(self):
        return (eval, ("__import__('os').getcwd()",))


class _CallsSubprocess:
    def __reduce__(self):
        return (subprocess.check_output, (["true"],))


class SomeClass:
    pass


def test_refuses_a_pickle_that_would_run_os_system_and_does_not_run_it(tmp_path):
    marker = tmp_path / "PWNED"
    path = tmp_path / "mesh_infos.pkl"
    path.write_bytes(pickle.dumps({"frame": {"Rh": np.zeros(3), "x": _CallsSystem(marker)}}))
    with pytest.raises(UserError) as e:
        load_pickle(path)
    assert "mesh_infos.pkl" in str(e.value) and "system" in str(e.value)
    assert not marker.exists()


@pytest.mark.parametrize("payload,name", [(_CallsEval(), "eval"), (_CallsSubprocess(), "check_output"),
                                          (SomeClass(), "SomeClass")])
def test_refuses_builtins_eval_subprocess_and_arbitrary_classes(tmp_path, payload, name):
    path = tmp_path / "bad.pkl"
    path.write_bytes(pickle.dumps([payload]))
    with pytest.raises(UserError, match=name):
        load_pickle(path)


def test_refuses_chumpy_objects_saying_what_to_convert(tmp_path):
    raw = b"\x80\x02cchumpy.ch\nCh\n)\x81q\x00."
    (tmp_path / "smpl.pkl").write_bytes(raw)
    with pytest.raises(UserError, match=r"chumpy\.ch\.Ch.*numpy\.array"):
        load_pickle(tmp_path / "smpl.pkl")


def test_reads_object_npy_files_like_neumans_alignments(tmp_path):
    align = {"00000.png": np.random.default_rng(0).normal(size=(4, 3)), "00001.png": np.eye(4, 3)}
    np.save(tmp_path / "alignments.npy", np.array(align, dtype=object), allow_pickle=True)
    assert same(load_npy(tmp_path / "alignments.npy"), align)
    np.save(tmp_path / "plain.npy", np.arange(3))
    assert np.array_equal(load_npy(tmp_path / "plain.npy"), np.arange(3))


def test_refuses_malicious_object_npy(tmp_path):
    marker = tmp_path / "PWNED"
    np.save(tmp_path / "alignments.npy", np.array([_CallsSystem(marker)], dtype=object), allow_pickle=True)
    with pytest.raises(UserError, match="alignments.npy"):
        load_npy(tmp_path / "alignments.npy")
    assert not marker.exists()


def test_reads_joblib_files_without_joblib_semantics(tmp_path):
    joblib = pytest.importorskip("joblib", reason="joblib not installed; NeuMan's fits are joblib files")
    fits = {1: {"pose": [np.random.rand(72).astype(np.float32) for _ in range(3)], "betas": np.random.rand(3, 10),
                "f_order": np.asfortranarray(np.arange(6.0).reshape(2, 3))}}
    for compress in (0, 3):
        joblib.dump(fits, tmp_path / "smpl_output_optimized.pkl", compress=compress)
        assert same(load_pickle(tmp_path / "smpl_output_optimized.pkl"), fits)


def test_missing_and_corrupt_files_are_user_errors_naming_the_file(tmp_path):
    with pytest.raises(UserError, match="nope.pkl"):
        load_pickle(tmp_path / "nope.pkl")
    (tmp_path / "trunc.pkl").write_bytes(pickle.dumps(DATA)[:40])
    with pytest.raises(UserError, match="trunc.pkl"):
        load_pickle(tmp_path / "trunc.pkl")
    (tmp_path / "bad.npy").write_bytes(b"not an npy")
    with pytest.raises(UserError, match="bad.npy"):
        load_npy(tmp_path / "bad.npy")


def test_build_on_a_class_is_refused(tmp_path):
    # GLOBAL <allowed class>, then BUILD with a state dict: would set attributes on the class.
    raw = b"\x80\x02cjoblib.numpy_pickle\nNumpyArrayWrapper\n}X\x03\x00\x00\x00fooK\x01sb."
    (tmp_path / "x.pkl").write_bytes(raw)
    with pytest.raises(UserError):
        load_pickle(tmp_path / "x.pkl")
