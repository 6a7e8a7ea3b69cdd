"""Pickles read without running code: an exact allowlist of globals, each rebuilt from checked parts.

A pickle may call any importable function while it loads, so every global it names goes through
:meth:`SafeUnpickler.find_class`, which knows only the (module, name) pairs of :data:`ALLOWED` and
refuses anything else by name (``FILE: refused to unpickle 'os.system' (...)``). Nothing is matched
by prefix. Even the allowed names do not reach numpy's or scipy's own reconstructors with what the file
says: ``numpy.ndarray(shape, object, buffer)`` turns raw bytes into object pointers, ``dtype.__setstate__``
accepts object fields overlapping other fields or lying outside the item, and scipy's sparse kernels
trust their index arrays (each a crash, or worse). So a pickle only builds inert records; arrays,
dtypes and sparse matrices are then made with public constructors from checked parts: plain dtypes
(bool, numbers, bytes, str, object), data whose length matches the shape, object arrays from lists,
sparse indices inside the shape.

Used for SMPL-family ``.pkl`` models, the object entries of ``.npz`` models, the GloVe pickles of the
T2M evaluator and HumanAct12's ``humanact12poses.pkl``.
"""
from __future__ import annotations

import math
import os
import pickle
import zipfile
import zlib
from typing import Any, BinaryIO

import numpy as np
import scipy.sparse

__all__ = ["ALLOWED", "REFUSAL_HINT", "PickleReadError", "SafeUnpickler", "load_npz", "load_pickle",
           "read_npy_object"]

REFUSAL_HINT = "only arrays, dtypes and sparse matrices are read"
_DTYPE_KINDS = "biufcSUO"  # bool, ints, floats, complex, bytes, str, object: no structured/void/datetime
_PY2_MODULES = {"__builtin__": "builtins", "copy_reg": "copyreg"}  # Python 2 names of the same modules
_ATOMS = (str, bytes, int, float, bool, type(None), complex, np.ndarray, np.generic)


class PickleReadError(ValueError):
    """A pickle (or ``.npz`` entry) that was refused or could not be read; the message starts with the file.

    ``refused`` is the global (``'module.name'``) outside the allowlist that stopped it, else None.
    """

    def __init__(self, message: str, refused: str | None = None) -> None:
        super().__init__(message)
        self.refused = refused


def with_chumpy_advice(error: PickleReadError, advice: str) -> str:
    """The refusal's message, plus ``advice`` when what was refused is a chumpy object (old SMPL/MANO files)."""
    return f"{error}; {advice}" if (error.refused or "").startswith("chumpy") else str(error)


class _Invalid(Exception):
    """Parts that are not those of a plain array, dtype or sparse matrix (reported as a refusal)."""


class _Allowed:
    """An allowed global: calls ``fn`` with the pickle's positional arguments, and cannot be modified by it."""

    __slots__ = ("_fn",)

    def __init__(self, fn) -> None:
        object.__setattr__(self, "_fn", fn)

    def __call__(self, *args):
        return self._fn(*args)

    def __setattr__(self, name, value):
        raise _Invalid("a pickle may not modify an allowed global")

    def __setstate__(self, state):
        raise _Invalid("a pickle may not modify an allowed global")


class _Record:
    """What a pickle says about an array, dtype or sparse matrix, inert until a builder checks it."""

    __hash__ = None  # never a dict key or set member, where it could not be replaced by what it stands for
    state: Any = None  # NEWOBJ makes records without calling __init__

    def __init__(self) -> None:
        self.state = None

    def __setstate__(self, state) -> None:
        self.state = state


class _ArrayRecord(_Record):
    """An array from ``_reconstruct``; its BUILD state is ``([1,] shape, dtype, fortran, data)``."""


class _DtypeRecord(_Record):
    """A dtype from ``numpy.dtype(spec, align, copy)``; its BUILD state is numpy's 8- or 9-tuple."""

    def __init__(self, *args) -> None:
        super().__init__()
        self.args = args
        self.built: np.dtype | None = None

    def dtype(self) -> np.dtype:
        if self.built is None:
            self.built = _checked_dtype(self.args, self.state)
        return self.built


class _SparseRecord(_Record):
    """A scipy sparse matrix (NEWOBJ, or ``copyreg._reconstructor`` for protocols 0/1); BUILD gives its __dict__."""

    kind = ""


class _CscRecord(_SparseRecord):
    kind = "csc"


class _CsrRecord(_SparseRecord):
    kind = "csr"


class _CooRecord(_SparseRecord):
    kind = "coo"


def _only_as_argument(name: str, of: str):
    def refuse(*args):
        raise _Invalid(f"{name} is only read as an argument of {of}")
    return refuse


def _shape(value) -> tuple[int, ...]:
    if not isinstance(value, (tuple, list)) or not all(type(n) is int and n >= 0 for n in value):
        raise _Invalid(f"shape {value!r} is not a tuple of sizes")
    return tuple(value)


def _dtype_of(value) -> np.dtype:
    if isinstance(value, _DtypeRecord):
        return value.dtype()
    if isinstance(value, np.dtype):  # a record built earlier (only the builder makes real dtypes)
        return value
    raise _Invalid(f"{type(value).__name__} where a dtype belongs")


def _checked_dtype(args: tuple, state) -> np.dtype:
    """A dtype from numpy's pickled parts; plain kinds only (structured dtypes can overlap or escape items)."""
    spec = args[0] if args else None
    if not isinstance(spec, str) or len(spec) > 16:
        raise _Invalid(f"dtype {spec!r} is not a type name")
    if not isinstance(state, tuple) or len(state) not in (8, 9) or state[0] not in (3, 4):
        raise _Invalid(f"dtype {spec!r} without numpy's state")
    byteorder, subarray, names, fields, elsize = state[1:6]
    if subarray is not None or names is not None or fields is not None:
        raise _Invalid("structured and subarray dtypes are not read")
    if byteorder not in ("<", ">", "|", "="):
        raise _Invalid(f"byte order {byteorder!r}")
    base = np.dtype(spec)
    if base.kind not in _DTYPE_KINDS or base.fields is not None or base.subdtype is not None:
        raise _Invalid(f"dtype {spec!r} ({base}) is not read")
    if base.kind in "SU":
        width = 4 if base.kind == "U" else 1
        if type(elsize) is not int or elsize < 0 or elsize % width:
            raise _Invalid(f"dtype {spec!r} with item size {elsize!r}")
        base = np.dtype(f"{base.kind}{elsize // width}")
    return base.newbyteorder(byteorder) if byteorder in "<>" else base


def _from_bytes(raw, dtype: np.dtype, shape: tuple[int, ...], order: str) -> np.ndarray:
    """A writable array of ``dtype`` and ``shape`` from exactly the bytes it needs."""
    if dtype.hasobject:
        raise _Invalid("object arrays are only read from lists")
    if isinstance(raw, str):  # a Python 2 pickle read with encoding='latin1'
        raw = raw.encode("latin1")
    if not isinstance(raw, (bytes, bytearray, memoryview)):
        raise _Invalid(f"array data is a {type(raw).__name__}, not bytes")
    n = math.prod(shape)
    size = memoryview(raw).nbytes
    if size != n * dtype.itemsize:
        raise _Invalid(f"{n} items of {dtype} need {n * dtype.itemsize} bytes, the pickle has {size}")
    if n == 0 or dtype.itemsize == 0:
        return np.zeros(shape, dtype)
    return np.frombuffer(raw, dtype=dtype, count=n).reshape(shape, order=order).copy(order="K")


def _reconstruct(subtype, shape, typecode) -> _ArrayRecord:
    """numpy's ``_reconstruct(ndarray, (0,), b'b')``: the array is made from its BUILD state later."""
    if subtype is not _NDARRAY:
        raise _Invalid("arrays are only reconstructed as numpy.ndarray")
    return _ArrayRecord()


def _scalar(dtype, data=None):
    """numpy's ``scalar(dtype, bytes)``; an object scalar is the object itself, as in numpy."""
    dt = _dtype_of(dtype)
    if dt.kind == "O":
        return data
    return _from_bytes(data, dt, (), "C")[()]


def _frombuffer(buf, dtype, shape, order):
    """numpy's ``_frombuffer(buffer, dtype, shape, order)`` of protocol 5 (the buffer in band)."""
    if order not in ("C", "F"):
        raise _Invalid(f"array order {order!r}")
    return _from_bytes(buf, _dtype_of(dtype), _shape(shape), order)


def _reconstructor(cls, base, state):
    """``copyreg._reconstructor`` as protocols 0/1 use it for sparse matrices (and nothing else)."""
    if not (isinstance(cls, type) and issubclass(cls, _SparseRecord)) or base is not _OBJECT or state is not None:
        raise _Invalid("copyreg._reconstructor is only read for sparse matrices")
    return cls()


def _latin1_encode(text, encoding):
    """``_codecs.encode(str, 'latin1')``: how Python 3 pickles bytes with protocol 2."""
    if type(text) is not str or encoding not in ("latin1", "latin-1"):
        raise _Invalid("_codecs.encode is only read for latin-1 text")
    return text.encode("latin1")


def _empty_bytes(*args):
    """``bytes()``: how Python 3 pickles b'' with protocols 0-2."""
    if args:
        raise _Invalid("builtins.bytes is only read without arguments")
    return b""


_RECONSTRUCT, _SCALAR, _FROMBUFFER = _Allowed(_reconstruct), _Allowed(_scalar), _Allowed(_frombuffer)
_NDARRAY = _Allowed(_only_as_argument("numpy.ndarray", "numpy's _reconstruct"))
_OBJECT = _Allowed(_only_as_argument("builtins.object", "copyreg._reconstructor"))

ALLOWED: dict[tuple[str, str], Any] = {
    ("numpy.core.multiarray", "_reconstruct"): _RECONSTRUCT,  # arrays, numpy 1.x and Python 2 files
    ("numpy._core.multiarray", "_reconstruct"): _RECONSTRUCT,  # arrays, numpy 2 files
    ("numpy", "ndarray"): _NDARRAY,  # the type argument of _reconstruct
    ("numpy", "dtype"): _Allowed(_DtypeRecord),  # every array and scalar names its dtype
    ("numpy.core.multiarray", "scalar"): _SCALAR,  # numpy scalars (np.float64, np.int64...), numpy 1.x
    ("numpy._core.multiarray", "scalar"): _SCALAR,  # the same, numpy 2
    ("numpy.core.numeric", "_frombuffer"): _FROMBUFFER,  # arrays pickled with protocol 5, numpy 1.x
    ("numpy._core.numeric", "_frombuffer"): _FROMBUFFER,  # the same, numpy 2
    ("scipy.sparse._csc", "csc_matrix"): _CscRecord,  # SMPL's J_regressor (scipy >= 1.8)
    ("scipy.sparse.csc", "csc_matrix"): _CscRecord,  # the same, older scipy (the original SMPL files)
    ("scipy.sparse._csr", "csr_matrix"): _CsrRecord,  # cleaned/converted model files
    ("scipy.sparse.csr", "csr_matrix"): _CsrRecord,
    ("scipy.sparse._coo", "coo_matrix"): _CooRecord,
    ("scipy.sparse.coo", "coo_matrix"): _CooRecord,
    ("copyreg", "_reconstructor"): _Allowed(_reconstructor),  # sparse matrices pickled with protocol 0/1
    ("builtins", "object"): _OBJECT,  # the base argument of _reconstructor
    ("_codecs", "encode"): _Allowed(_latin1_encode),  # bytes (array data) pickled by Python 3, protocol 2
    ("builtins", "bytes"): _Allowed(_empty_bytes),  # b'' pickled by Python 3, protocols 0-2
}
"""Every global a pickle may name, as (module, name) -> what it gets instead of the real object.

Python 2's ``__builtin__`` and ``copy_reg`` are read as ``builtins`` and ``copyreg``."""


class _Builder:
    """Replaces the records in an unpickled object by the checked arrays, dtypes and matrices they stand for."""

    _BUSY = object()

    def __init__(self) -> None:
        self.done: dict[int, Any] = {}
        self.alive: list[Any] = []  # keeps every visited object alive, so that no id is reused

    def finish(self, obj):
        if isinstance(obj, _ATOMS):
            return obj
        key = id(obj)
        if key in self.done:
            if self.done[key] is self._BUSY:
                raise _Invalid("an array or sparse matrix contains itself")
            return self.done[key]
        self.alive.append(obj)
        if isinstance(obj, dict):
            self.done[key] = obj
            for k, v in list(obj.items()):
                obj[k] = self.finish(v)
        elif isinstance(obj, list):
            self.done[key] = obj
            obj[:] = [self.finish(v) for v in obj]
        elif isinstance(obj, tuple):
            self.done[key] = obj
            self.done[key] = obj = tuple(self.finish(v) for v in obj)
        elif isinstance(obj, _Record):
            self.done[key] = self._BUSY
            self.done[key] = obj = self._build(obj)
        return obj

    def _build(self, record: _Record):
        if isinstance(record, _DtypeRecord):
            return record.dtype()
        if isinstance(record, _SparseRecord):
            return self._sparse(record)
        state = record.state
        if not isinstance(state, tuple) or len(state) not in (4, 5):
            raise _Invalid("an array without numpy's state")
        shape, dtype, fortran, data = state[-4:]
        shape, dtype = _shape(shape), _dtype_of(dtype)
        if dtype.kind != "O":
            return _from_bytes(data, dtype, shape, "F" if fortran else "C")
        n = math.prod(shape)
        if not isinstance(data, list) or len(data) != n:
            raise _Invalid(f"an object array of {n} items without a list of {n} items")
        items = [self.finish(v) for v in data]
        return np.fromiter(items, dtype=object, count=n).reshape(shape)

    def _numeric(self, value, what: str) -> np.ndarray:
        array = self.finish(value)
        if not isinstance(array, np.ndarray) or array.ndim != 1 or array.dtype.kind not in "biufc":
            raise _Invalid(f"a sparse matrix's {what} is not a 1-d numeric array")
        return array

    def _sparse(self, record: _SparseRecord):
        """The matrix from its attributes, through scipy's constructor and full format check."""
        state = record.state
        if not isinstance(state, dict):
            raise _Invalid("a sparse matrix without its attributes")
        shape = _shape(self.finish(state.get("_shape")))
        if len(shape) != 2:
            raise _Invalid(f"a sparse matrix of shape {shape}")
        data = self._numeric(state.get("data"), "data")
        if record.kind == "coo":
            coords = self.finish(state["coords"] if "coords" in state else (state.get("row"), state.get("col")))
            if not isinstance(coords, tuple) or len(coords) != 2:
                raise _Invalid("a coo matrix without two index arrays")
            row, col = (self._numeric(c, "indices") for c in coords)
            if not len(row) == len(col) == len(data):
                raise _Invalid("a coo matrix whose index and data arrays differ in length")
            parts: tuple = (data, (row, col))
        else:
            parts = (data, self._numeric(state.get("indices"), "indices"), self._numeric(state.get("indptr"), "indptr"))
        cls = {"csc": scipy.sparse.csc_matrix, "csr": scipy.sparse.csr_matrix, "coo": scipy.sparse.coo_matrix}
        try:
            matrix = cls[record.kind](parts, shape=shape)  # coo_matrix checks its indices against the shape here
            if record.kind != "coo":
                matrix.check_format(full_check=True)
        except ValueError as exc:
            raise _Invalid(f"a {record.kind} matrix that fails scipy's format check ({exc})") from None
        return matrix


class SafeUnpickler(pickle.Unpickler):
    """``pickle.Unpickler`` that knows only the globals of :data:`ALLOWED`; ``load`` returns checked objects.

    ``source`` (the file) starts every error message. Python 2 pickles are read with
    ``encoding='latin1'``, numpy's own choice for them.
    """

    def __init__(self, file: BinaryIO, source: str) -> None:
        super().__init__(file, encoding="latin1")
        self.source = source

    def find_class(self, module: str, name: str) -> Any:
        found = ALLOWED.get((_PY2_MODULES.get(module, module), name))
        if found is None:
            raise PickleReadError(f"{self.source}: refused to unpickle '{module}.{name}' ({REFUSAL_HINT})",
                                  refused=f"{module}.{name}")
        return found

    def load(self) -> Any:
        return _Builder().finish(super().load())


def _unpickle(fh: BinaryIO, source: str) -> Any:
    """SafeUnpickler(fh).load() with every failure as a PickleReadError naming ``source``."""
    try:
        return SafeUnpickler(fh, source).load()
    except PickleReadError:
        raise
    except _Invalid as exc:
        raise PickleReadError(f"{source}: refused: {exc} ({REFUSAL_HINT})") from None
    except RecursionError:
        raise PickleReadError(f"{source}: refused: nested too deeply") from None
    except Exception as exc:  # noqa: BLE001 - whatever a damaged pickle raises (EOFError, UnpicklingError...)
        raise PickleReadError(f"{source}: truncated or corrupt pickle ({type(exc).__name__}: {exc})") from exc


def load_pickle(path: str | os.PathLike) -> Any:
    """The object in the pickle file ``path``, read by :class:`SafeUnpickler` (so no code in it runs)."""
    try:
        fh = open(path, "rb")
    except OSError as exc:
        raise PickleReadError(f"{path}: cannot open it ({exc.strerror or exc})") from exc
    with fh:
        return _unpickle(fh, str(path))


def _object_npy_shape(fh: BinaryIO) -> tuple[int, ...] | None:
    """The shape in an ``.npy`` header when its dtype holds objects (the payload is then a pickle), else None."""
    try:
        version = np.lib.format.read_magic(fh)
        read_header = {(1, 0): np.lib.format.read_array_header_1_0,
                       (2, 0): np.lib.format.read_array_header_2_0}.get(version)
        if read_header is None:
            return None
        shape, _, dtype = read_header(fh)
    except ValueError:
        return None  # not a header this reader knows: numpy's own reader reports it
    return shape if dtype.hasobject else None


def _object_payload(fh: BinaryIO, source: str, shape: tuple[int, ...]) -> np.ndarray:
    array = _unpickle(fh, source)
    if not isinstance(array, np.ndarray) or array.shape != tuple(shape):
        raise PickleReadError(f"{source}: the pickle does not hold the {tuple(shape)} array its header names")
    return array


def read_npy_object(fh: BinaryIO, source: str) -> np.ndarray:
    """The object array of an ``.npy`` stream: numpy writes it as a header then a pickle, read here safely."""
    shape = _object_npy_shape(fh)
    if shape is None:
        raise PickleReadError(f"{source}: not an .npy object array (read numeric arrays with allow_pickle=False)")
    return _object_payload(fh, source, shape)


def load_npz(path: str | os.PathLike, keys: tuple[str, ...] | None = None) -> dict[str, Any]:
    """The entries of an ``.npz`` (all, or those of ``keys`` it has), never with ``allow_pickle=True``.

    Numeric entries are read by numpy without pickles; object entries (e.g. a 0-d array holding a sparse
    matrix) through :func:`read_npy_object`. Errors are PickleReadError naming the file and entry.
    """
    out: dict[str, Any] = {}
    try:
        with np.load(path, allow_pickle=False) as npz:
            names = set(npz.zip.namelist())
            for key in [k for k in (npz.files if keys is None else keys) if k in npz.files]:
                with npz.zip.open(key if key in names else f"{key}.npy") as fh:
                    shape = _object_npy_shape(fh)
                    if shape is not None:
                        out[key] = _object_payload(fh, f"{path}: entry {key!r}", shape)
                        continue
                out[key] = npz[key]
    except PickleReadError:
        raise
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
        raise PickleReadError(f"{path}: cannot read it as .npz ({exc})") from exc
    return out
