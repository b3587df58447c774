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
from cogs.data.safe_pickle import load_npy, load_pickle


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


# -- body-model files (SMPL / SMPL-X .pkl) --------------------------------------------------


def _official_style_smpl_pickle(data: dict, monkeypatch, protocol: int = 2) -> bytes:
    """`data` pickled the way the official SMPL release stores it: the dense arrays as plain
    chumpy arrays (`chumpy.ch.Ch`, state = chumpy's own `__getstate__`), the joint regressor
    as a scipy csc matrix under its pre-1.8 module path, numpy under its 1.x path. chumpy is
    not installed: a stand-in class pickles under its name."""
    import sys
    import types

    import scipy.sparse as sp

    class Ch:
        def __init__(self, x):
            self.x = np.asarray(x, np.float64)
            self._dirty_vars, self._itr, self._depends_on_deps = {"x"}, None, {}
            self._make_dense, self._make_sparse = False, False

    Ch.__module__, Ch.__qualname__ = "chumpy.ch", "Ch"
    chumpy, ch = types.ModuleType("chumpy"), types.ModuleType("chumpy.ch")
    ch.Ch, chumpy.ch = Ch, ch
    monkeypatch.setitem(sys.modules, "chumpy", chumpy)
    monkeypatch.setitem(sys.modules, "chumpy.ch", ch)
    out = {k: Ch(v) for k, v in data.items() if k in ("v_template", "shapedirs", "posedirs", "weights")}
    out.update(J_regressor=sp.csc_matrix(data["J_regressor"]), kintree_table=data["kintree_table"], f=data["f"],
               bs_type="lrotmin", bs_style="lbs")
    raw = pickle.dumps(out, protocol=protocol)
    assert b"chumpy.ch" in raw and b"scipy.sparse._csc" in raw
    return raw.replace(b"scipy.sparse._csc", b"scipy.sparse.csc").replace(b"numpy._core.", b"numpy.core.")


@pytest.mark.parametrize("protocol", [0, 2])
def test_official_smpl_pickle_reads_chumpy_as_arrays_and_the_sparse_regressor(tmp_path, monkeypatch, protocol):
    import scipy.sparse as sp

    from cogs.data.safe_pickle import load_model_pickle
    from tests.test_retarget import write_toy_smpl_model

    data = write_toy_smpl_model(tmp_path / "toy.npz")
    path = tmp_path / "SMPL_NEUTRAL.pkl"
    path.write_bytes(_official_style_smpl_pickle(data, monkeypatch, protocol))
    got = load_model_pickle(path)
    for k in ("v_template", "shapedirs", "posedirs", "weights"):
        assert type(got[k]) is np.ndarray and got[k].dtype == np.float64 and np.array_equal(got[k], data[k]), k
    assert sp.issparse(got["J_regressor"]) and got["J_regressor"].format == "csc"
    assert np.array_equal(got["J_regressor"].toarray(), data["J_regressor"])
    assert got["bs_style"] == "lbs"


def test_smpl_body_from_an_official_style_pickle_equals_the_npz(tmp_path, monkeypatch):
    pytest.importorskip("smplx", reason="smplx (optional extra cogs[smpl]) is not installed")
    import torch

    from cogs.body.smpl_body import SmplBody
    from tests.test_retarget import write_toy_smpl_model

    data = write_toy_smpl_model(tmp_path / "toy.npz")
    (tmp_path / "SMPL_NEUTRAL.pkl").write_bytes(_official_style_smpl_pickle(data, monkeypatch))
    a, b = SmplBody(tmp_path / "SMPL_NEUTRAL.pkl").canonical(), SmplBody(tmp_path / "toy.npz").canonical()
    assert torch.allclose(a.vertices, b.vertices) and torch.allclose(a.joints, b.joints)


def test_a_malicious_smpl_model_file_never_runs_and_is_named(tmp_path, monkeypatch):
    from cogs.body import load_body_model
    from cogs.body.smpl_body import set_smpl_model_path

    marker = tmp_path / "PWNED"
    path = tmp_path / "SMPL_NEUTRAL.pkl"
    path.write_bytes(pickle.dumps({"v_template": np.zeros((4, 3)), "f": _CallsSystem(marker)}, protocol=2))
    set_smpl_model_path(None)
    monkeypatch.setenv("COGS_SMPL_MODEL", str(path))
    try:
        with pytest.raises(UserError) as e:
            load_body_model("smpl")
    finally:
        set_smpl_model_path(None)
    assert str(path) in str(e.value) and "posix.system" in str(e.value)
    assert not marker.exists()


@pytest.mark.parametrize("payload,name", [
    (b"\x80\x02cchumpy.ch_ops\nadd\n)\x81q\x00.", "chumpy.ch_ops.add"),  # an expression, not a stored array
    (b"\x80\x02cchumpy.ch\nCh\n)\x81}X\x01\x00\x00\x00xX\x03\x00\x00\x00abcsb.", "chumpy array"),
    (b"\x80\x02cscipy.sparse._csc\ncsc_matrix\n)\x81}X\x04\x00\x00\x00dataK\x01sb.", "sparse matrix"),
    (b"\x80\x02ccopyreg\n_reconstructor\ncposix\nsystem\ncbuiltins\nobject\nN\x87R.", "posix.system"),
])
def test_model_pickles_refuse_chumpy_expressions_and_malformed_records(tmp_path, payload, name):
    from cogs.data.safe_pickle import load_model_pickle

    (tmp_path / "m.pkl").write_bytes(payload)
    with pytest.raises(UserError, match=name) as e:
        load_model_pickle(tmp_path / "m.pkl")
    assert "m.pkl" in str(e.value)


def test_dataset_pickles_still_refuse_chumpy_and_sparse(tmp_path, monkeypatch):
    from tests.test_retarget import write_toy_smpl_model

    data = write_toy_smpl_model(tmp_path / "toy.npz")
    (tmp_path / "fits.pkl").write_bytes(_official_style_smpl_pickle(data, monkeypatch))
    with pytest.raises(UserError, match="refusing"):
        load_pickle(tmp_path / "fits.pkl")
