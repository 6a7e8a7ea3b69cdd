"""lsgan.pickles and the loaders that use it: gadgets that run code when unpickled are refused, by name and
without running, through every entry point (SMPL .pkl, `lsgan export --body-model`, GloVe, HumanAct12, AMASS
model .npz/.pkl, a checkpoint's state.pt, the official evaluator's finest.tar); real-format files still load.
Pickles that break a bound (nesting, item count, declared sizes, zero-size dtypes, huge sparse matrices) and
.npy/.npz headers or torch storages claiming more than the file holds are refused before anything is
unpickled or allocated, by every reader (hostile cases that crash plain pickle run in a child process); and
no module but lsgan/pickles.py unpickles (a check of the package's syntax tree).

Every gadget writes the sentinel file ``pwned.npy`` when it runs. ``test_gadget_is_live`` first shows that
plain ``pickle.loads`` does run it (so each refusal below is a refusal of working code); the other tests
check that the sentinel never appears.
"""
from __future__ import annotations

import ast
import importlib.util
import io
import json
import os
import pickle
import struct
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp
import torch
from body_models import make_model, write_models

from lsgan.data.body_model import BodyModelError, read_body_model
from lsgan.data.clip import ClipError
from lsgan.data.sources.amass import read_body_model_file
from lsgan.data.sources.humanact12 import HumanAct12Source
from lsgan.models.checkpoint import load_state, load_torch_file, load_weights, read_meta, save_checkpoint, weights_hash
from lsgan.models.evaluator import load_evaluator
from lsgan.models.word_vectorizer import WordVectorizer
import lsgan.pickles
from lsgan.pickles import (
    ALLOWED,
    MAX_PICKLE_DEPTH,
    PickleReadError,
    SafeUnpickler,
    load_npy,
    load_npz,
    load_pickle,
    read_npy_object,
)

SENTINEL = "pwned.npy"  # numpy.save appends .npy, so every gadget writes this name

# ------------------------------------------------------------------------------------------------------------------
# Gadgets. Protocol 0 is text, so calls are written out: GLOBAL 'c module\nname\n', MARK '(', TUPLE 't', REDUCE 'R'.


def glob(module: str, name: str) -> str:
    return f"c{module}\n{name}\n"


def text(value: str) -> str:
    assert "\n" not in value and "\\" not in value
    return f"V{value}\n"


def call(fn: str, *args: str) -> str:
    return fn + "(" + "".join(args) + "tR"


def p0(expr: str) -> bytes:
    return (expr + ".").encode()


NONE, TRUE, EMPTY_DICT = "N", "I01\n", "(d"


class Call:
    """Pickles as ``fn(*args)``, for gadgets whose arguments are not text (bytes, objects)."""

    def __init__(self, fn, *args) -> None:
        self.fn, self.args = fn, args

    def __reduce__(self):
        return self.fn, self.args


def _code(d: Path) -> str:
    return f"open({str(d / SENTINEL)!r}, 'w').close()"


def _module(d: Path, name: str) -> str:
    """A module file in ``d`` that writes the sentinel when imported or run; returns its name."""
    (d / f"{name}.py").write_text(_code(d) + "\n")
    return name


def _f2py_eval(d):
    return p0(call(glob("numpy.f2py.crackfortran", "myeval"), text(_code(d))))


def _f2cmap_file(d):
    # capi_maps.load_f2cmap_file evals the file's text lowercased; hex digits survive that
    (d / "f2cmap.txt").write_text(f"exec(bytes.fromhex('{_code(d).encode().hex()}').decode())")
    return p0(call(glob("numpy.f2py.capi_maps", "load_f2cmap_file"), text(str(d / "f2cmap.txt"))))


def _numpy_load(d):
    (d / "second.pkl").write_bytes(_os_system(d))
    return p0(call(glob("numpy", "load"), text(str(d / "second.pkl")), NONE, TRUE))


def _os_system(d):
    return p0(call(glob("os", "system"), text(f"touch {d / SENTINEL}")))


def _posix_system(d):
    return p0(call(glob("posix", "system"), text(f"touch {d / SENTINEL}")))


def _popen(d):
    return p0(call(glob("subprocess", "Popen"), "(" + text("touch") + text(str(d / SENTINEL)) + "l"))


def _getattr_chain(d):
    system = call(glob("builtins", "getattr"), call(glob("builtins", "__import__"), text("os")), text("system"))
    return p0(call(system, text(f"touch {d / SENTINEL}")))


def _torch_load(d):
    torch.save(Call(os.system, f"touch {d / SENTINEL}"), d / "second.pt")
    return pickle.dumps(Call(torch.load, str(d / "second.pt")), protocol=2)


def _pickle_loads(d):
    return pickle.dumps(Call(pickle.loads, _os_system(d)), protocol=2)  # names _pickle.loads


def _in_object_array(d):
    return pickle.dumps({"v_template": np.array([Call(os.system, f"touch {d / SENTINEL}")], dtype=object)},
                        protocol=2)


def _in_sparse_matrix(d):
    matrix = sp.csc_matrix(np.eye(3))
    matrix.data = [Call(os.system, f"touch {d / SENTINEL}")]
    return pickle.dumps({"J_regressor": matrix}, protocol=2)


GADGETS = {
    "numpy.f2py.crackfortran.myeval": _f2py_eval,  # eval(arg) in numpy.f2py
    "numpy.load(allow_pickle=True)": _numpy_load,  # loads a second, malicious pickle
    "os.system": _os_system,
    "posix.system": _posix_system,
    "subprocess.Popen": _popen,
    "builtins.eval": lambda d: p0(call(glob("builtins", "eval"), text(_code(d)))),
    "builtins.exec": lambda d: p0(call(glob("builtins", "exec"), text(_code(d)))),
    "__builtin__.eval (Python 2 name)": lambda d: p0(call(glob("__builtin__", "eval"), text(_code(d)))),
    "builtins.getattr(__import__('os'), 'system')": _getattr_chain,
    "builtins.__import__": lambda d: p0(call(glob("builtins", "__import__"), text(_module(d, "gadget_import")))),
    "nested __reduce__ in an object array": _in_object_array,
    "nested __reduce__ in a sparse matrix": _in_sparse_matrix,
    "numpy.testing.measure": lambda d: p0(call(glob("numpy.testing", "measure"), text(_code(d)))),
    "pickle.loads": _pickle_loads,
    "pickle.loads (module pickle)": lambda d: _pickle_loads(d).replace(b"c_pickle\nloads\n", b"cpickle\nloads\n"),
    "torch.load": _torch_load,
    # found in the installed numpy / scipy / stdlib (eval, exec, subprocess, file writes):
    "numpy.f2py.capi_maps.load_f2cmap_file": _f2cmap_file,
    "numpy.testing._private.utils.runstring": lambda d: p0(call(
        glob("numpy.testing._private.utils", "runstring"), text(_code(d)), EMPTY_DICT)),
    "numpy.testing.rundocs": lambda d: p0(call(glob("numpy.testing", "rundocs"),
                                               text(str(d / (_module(d, "gadget_docs") + ".py"))))),
    "numpy.distutils.exec_command.exec_command": lambda d: p0(call(
        glob("numpy.distutils.exec_command", "exec_command"), text(f"touch {d / SENTINEL}"))),
    "numpy.save": lambda d: p0(call(glob("numpy", "save"), text(str(d / SENTINEL)), "I0\n")),
    "builtins.open": lambda d: p0(call(glob("builtins", "open"), text(str(d / SENTINEL)), text("w"))),
    "timeit.timeit": lambda d: p0(call(glob("timeit", "timeit"), text("pass"), text(_code(d)), NONE, "I1\n")),
    "runpy.run_path": lambda d: p0(call(glob("runpy", "run_path"), text(str(d / (_module(d, "gadget_run") + ".py"))))),
    "importlib.import_module": lambda d: p0(call(glob("importlib", "import_module"), text(_module(d, "gadget_imp")))),
}


def _needs(name: str) -> None:
    """Skips the live run of a gadget whose module is not installed (refusals are by name, and need nothing)."""
    if "distutils" in name and importlib.util.find_spec("numpy.distutils") is None:
        pytest.skip("numpy.distutils is not installed here")


@pytest.fixture()
def gadget_dir(tmp_path, monkeypatch) -> Path:
    """A folder for the gadget's helper files, importable (so import gadgets would work if they ran)."""
    d = tmp_path / "gadget"
    d.mkdir()
    monkeypatch.syspath_prepend(str(d))
    return d


def _assert_refused(exc: BaseException, path: Path) -> None:
    message = str(exc)
    assert message.startswith(str(path)), message
    assert "refused" in message and "weights_only" not in message, message


@pytest.mark.parametrize("name", GADGETS)
def test_gadget_is_live(name, gadget_dir):
    """Plain pickle.loads runs it (in a child process): the refusals below are of working code."""
    _needs(name)
    (gadget_dir / "evil.pkl").write_bytes(GADGETS[name](gadget_dir))
    env = dict(os.environ, PYTHONPATH=str(gadget_dir), TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD="1")
    subprocess.run([sys.executable, "-c", "import pickle, sys\ntry:\n pickle.loads(open(sys.argv[1], 'rb').read())\n"
                    "except Exception:\n pass", str(gadget_dir / "evil.pkl")], cwd=gadget_dir, env=env, timeout=120)
    deadline = time.monotonic() + 10  # Popen's child may finish after the parent
    while not (gadget_dir / SENTINEL).exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    assert (gadget_dir / SENTINEL).exists(), f"{name} did not run under plain pickle"


@pytest.mark.parametrize("name", GADGETS)
def test_body_model_loaders_refuse(name, gadget_dir, tmp_path):
    payload = GADGETS[name](gadget_dir)
    pkl = tmp_path / "smpl" / "SMPL_NEUTRAL.pkl"
    pkl.parent.mkdir()
    pkl.write_bytes(payload)
    with pytest.raises(BodyModelError) as err:
        read_body_model(tmp_path)
    _assert_refused(err.value, pkl)
    with pytest.raises(ClipError) as err:  # AMASS's SMPL-H reader, .pkl
        read_body_model_file(str(pkl))
    _assert_refused(err.value, pkl)
    npz = tmp_path / "male" / "model.npz"
    _npz_with_object_entry(npz, make_model("smplh"), "J_regressor", payload)
    with pytest.raises(ClipError) as err:  # AMASS's SMPL-H reader, an object entry of model.npz
        read_body_model_file(str(npz))
    _assert_refused(err.value, npz)
    assert "'J_regressor'" in str(err.value)
    with pytest.raises(BodyModelError) as err:
        read_body_model(npz)
    _assert_refused(err.value, npz)
    assert not (gadget_dir / SENTINEL).exists()


@pytest.mark.parametrize("name", GADGETS)
def test_export_cli_refuses(name, gadget_dir, tmp_path):
    model = tmp_path / "evil.pkl"
    model.write_bytes(GADGETS[name](gadget_dir))
    np.save(tmp_path / "walk_joints.npy", np.zeros((8, 22, 3), np.float32))
    env = dict(os.environ, PYTHONPATH=str(gadget_dir), OMP_NUM_THREADS="1")
    run = subprocess.run([sys.executable, "-c", "from lsgan.cli import main; main()", "export", "--glb",
                          str(tmp_path / "walk_joints.npy"), "--body-model", str(model), "-o", str(tmp_path / "w.glb")],
                         capture_output=True, text=True, env=env, timeout=300)
    assert run.returncode != 0
    assert f"error: {model}: refused" in run.stderr, run.stderr
    assert not (gadget_dir / SENTINEL).exists() and not (tmp_path / "w.glb").exists()


@pytest.mark.parametrize("name", GADGETS)
def test_glove_and_humanact12_refuse(name, gadget_dir, tmp_path):
    payload = GADGETS[name](gadget_dir)
    glove = tmp_path / "glove"
    _write_glove(glove, protocol=4)
    (glove / "our_vab_idx.pkl").write_bytes(payload)
    with pytest.raises(ValueError) as err:
        WordVectorizer(glove)
    _assert_refused(err.value, glove / "our_vab_idx.pkl")
    act = tmp_path / "HumanAct12Poses" / "humanact12poses.pkl"
    act.parent.mkdir()
    act.write_bytes(payload)
    with pytest.raises(ValueError) as err:
        HumanAct12Source(str(act.parent)).scan()
    _assert_refused(err.value, act)
    assert not (gadget_dir / SENTINEL).exists()


@pytest.mark.parametrize("name", GADGETS)
def test_checkpoint_state_and_official_weights_refuse(name, gadget_dir, tmp_path):
    payload = GADGETS[name](gadget_dir)
    folder = _checkpoint(tmp_path / "run" / "last")
    _torch_file_with(folder / "state.pt", payload)
    with pytest.raises(ValueError) as err:
        load_state(tmp_path / "run")
    _assert_refused(err.value, folder / "state.pt")
    assert "objects other than tensors and plain values" in str(err.value)
    (folder / "state.pt").write_bytes(payload)  # a bare pickle: torch's legacy format
    with pytest.raises(ValueError) as err:
        load_state(folder)
    _assert_refused(err.value, folder / "state.pt")
    root = _official_layout(tmp_path / "t2m")
    _torch_file_with(root / "t2m/text_mot_match/model/finest.tar", payload)
    with pytest.raises(ValueError) as err:
        load_evaluator(root)
    _assert_refused(err.value, root / "t2m/text_mot_match/model/finest.tar")
    assert not (gadget_dir / SENTINEL).exists()


# ------------------------------------------------------------------------------------------------------------------
# Allowed globals used against their purpose (raw bytes as object pointers, dtypes whose fields overlap, sparse
# indices outside the matrix, other codecs, huge allocations, BUILD on a global): refused before numpy/scipy see them


def _forged() -> dict[str, bytes]:
    out_of_range = sp.csc_matrix(np.eye(3))
    out_of_range.indices = np.array([0, 1, 10**6], dtype=np.int32)
    short_coo = sp.coo_matrix(np.eye(3))
    short_coo.data = short_coo.data[:1]
    return {
        # numpy.ndarray(shape, object, buffer): raw bytes as object pointers (numpy segfaults on it)
        "object array from bytes": pickle.dumps(Call(np.ndarray, (2,), np.dtype("O"), b"A" * 16), protocol=2),
        # a structured dtype: dtype.__setstate__ would accept an object field overlapping a float one
        "structured dtype": pickle.dumps(np.zeros(2, dtype=[("a", "O"), ("b", "f8")]), protocol=2),
        "datetime dtype": pickle.dumps(np.zeros(2, dtype="M8[ns]"), protocol=2),
        "array data shorter than its shape": _short_array(),
        "sparse indices outside the shape": pickle.dumps(out_of_range, protocol=4),
        "coo data shorter than its indices": pickle.dumps(short_coo, protocol=4),
        "_codecs.encode with another codec": p0(call(glob("_codecs", "encode"), text("abc"), text("rot13"))),
        "bytes(n) allocation": p0(call(glob("builtins", "bytes"), "I1000000000000\n")),
        "copyreg._reconstructor for numpy.ndarray": p0(call(glob("copy_reg", "_reconstructor"),
                                                            glob("numpy", "ndarray"), glob("__builtin__", "object"), NONE)),
        "BUILD on an allowed global": p0(glob("numpy", "dtype") + "(d" + text("x") + "I1\nsb"),
    }


def _short_array() -> bytes:
    """An array pickle whose shape asks for more items than its data holds."""
    data = pickle.dumps(np.arange(4, dtype=np.int64), protocol=4)
    return data.replace(struct.pack("<BB", 0x4B, 4) + b"\x85", struct.pack("<BB", 0x4B, 9) + b"\x85", 1)


FORGED = _forged()


@pytest.mark.parametrize("name", FORGED)
def test_forged_parts_are_refused(name, tmp_path):
    path = tmp_path / "forged.pkl"
    path.write_bytes(FORGED[name])
    with pytest.raises(PickleReadError) as err:
        load_pickle(path)
    _assert_refused(err.value, path)


def test_refusal_message_names_file_and_global(tmp_path):
    path = tmp_path / "model.pkl"
    path.write_bytes(_os_system(tmp_path))
    with pytest.raises(PickleReadError) as err:
        load_pickle(path)
    assert str(err.value) == (f"{path}: refused to unpickle 'os.system' "
                              "(only arrays, dtypes and sparse matrices are read)")
    assert err.value.refused == "os.system"


def test_allowlist_is_exact():
    core = {(f"numpy.{c}.{m}", n) for c in ("core", "_core") for m, n in
            [("multiarray", "_reconstruct"), ("multiarray", "scalar"), ("numeric", "_frombuffer")]}
    sparse = {(f"scipy.sparse.{p}{f}", f"{f}_matrix") for p in ("", "_") for f in ("csc", "csr", "coo")}
    assert set(ALLOWED) == core | sparse | {("numpy", "ndarray"), ("numpy", "dtype"), ("copyreg", "_reconstructor"),
                                            ("builtins", "object"), ("builtins", "bytes"), ("_codecs", "encode")}
    for module, name in [("numpy", "load"), ("numpy.core.multiarray", "fromstring"), ("scipy.sparse", "load_npz"),
                         ("builtins", "getattr"), ("copyreg", "__newobj__")]:
        with pytest.raises(PickleReadError, match="refused to unpickle"):
            SafeUnpickler(io.BytesIO(p0(glob(module, name))), "x").load()


# ------------------------------------------------------------------------------------------------------------------
# Real formats still load


def _same(a, b) -> bool:
    if sp.issparse(a):
        return type(a) is type(b) and a.shape == b.shape and (a != b).nnz == 0
    if isinstance(a, np.ndarray):
        if a.dtype == object:
            return isinstance(b, np.ndarray) and a.shape == b.shape and all(map(_same, a.flat, b.flat))
        return isinstance(b, np.ndarray) and a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a, b)
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)):
        return type(a) is type(b) and len(a) == len(b) and all(map(_same, a, b))
    return type(a) is type(b) and a == b


def _sample() -> dict:
    rng = np.random.default_rng(0)
    return {
        "f8": rng.normal(size=(5, 3)), "f4_fortran": np.asfortranarray(rng.normal(size=(4, 3)).astype(np.float32)),
        "u4": np.arange(6, dtype=np.uint32).reshape(2, 3), "big_endian": np.arange(3, dtype=">i4"),
        "empty": np.zeros((0, 3)), "bool": np.array([True, False]), "unicode": np.array(["lbs", "x"]),
        "bytes_array": np.array([b"ab"]), "str_0d": np.array("lrotmin"), "complex": np.array([1 + 2j]),
        "scalars": [np.float64(1.5), np.int64(-3), np.float32(2.0), np.bool_(True), np.str_("s")],
        "csc": sp.csc_matrix(rng.normal(size=(4, 6)) * (rng.random((4, 6)) > 0.5)),
        "csr": sp.csr_matrix(np.eye(3)), "coo": sp.coo_matrix(np.eye(2) * 2), "object": np.array(["a", 1, None], object),
        "plain": {"int": 3, "float": 0.5, "str": "é", "bytes": b"\x00\xff", "empty_bytes": b"", "none": None,
                  "tuple": (1, "a"), "nested": [[1, 2], {"k": [3]}]},
    }


@pytest.mark.parametrize("protocol", range(pickle.HIGHEST_PROTOCOL + 1))
def test_arrays_scalars_and_sparse_round_trip(tmp_path, protocol):
    path = tmp_path / "data.pkl"
    path.write_bytes(pickle.dumps(_sample(), protocol=protocol))
    loaded = load_pickle(path)
    assert _same(_sample(), loaded)
    assert loaded["f4_fortran"].flags.f_contiguous and loaded["f8"].flags.writeable


def test_old_module_names_and_python2_pickles(tmp_path):
    """numpy 1.x / old scipy names (the original SMPL files), and a Python 2 pickle (str data, latin1)."""
    data = pickle.dumps({"a": np.arange(3.0), "j": sp.csc_matrix(np.eye(2)), "s": np.float64(2.5)}, protocol=2)
    for new, old in [(b"numpy._core.multiarray", b"numpy.core.multiarray"), (b"scipy.sparse._csc", b"scipy.sparse.csc")]:
        assert new in data
        data = data.replace(new, old)
    out = SafeUnpickler(io.BytesIO(data), "old").load()
    assert _same(out, {"a": np.arange(3.0), "j": sp.csc_matrix(np.eye(2)), "s": np.float64(2.5)})
    a = np.arange(6.0).reshape(2, 3)
    py2 = _py2_array_pickle(a)
    assert np.array_equal(pickle.loads(py2, encoding="latin1"), a)  # what numpy itself reads from it
    assert _same(SafeUnpickler(io.BytesIO(py2), "py2").load(), a)


def _shared_buffer_arrays(count: int, data: bytes) -> bytes:
    """A pickle of ``count`` float32 arrays built from one bytes object (memoised: stored once)."""
    from numpy._core.multiarray import _reconstruct

    state = (1, (len(data) // 4,), np.dtype("f4"), False, data)
    return pickle.dumps([_Built(Call(_reconstruct, np.ndarray, (0,), b"b"), state) for _ in range(count)], protocol=2)


class _Built:
    """Pickles as ``made`` (a Call) followed by BUILD with ``state``."""

    def __init__(self, made: Call, state) -> None:
        self.made, self.state = made, state

    def __reduce__(self):
        return self.made.fn, self.made.args, self.state


def test_arrays_sharing_one_buffer_are_counted_against_the_budget(tmp_path, monkeypatch):
    """Each array made from memoised data is its own copy (500 arrays of one 20 MB string are 10 GB from a 21 MB
    file): the copies count against MEMORY_BUDGET together, and a pickle within it reads as independent arrays."""
    path = tmp_path / "shared.pkl"
    path.write_bytes(_shared_buffer_arrays(3, bytes(4000)))
    assert path.stat().st_size < 5000
    arrays = load_pickle(path)
    arrays[0][0] = 1.0
    assert [float(a[0]) for a in arrays] == [1.0, 0.0, 0.0] and all(a.shape == (1000,) for a in arrays)
    monkeypatch.setattr(lsgan.pickles, "MEMORY_BUDGET", 10_000)
    with pytest.raises(PickleReadError) as err:
        load_pickle(path)
    assert str(err.value) == (f"{path}: refused: the arrays it builds would take more than MEMORY_BUDGET (10,000 "
                              "bytes); data it shares between arrays is copied for each")


def _py2_str(b: bytes) -> bytes:
    return b"U" + bytes([len(b)]) + b if len(b) < 256 else b"T" + struct.pack("<i", len(b)) + b


def _py2_array_pickle(a: np.ndarray) -> bytes:
    """How Python 2 with numpy 1.x pickled an array (protocol 2; strings are str, data a str)."""
    shape = b"(" + b"".join(b"K" + bytes([n]) for n in a.shape) + b"t"
    dtype = (b"cnumpy\ndtype\n" + _py2_str(a.dtype.str[1:].encode()) + b"K\x00K\x01\x87R"
             + b"(K\x03" + _py2_str(a.dtype.str[:1].encode()) + b"NNNJ\xff\xff\xff\xffJ\xff\xff\xff\xffK\x00tb")
    return (b"\x80\x02cnumpy.core.multiarray\n_reconstruct\ncnumpy\nndarray\nK\x00\x85" + _py2_str(b"b") + b"\x87R"
            + b"(K\x01" + shape + dtype + b"\x89" + _py2_str(a.tobytes()) + b"tb.")


@pytest.mark.parametrize("protocol", [0, 2, 4, 5])
def test_smpl_stand_ins_load(tmp_path, protocol):
    write_models(tmp_path)
    data = make_model("smpl")
    data["J_regressor"] = sp.csc_matrix(data["J_regressor"])
    (tmp_path / "smpl" / "SMPL_NEUTRAL.pkl").write_bytes(pickle.dumps(data, protocol=protocol))
    model = read_body_model(tmp_path, model_type="smpl")
    np.testing.assert_allclose(model.j_regressor, data["J_regressor"].toarray(), rtol=1e-6)
    for model_type in ("smplh", "smplx"):
        assert read_body_model(tmp_path, model_type=model_type).model_type == model_type


def test_npz_object_entries_are_read_without_allow_pickle(tmp_path, monkeypatch):
    data = make_model("smplh")
    path = tmp_path / "male" / "model.npz"
    path.parent.mkdir()
    np.savez(path, **dict(data, J_regressor=np.array(sp.csc_matrix(data["J_regressor"]), dtype=object),
                          bs_style=np.array("lbs", dtype=object)))
    real_load = np.load
    monkeypatch.setattr(np, "load", lambda *a, **k: real_load(*a, **dict(k, allow_pickle=False)))
    read = read_body_model_file(str(path))
    assert sp.issparse(read["J_regressor"]) and np.allclose(read["J_regressor"].toarray(), data["J_regressor"])
    assert read_body_model(tmp_path, gender="male").model_type == "smplh"
    entries = load_npz(path)
    assert entries["bs_style"].item() == "lbs" and entries["f"].dtype == np.uint32
    with zipfile.ZipFile(path) as z, z.open("bs_style.npy") as fh:
        assert read_npy_object(fh, "bs_style").item() == "lbs"


@pytest.mark.parametrize("protocol", [0, 2, 4, 5])
def test_glove_stand_in_loads(tmp_path, protocol):
    _write_glove(tmp_path, protocol)
    wv = WordVectorizer(tmp_path)
    assert set(wv.word2vec) == {"unk", "walk", "forward"}


@pytest.mark.parametrize("protocol", [2, 4, 5])
def test_humanact12_stand_in_loads(tmp_path, protocol):
    rng = np.random.default_rng(0)
    data = {"poses": [rng.normal(size=(n, 72)).astype(np.float32) for n in (5, 7)],
            "oldposes": [rng.normal(size=(n, 72)) for n in (5, 7)],
            "joints3D": [rng.normal(size=(n, 24, 3)).astype(np.float32) for n in (5, 7)], "y": [3, np.int64(11)]}
    (tmp_path / "humanact12poses.pkl").write_bytes(pickle.dumps(data, protocol=protocol))
    src = HumanAct12Source(str(tmp_path / "humanact12poses.pkl"))
    clips = [src.load(item)[0] for item in src.scan()]
    assert [c.action for c in clips] == ["jump", "throw"]
    np.testing.assert_array_equal(clips[1].joints, data["joints3D"][1][:, :22])


# ------------------------------------------------------------------------------------------------------------------
# Checkpoints: weights_only refusals and damaged files name the file, never suggest weights_only=False


def test_checkpoint_state_loads_and_damaged_files_are_named(tmp_path):
    folder = _checkpoint(tmp_path / "run" / "last")
    state = load_state(folder)
    assert state["step"] == 3 and torch.equal(state["rng"], torch.arange(4))
    whole = (folder / "state.pt").read_bytes()
    for damaged in (whole[: len(whole) // 2], b"", b"not a checkpoint at all"):
        (folder / "state.pt").write_bytes(damaged)
        with pytest.raises(ValueError, match=r"state\.pt: truncated or corrupt") as err:
            load_state(folder)
        assert str(err.value).startswith(str(folder / "state.pt")) and "weights_only" not in str(err.value)
    weights = (folder / "model.safetensors").read_bytes()
    (folder / "model.safetensors").write_bytes(weights[:-10])
    for read in (load_weights, weights_hash):
        with pytest.raises(ValueError, match=r"model\.safetensors: truncated or corrupt"):
            read(folder)
    (folder / "config.json").write_text('{"kind": "vae", "conf')
    for read in (read_meta, load_weights):
        with pytest.raises(ValueError, match=r"config\.json: truncated or corrupt"):
            read(folder)


def test_official_weights_damaged(tmp_path):
    root = _official_layout(tmp_path)
    tar = root / "t2m/text_mot_match/model/finest.tar"
    tar.write_bytes(tar.read_bytes()[:100])
    with pytest.raises(ValueError, match=r"finest\.tar: truncated or corrupt") as err:
        load_evaluator(root)
    assert "weights_only" not in str(err.value)
    assert load_torch_file(_checkpoint(tmp_path / "ok") / "state.pt")["step"] == 3


# ------------------------------------------------------------------------------------------------------------------
# Helpers


def _npz_with_object_entry(path: Path, arrays: dict, key: str, payload: bytes) -> None:
    """An .npz of ``arrays`` whose ``key`` entry is an object array: an .npy header, then ``payload``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, **{k: v for k, v in arrays.items() if k != key})
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {"descr": "|O", "fortran_order": False, "shape": ()})
    with zipfile.ZipFile(path, "a") as z:
        z.writestr(f"{key}.npy", header.getvalue() + payload)


def _write_glove(folder: Path, protocol: int) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    words = ["unk", "walk", "forward"]
    np.save(folder / "our_vab_data.npy", np.random.default_rng(0).normal(size=(3, 300)))
    (folder / "our_vab_words.pkl").write_bytes(pickle.dumps(words, protocol=protocol))
    (folder / "our_vab_idx.pkl").write_bytes(pickle.dumps({w: i for i, w in enumerate(words)}, protocol=protocol))


def _checkpoint(folder: Path) -> Path:
    model = torch.nn.Linear(2, 2)
    opt = torch.optim.Adam(model.parameters())
    model(torch.ones(1, 2)).sum().backward()
    opt.step()
    save_checkpoint(folder, model=model, kind="toy", config={}, step=3,  # not a trainer's: its state is not checked
                    state={"optimizer": opt.state_dict(), "rng": torch.arange(4), "step": 3})
    return folder


def _torch_file_with(path: Path, payload: bytes) -> None:
    """A torch zip checkpoint at ``path`` whose data.pkl is ``payload``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({}, path)
    with zipfile.ZipFile(path) as z:
        members = {n: z.read(n) for n in z.namelist()}
    with zipfile.ZipFile(path, "w") as z:
        for n, blob in members.items():
            z.writestr(n, payload if n.endswith("/data.pkl") else blob)


def _official_layout(root: Path) -> Path:
    """The official evaluator's file layout: a real finest.tar of plain tensors, small stand-ins for the rest."""
    (root / "t2m/text_mot_match/model").mkdir(parents=True)
    torch.save({"epoch": 1, "w": torch.zeros(2)}, root / "t2m/text_mot_match/model/finest.tar")
    (root / "t2m/Comp_v6_KLD01/meta").mkdir(parents=True)
    for name in ("mean", "std"):
        np.save(root / f"t2m/Comp_v6_KLD01/meta/{name}.npy", np.ones(263, np.float32))
    _write_glove(root / "glove", protocol=4)
    return root


# ------------------------------------------------------------------------------------------------------------------
# One place unpickles: no module but lsgan/pickles.py calls an unpickler, torch.load or np.load(allow_pickle=True)

PACKAGE = Path(__file__).resolve().parents[1] / "lsgan"
FORBIDDEN = {"pickle.load", "pickle.loads", "pickle.Unpickler", "pickle._Unpickler", "_pickle.load", "_pickle.loads",
             "_pickle.Unpickler", "torch.load", "torch.serialization.load", "joblib.load", "pandas.read_pickle",
             "dill.load", "dill.loads", "cloudpickle.load", "cloudpickle.loads"}
NP_LOAD = {"numpy.load"}


def _aliases(tree: ast.AST) -> dict[str, str]:
    """Local name -> the dotted name it stands for, from the module's imports (``import numpy as np``, ``from torch
    import load``)."""
    out = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update({a.asname or a.name.split(".")[0]: a.name if a.asname else a.name.split(".")[0]
                        for a in node.names})
        elif isinstance(node, ast.ImportFrom) and node.module:
            out.update({a.asname or a.name: f"{node.module}.{a.name}" for a in node.names})
    return out


def _dotted(node: ast.AST, aliases: dict[str, str]) -> str | None:
    """``np.load`` -> 'numpy.load' (through the module's imports); None for anything but a (dotted) name."""
    parts = []
    while isinstance(node, ast.Attribute):
        parts.append(node.attr)
        node = node.value
    if not isinstance(node, ast.Name):
        return None
    return ".".join([aliases.get(node.id, node.id), *reversed(parts)])


def _unpickling_sites(path: Path) -> list[tuple[int, str]]:
    """Every use of an unpickler in the module at ``path``: (line, what)."""
    tree = ast.parse(path.read_text(), str(path))
    aliases = _aliases(tree)
    found = []
    for node in ast.walk(tree):
        name = _dotted(node, aliases) if isinstance(node, (ast.Attribute, ast.Name)) else None
        if name in FORBIDDEN:
            found.append((node.lineno, name))
        if isinstance(node, ast.Call) and _dotted(node.func, aliases) in NP_LOAD:
            pickles = [k.value for k in node.keywords if k.arg == "allow_pickle"] + node.args[2:3]
            if any(not (isinstance(v, ast.Constant) and v.value is False) for v in pickles):
                found.append((node.lineno, "numpy.load(allow_pickle=...)"))
    return found


def test_only_lsgan_pickles_unpickles():
    sites = [f"{p.relative_to(PACKAGE.parent)}:{line} {what}" for p in sorted(PACKAGE.rglob("*.py"))
             if p != PACKAGE / "pickles.py" for line, what in _unpickling_sites(p)]
    assert sites == [], "unpickling outside lsgan/pickles.py (use its loaders): " + ", ".join(sites)
    own = {what for _, what in _unpickling_sites(PACKAGE / "pickles.py")}
    assert {"torch.load", "pickle.Unpickler"} <= own


def test_the_syntax_check_sees_every_spelling(tmp_path):
    """The check itself finds the usual spellings (a check that finds nothing would pass anything)."""
    src = ("import pickle as pk\nimport numpy as np\nimport torch\nfrom torch import load\nfrom pickle import loads\n"
           "pk.load(f)\nloads(b)\ntorch.load(p)\nload(p)\nnp.load(p, allow_pickle=True)\nnp.load(p, None, True)\n"
           "np.load(p, allow_pickle=flag)\nnp.load(p)\nnp.load(p, allow_pickle=False)\nclass U(pk.Unpickler): pass\n")
    (tmp_path / "m.py").write_text(src)
    assert sorted(line for line, _ in _unpickling_sites(tmp_path / "m.py")) == [6, 7, 8, 9, 10, 11, 12, 15]


# ------------------------------------------------------------------------------------------------------------------
# Bounds, checked on the opcode stream before anything is unpickled (issue 28)

NESTED_KEY = b"\x80\x02}" + b")" + b"\x85" * 1_000_000 + b"Ns."  # {((((...),),),): None}, 1 MB, no globals


def _s0_array() -> bytes:
    """An array of 2**32 items of the zero-size dtype S0 and no data (lsgan's reader made it with np.zeros: 4 GiB)."""
    return (b"\x80\x02cnumpy._core.multiarray\n_reconstruct\ncnumpy\nndarray\nK\x00\x85C\x01b\x87R(K\x01\x8a\x05"
            + (1 << 32).to_bytes(5, "little") + b"\x85cnumpy\ndtype\nX\x02\x00\x00\x00S0\x89\x88\x87R"
            b"(K\x03X\x01\x00\x00\x00|NNNK\x00K\x01K\x00tb\x89C\x00tb.")


def _in_child(code: str, *args, limit_gb: float = 2.0) -> subprocess.CompletedProcess:
    """``code`` run by a fresh Python under a ``limit_gb`` address-space limit (a crash there cannot stop pytest)."""
    prelude = (f"import resource; resource.setrlimit(resource.RLIMIT_AS, ({int(limit_gb * 2**30)},) * 2)\n"
               "import sys, json\n")
    return subprocess.run([sys.executable, "-c", prelude + code, *map(str, args)], capture_output=True, text=True,
                          timeout=300, env=dict(os.environ, OMP_NUM_THREADS="1"))


def test_nested_key_is_live():
    """Plain pickle.loads of the 1 MB nested key, no globals at all, kills the process with SIGSEGV."""
    code = "import pickle; pickle.loads(b'\\x80\\x02}' + b')' + b'\\x85' * 1_000_000 + b'Ns.')"
    assert _in_child(code).returncode == -11


READERS_CHILD = """
from pathlib import Path
from lsgan.data.body_model import read_body_model
from lsgan.data.sources.amass import read_body_model_file
from lsgan.data.sources.humanact12 import HumanAct12Source
from lsgan.models.checkpoint import load_state
from lsgan.models.evaluator import load_evaluator
from lsgan.models.word_vectorizer import WordVectorizer
d = Path(sys.argv[1])
reads = {
    "body model .pkl": lambda: read_body_model(d / "smpl"),
    "AMASS model .pkl": lambda: read_body_model_file(str(d / "smpl" / "smpl" / "SMPL_NEUTRAL.pkl")),
    "AMASS model .npz entry": lambda: read_body_model_file(str(d / "male" / "model.npz")),
    "body model .npz entry": lambda: read_body_model(d / "male" / "model.npz"),
    "HumanAct12": lambda: HumanAct12Source(str(d / "act" / "humanact12poses.pkl")).scan(),
    "GloVe": lambda: WordVectorizer(d / "t2m" / "glove"),
    "state.pt": lambda: load_state(d / "run"),
    "state.pt, legacy format": lambda: load_state(d / "legacy"),
    "finest.tar": lambda: load_evaluator(d / "t2m"),
}
out = {}
for name, read in reads.items():
    try:
        read()
        out[name] = "read"
    except Exception as e:
        out[name] = f"{type(e).__name__}: {e}"
print(json.dumps(out))
"""


def _hostile_everywhere(d: Path, payload: bytes) -> dict[str, Path]:
    """``payload`` as the pickle of every reader's input; returns the file each reader should name."""
    (d / "smpl" / "smpl").mkdir(parents=True)
    (d / "smpl" / "smpl" / "SMPL_NEUTRAL.pkl").write_bytes(payload)
    _npz_with_object_entry(d / "male" / "model.npz", make_model("smplh"), "J_regressor", payload)
    (d / "act").mkdir()
    (d / "act" / "humanact12poses.pkl").write_bytes(payload)
    root = _official_layout(d / "t2m")
    (root / "glove" / "our_vab_idx.pkl").write_bytes(payload)
    _torch_file_with(root / "t2m/text_mot_match/model/finest.tar", payload)
    _torch_file_with(_checkpoint(d / "run" / "last") / "state.pt", payload)
    (_checkpoint(d / "legacy") / "state.pt").write_bytes(payload)
    pkl = d / "smpl" / "smpl" / "SMPL_NEUTRAL.pkl"
    return {"body model .pkl": pkl, "AMASS model .pkl": pkl, "AMASS model .npz entry": d / "male" / "model.npz",
            "body model .npz entry": d / "male" / "model.npz", "HumanAct12": d / "act" / "humanact12poses.pkl",
            "GloVe": root / "glove" / "our_vab_idx.pkl", "state.pt": d / "run" / "last" / "state.pt",
            "state.pt, legacy format": d / "legacy" / "state.pt",
            "finest.tar": root / "t2m/text_mot_match/model/finest.tar"}


@pytest.mark.parametrize("payload,phrase", [(NESTED_KEY, "containers nested more than 100 deep"),
                                            (b"\x80\x02" + b"]" * 2 + b"\x8e" + struct.pack("<Q", 1 << 40) + b"ab.",
                                             "declares 1,099,511,627,776 bytes")],
                         ids=["nested-tuple-key", "huge-bytes8"])
def test_every_reader_refuses_past_the_bounds(tmp_path, payload, phrase):
    """The nested key crashed 8 of 9 readers (SIGSEGV); now each refuses it in one line naming its file."""
    expected = _hostile_everywhere(tmp_path, payload)
    run = _in_child(READERS_CHILD, tmp_path)
    assert run.returncode == 0, run.stderr[-2000:]
    results = json.loads(run.stdout)
    for name, path in expected.items():
        message = results[name].split(": ", 1)[1]
        assert message.startswith(str(path)) and phrase in message and "\n" not in message, (name, message)


@pytest.mark.parametrize("name,data,phrase", [
    ("S0 array", _s0_array(), "has zero-size items"),
    ("U0 scalar", pickle.dumps(np.str_(""), protocol=2), "has zero-size items"),
    ("101 nested lists", b"\x80\x02" + b"]" * 101 + b"a" * 100 + b".", "nested more than 100 deep"),
    ("memo index 2**32-1", b"\x80\x02]r\xff\xff\xff\xff.", "memo index 4,294,967,295"),
    ("protocol-4 frame past the end", b"\x80\x04\x95" + struct.pack("<Q", 1 << 40) + b"N.", "a frame of 1,099,511"),
    ("a list deepened after it was put in a tuple",  # l = []; t = (l,); l.append([[...]]), through the memo
     b"\x80\x02]q\x00\x85h\x00" + b"]" * 100 + b"a" * 99 + b"a0.", "nested more than 100 deep"),
    ("huge sparse matrix", pickle.dumps(sp.csc_matrix((3_000_000, 8_000)), protocol=4), "MEMORY_BUDGET"),
])
def test_bounds_refuse_before_allocating(tmp_path, name, data, phrase):
    path = tmp_path / "hostile.pkl"
    path.write_bytes(data)
    with pytest.raises(PickleReadError) as err:
        load_pickle(path)
    assert str(err.value).startswith(f"{path}: refused: ") and phrase in str(err.value), str(err.value)


def test_depth_and_items_at_the_limits_still_load(tmp_path, monkeypatch):
    path = tmp_path / "deep.pkl"
    deep: list = []
    for _ in range(MAX_PICKLE_DEPTH - 1):
        deep = [deep]
    path.write_bytes(pickle.dumps(deep, protocol=4))
    assert isinstance(load_pickle(path), list)
    monkeypatch.setattr(lsgan.pickles, "MAX_PICKLE_ITEMS", 1000)
    path.write_bytes(pickle.dumps(list(range(900)), protocol=4))
    assert load_pickle(path) == list(range(900))
    path.write_bytes(pickle.dumps(list(range(2000)), protocol=4))
    with pytest.raises(PickleReadError, match=r"refused: more than 1,000 items \(MAX_PICKLE_ITEMS\)"):
        load_pickle(path)


def test_huge_sparse_body_model_is_one_line(tmp_path):
    """A J_regressor declaring 179 GiB dense ended in 'internal error: MemoryError'."""
    data = make_model("smpl")
    data["J_regressor"] = sp.csc_matrix((3_000_000, 8_000))
    (tmp_path / "smpl").mkdir()
    (tmp_path / "smpl" / "SMPL_NEUTRAL.pkl").write_bytes(pickle.dumps(data, protocol=4))
    with pytest.raises(BodyModelError, match="192,000,000,000 bytes dense, more than MEMORY_BUDGET"):
        read_body_model(tmp_path)


@pytest.mark.parametrize("descr,shape,phrase", [("|S0", (1 << 32,), "zero-size items"),
                                                ("<f8", (1 << 20, 1 << 20), "where the file holds")])
def test_npy_and_npz_headers_are_checked_against_the_file(tmp_path, descr, shape, phrase):
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {"descr": descr, "fortran_order": False, "shape": shape})
    npy = tmp_path / "mean.npy"
    npy.write_bytes(header.getvalue() + b"\0" * 64)
    with pytest.raises(PickleReadError, match=phrase) as err:
        load_npy(npy)
    assert str(err.value).startswith(f"{npy}: refused: ")
    npz = tmp_path / "model.npz"
    np.savez(npz, f=np.zeros((2, 3), np.uint32))
    with zipfile.ZipFile(npz, "a", zipfile.ZIP_DEFLATED) as z:
        z.writestr("v_template.npy", header.getvalue() + b"\0" * 64)
    with pytest.raises(PickleReadError, match=phrase) as err:
        load_npz(npz)
    assert str(err.value).startswith(f"{npz}: entry 'v_template': refused: ")


def test_torch_legacy_format_loads_and_its_storages_are_bounded(tmp_path):
    path = tmp_path / "state.pt"
    torch.save({"step": 3, "w": torch.arange(4.0)}, path, _use_new_zipfile_serialization=False)
    assert torch.equal(load_torch_file(path)["w"], torch.arange(4.0))
    forged = path.read_bytes().replace(b"K\x04N", struct.pack("<BI", 0x4A, 1 << 30) + b"N", 1)
    assert forged != path.read_bytes()
    path.write_bytes(forged)
    with pytest.raises(ValueError, match="refused: its storages declare 1,073,741,824 elements where"):
        load_torch_file(path)
