"""Every unpickling in lsgan: bounds checked on the opcode stream first, then an exact allowlist of globals.

Before anything is unpickled, :func:`check_pickle` walks the opcode stream with ``pickletools.genops``
(which executes nothing) and a model of the unpickler's stack, and refuses nesting deeper than
:data:`MAX_PICKLE_DEPTH`, more than :data:`MAX_PICKLE_ITEMS` items and strings, frames or memo indices
that claim more than the file holds. Then a pickle may still call any importable function while it loads,
so every global it names goes through :meth:`SafeUnpickler.find_class`, which knows only the (module,
name) pairs of :data:`ALLOWED` and refuses anything else by name (``FILE: refused to unpickle 'os.system'
(...)``). Nothing is matched by prefix. Even the allowed names do not reach numpy's or scipy's own
reconstructors with what the file says: ``numpy.ndarray(shape, object, buffer)`` turns raw bytes into
object pointers, ``dtype.__setstate__`` accepts object fields overlapping other fields or lying outside the
item, and scipy's sparse kernels trust their index arrays (each a crash, or worse). So a pickle only builds
inert records; arrays, dtypes and sparse matrices are then made with public constructors from checked
parts: plain dtypes with items of non-zero size, data whose length matches the shape, object arrays from
lists, sparse indices inside the shape and a dense size within :data:`MEMORY_BUDGET`, and all the arrays of one
pickle within it too (data the memo shares is copied for each array made from it).

Used for SMPL-family ``.pkl`` models, the object entries of ``.npz`` models, the GloVe pickles of the
T2M evaluator and HumanAct12's ``humanact12poses.pkl``; :func:`load_torch` scans the pickles of a torch
checkpoint (``state.pt``, the evaluator's ``finest.tar``) before ``torch.load(weights_only=True)`` reads
it; :func:`load_npy` and :func:`load_npz` check an array's header against the bytes that could hold it
before numpy allocates it. ``tests/test_pickles.py`` fails if another module unpickles.
"""
from __future__ import annotations

import io
import math
import os
import pickle
import pickletools
import re
import zipfile
import zlib
from contextvars import ContextVar
from typing import Any, BinaryIO

import numpy as np

__all__ = ["ALLOWED", "DEFLATE_MAX_RATIO", "MAX_PICKLE_DEPTH", "MAX_PICKLE_ITEMS", "MEMORY_BUDGET", "REFUSAL_HINT",
           "PickleReadError", "SafeUnpickler", "check_pickle", "load_npy", "load_npz", "load_pickle", "load_torch",
           "read_npy_object"]

MAX_PICKLE_DEPTH = 100
"""Deepest nesting of containers a pickle may build, as the scan counts it. Real inputs nest under 10 deep (an
SMPL model with a sparse J_regressor 7, an optimiser's state in state.pt 6, an object array of sparse
matrices 9). CPython hashes nested tuples recursively in C with no depth check, so a 1 MB pickle of a tuple
nested 1,000,000 deep used as a dict key overflows the C stack (SIGSEGV) inside the unpickler; 100 also keeps
lsgan's own recursive rebuild far below Python's recursion limit."""

MAX_PICKLE_ITEMS = 20_000_000
"""Most opcodes a pickle may hold. Each may make a Python object of 50-100 bytes from one byte of file,
so this bounds the unpickled objects to about 2 GB; real inputs hold far fewer (a HumanAct12-sized pickle of
1,191 clips about 100,000; a word -> index dict of 400,000 words, GloVe 6B's vocabulary, 1,200,000)."""

MEMORY_BUDGET = 1 << 30
"""Most bytes (1 GiB) a reader allocates on a file's word: a pickle file or pickled entry read into memory, the
dense size of a sparse matrix (body models turn them dense), an ``.npz`` entry compressed with anything but
deflate, and all the arrays one pickle builds together (see :class:`_Meter`; without shared data they are no
larger than the file). The largest real entries are about 100 MB (SMPL-X's shapedirs, 10475x3x400 float64)."""

DEFLATE_MAX_RATIO = 1032
"""Deflate's largest possible compression ratio: a deflated zip member cannot inflate to more than this many
times its stored size, whatever its header declares."""

REFUSAL_HINT = "only arrays, dtypes and sparse matrices are read"
_DTYPE_KINDS = "biufcSUO"  # bool, ints, floats, complex, bytes, str, object: no structured/void/datetime
_PY2_MODULES = {"__builtin__": "builtins", "copy_reg": "copyreg"}  # Python 2 names of the same modules
_ATOMS = (str, bytes, int, float, bool, type(None), complex, np.ndarray, np.generic)


class PickleReadError(ValueError):
    """A pickle (or ``.npz`` entry) that was refused or could not be read; the message starts with the file.

    ``refused`` is the global (``'module.name'``) outside the allowlist that stopped it, else None.
    """

    def __init__(self, message: str, refused: str | None = None) -> None:
        super().__init__(re.sub(r"\s*\n\s*", " ", message))  # one line, whatever the quoted cause held
        self.refused = refused


def with_chumpy_advice(error: PickleReadError, advice: str) -> str:
    """The refusal's message, plus ``advice`` when what was refused is a chumpy object (old SMPL/MANO files)."""
    return f"{error}; {advice}" if (error.refused or "").startswith("chumpy") else str(error)


class _Invalid(Exception):
    """Parts that are not those of a plain array, dtype or sparse matrix (reported as a refusal)."""


class _Bound(_Invalid):
    """A pickle that breaks one of the bounds (reported as a refusal, without the allowlist's hint)."""


class _Corrupt(Exception):
    """An opcode stream no unpickler could read (reported as a truncated or corrupt pickle)."""


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
    if base.itemsize == 0:
        raise _Invalid(f"dtype {spec!r} has zero-size items")
    return base.newbyteorder(byteorder) if byteorder in "<>" else base


class _Meter:
    """The bytes the arrays of one pickle take, counted before each is made: data that the pickle shares through
    its memo is copied for every array made from it, so a 21 MB file can ask for 10 GB (500 arrays of one 20 MB
    string). Past MEMORY_BUDGET the pickle is refused."""

    def __init__(self) -> None:
        self.spent = 0

    def spend(self, nbytes: int) -> None:
        self.spent += nbytes
        if self.spent > MEMORY_BUDGET:
            raise _Bound(f"the arrays it builds would take more than MEMORY_BUDGET ({MEMORY_BUDGET:,} bytes); data "
                         "it shares between arrays is copied for each")


_METER: ContextVar[_Meter | None] = ContextVar("lsgan_pickle_meter", default=None)


def _allocating(nbytes: int) -> None:
    """Count ``nbytes`` about to be allocated against the current load's :class:`_Meter` (if one is running)."""
    meter = _METER.get()
    if meter is not None:
        meter.spend(nbytes)


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
    _allocating(size)
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
    _allocating(len(text))
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
        _allocating(2 * n * dtype.itemsize)  # the list of built items, then the array
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
        if math.prod(shape) * 8 > MEMORY_BUDGET:
            raise _Bound(f"a sparse matrix of shape {shape} is {math.prod(shape) * 8:,} bytes dense, more than "
                         f"MEMORY_BUDGET ({MEMORY_BUDGET:,})")
        data = self._numeric(state.get("data"), "data")
        if record.kind == "coo":
            coords = self.finish(state["coords"] if "coords" in state else (state.get("row"), state.get("col")))
            if not isinstance(coords, tuple) or len(coords) != 2:
                raise _Invalid("a coo matrix without two index arrays")
            row, col = (self._numeric(c, "indices") for c in coords)
            if not len(row) == len(col) == len(data):
                raise _Invalid("a coo matrix whose index and data arrays differ in length")
            parts: tuple = (data, (row, col))
            arrays = (data, row, col)
        else:
            parts = arrays = (data, self._numeric(state.get("indices"), "indices"),
                              self._numeric(state.get("indptr"), "indptr"))
        _allocating(sum(a.nbytes for a in arrays))  # scipy may copy them (a shared array, once per matrix)
        import scipy.sparse  # only here: most readers of this module never meet a sparse matrix

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
        token = _METER.set(_Meter())
        try:
            return _Builder().finish(super().load())
        finally:
            _METER.reset(token)


# ------------------------------------------------------------------------------------------------------------------
# The opcode scan: bounds checked on the stream before anything is unpickled


class _Node:
    """A container (or an object built by a call) on the scan's model stack: how deep it nests, who holds it."""

    __slots__ = ("depth", "parents", "items")

    def __init__(self, depth: int, items: tuple | None = None) -> None:
        self.depth, self.parents, self.items = depth, [], items


def _depth(value) -> int:
    return value.depth if value.__class__ is _Node else 0


class _Stream:
    """What ``pickletools.genops`` reads from: ``data`` from ``pos``; a declared length past the end is refused
    before anything of that size is allocated."""

    def __init__(self, data: bytes, pos: int = 0) -> None:
        self.data, self.pos = data, pos

    def read(self, n: int) -> bytes:
        left = len(self.data) - self.pos
        if n > left and n > 8:  # a string or frame length (shorter reads are genops' own 'truncated' errors)
            raise _Bound(f"it declares {n:,} bytes where {left:,} remain")
        out = self.data[self.pos:self.pos + n]
        self.pos += len(out)
        return out

    def readline(self) -> bytes:
        end = self.data.find(b"\n", self.pos)
        return self.read((len(self.data) if end < 0 else end + 1) - self.pos)

    def tell(self) -> int:
        return self.pos


_CONTAINERS = {"TUPLE", "TUPLE1", "TUPLE2", "TUPLE3", "LIST", "DICT", "FROZENSET", "EMPTY_TUPLE", "EMPTY_LIST",
               "EMPTY_DICT", "EMPTY_SET"}
_MUTATORS = {"APPEND", "APPENDS", "SETITEM", "SETITEMS", "ADDITEMS", "BUILD"}
_INTS = {"INT", "BININT", "BININT1", "BININT2", "LONG", "LONG1", "LONG4"}
_STRINGS = {"UNICODE", "SHORT_BINUNICODE", "BINUNICODE", "BINUNICODE8", "STRING", "BINSTRING", "SHORT_BINSTRING"}
_PUTS = {"PUT", "BINPUT", "LONG_BINPUT"}
_GETS = {"GET", "BINGET", "LONG_BINGET"}


class _Scan:
    """A model of the unpickler's stack, marks and memo, run over ``pickletools.genops`` (which executes
    nothing): refuses nesting past :data:`MAX_PICKLE_DEPTH`, more than :data:`MAX_PICKLE_ITEMS` items (opcodes,
    plus the updates of depths they cause) and memo indices beyond the items read. Stack underflows and
    missing marks or memo entries are the corruption the unpickler would report, found first."""

    def __init__(self) -> None:
        self.stack: list = []
        self.marks: list[int] = []
        self.memo: dict[int, Any] = {}
        self.items = 0
        self.storages: list = []  # (key, element count) of each torch storage: items 2 and 4 of a persistent id

    def run(self, stream: _Stream) -> None:
        """Scan one pickle, up to and including its STOP."""
        self.stack.clear()
        self.marks.clear()
        self.memo.clear()
        for op, arg, _ in pickletools.genops(stream):
            self._count(1)
            name = op.name
            if name in _CONTAINERS:
                self._container(self._pop(op.stack_before))
            elif name in _MUTATORS:
                self._mutate(self._pop(op.stack_before))
            elif name in _INTS or name in _STRINGS:  # their values: a torch storage's key and size (legacy format)
                self.stack.append(arg if name in _INTS or len(arg) <= 64 else None)
            elif name in _PUTS or name == "MEMOIZE":
                self._put(len(self.memo) if name == "MEMOIZE" else arg)
            elif name in _GETS:
                self._get(arg)
            elif name == "FRAME" and arg > len(stream.data) - stream.pos:
                raise _Bound(f"a frame of {arg:,} bytes declared where {len(stream.data) - stream.pos:,} remain")
            else:
                self._other(op)

    def _count(self, n: int) -> None:
        self.items += n
        if self.items > MAX_PICKLE_ITEMS:
            raise _Bound(f"more than {MAX_PICKLE_ITEMS:,} items (MAX_PICKLE_ITEMS)")

    def _pop(self, before: list) -> list:
        """The values ``before`` names, the marked slice included; below the last mark is out of reach."""
        taken: list = []
        if pickletools.markobject in before:
            if not self.marks:
                raise _Corrupt("an opcode needs a MARK that is not there")
            mark = self.marks.pop()
            taken, self.stack[mark:] = self.stack[mark:], []
            before = before[:before.index(pickletools.markobject)]
        fence = self.marks[-1] if self.marks else 0
        if len(self.stack) - len(before) < fence:
            raise _Corrupt("the stack underflows")
        if before:
            taken = self.stack[-len(before):] + taken
            del self.stack[-len(before):]
        return taken

    def _container(self, items: list) -> None:
        node = _Node(max(map(_depth, items), default=0) + 1, tuple(items) if len(items) <= 8 else None)
        if node.depth > MAX_PICKLE_DEPTH:
            raise _Bound(f"containers nested more than {MAX_PICKLE_DEPTH} deep (MAX_PICKLE_DEPTH)")
        for item in items:
            if item.__class__ is _Node:
                item.parents.append(node)
        self.stack.append(node)

    def _mutate(self, values: list) -> None:
        """APPEND(S), SETITEM(S), ADDITEMS, BUILD: the target gets deeper, and so does every container holding it."""
        target, items = values[0], values[1:]
        self.stack.append(target)
        if target.__class__ is not _Node:
            return
        for item in items:
            if item.__class__ is _Node:
                item.parents.append(target)
        work = [(target, max(map(_depth, items), default=0) + 1)]
        while work:
            node, depth = work.pop()
            if depth <= node.depth:
                continue
            if depth > MAX_PICKLE_DEPTH:
                raise _Bound(f"containers nested more than {MAX_PICKLE_DEPTH} deep (MAX_PICKLE_DEPTH), or one "
                               "contains itself")
            node.depth = depth
            self._count(len(node.parents))
            work += [(parent, depth + 1) for parent in node.parents]

    def _put(self, index: int) -> None:
        if index > self.items:
            raise _Bound(f"memo index {index:,} beyond the {self.items:,} items read")
        if len(self.stack) <= (self.marks[-1] if self.marks else 0):
            raise _Corrupt("a memo entry of nothing")
        self.memo[index] = self.stack[-1]

    def _get(self, index: int) -> None:
        if index not in self.memo:
            raise _Corrupt(f"memo entry {index} read before it is written")
        self.stack.append(self.memo[index])

    def _other(self, op) -> None:
        """Every other opcode: pops what it reads; what it pushes holds what it read (a call's result its args)."""
        if op.name == "POP" and self.marks and len(self.stack) == self.marks[-1]:
            self.marks.pop()  # as CPython's unpickler does: POP right after a MARK drops the mark
            return
        values = self._pop(op.stack_before)
        if op.name == "BINPERSID":
            pid = values[0].items if values[0].__class__ is _Node else None
            self.storages.append((pid[2], pid[4]) if pid is not None and len(pid) >= 5 else (None, None))
        after = op.stack_after
        if pickletools.markobject in after:
            self.marks.append(len(self.stack))
        elif op.name == "DUP":
            self.stack += values * 2
        elif after and values:
            result = _Node(max(map(_depth, values)))
            for value in values:
                if value.__class__ is _Node:
                    value.parents.append(result)
            self.stack.append(result)
        elif after:
            self.stack.append(None)


# ------------------------------------------------------------------------------------------------------------------
# Entry points: every unpickling in lsgan (and every .npy/.npz read whose header could claim more than the file)


def _refusing(source: str, work):
    """``work()`` with a scan's or builder's objection as a PickleReadError naming ``source``."""
    try:
        return work()
    except PickleReadError:
        raise
    except _Bound as exc:
        raise PickleReadError(f"{source}: refused: {exc}") from None
    except _Invalid as exc:
        raise PickleReadError(f"{source}: refused: {exc} ({REFUSAL_HINT})") from None
    except _Corrupt as exc:
        raise PickleReadError(f"{source}: truncated or corrupt pickle ({exc})") from None
    except RecursionError:
        raise PickleReadError(f"{source}: refused: nested too deeply") from None
    except Exception as exc:  # noqa: BLE001 - whatever a damaged pickle raises (EOFError, UnpicklingError...)
        raise PickleReadError(f"{source}: truncated or corrupt pickle ({type(exc).__name__}: {exc})") from None


def check_pickle(data: bytes, source: str, pos: int = 0, scan: _Scan | None = None) -> int:
    """Scan the pickle at ``data[pos:]`` without unpickling it (see :class:`_Scan`); returns where it ends.

    PickleReadError naming ``source`` when it breaks a bound or is damaged.
    """
    stream = _Stream(data, pos)
    _refusing(source, lambda: (scan or _Scan()).run(stream))
    return stream.pos


def _unpickle(data: bytes, source: str) -> Any:
    """The checked object in the pickle ``data``: scanned first, then read by :class:`SafeUnpickler`."""
    check_pickle(data, source)
    return _refusing(source, lambda: SafeUnpickler(io.BytesIO(data), source).load())


def _read_file(path: str | os.PathLike) -> bytes:
    """The bytes of ``path``, refused past :data:`MEMORY_BUDGET`."""
    try:
        with open(path, "rb") as fh:
            size = os.fstat(fh.fileno()).st_size
            if size > MEMORY_BUDGET:
                raise PickleReadError(f"{path}: refused: {size:,} bytes, more than MEMORY_BUDGET ({MEMORY_BUDGET:,})")
            return fh.read()
    except OSError as exc:
        raise PickleReadError(f"{path}: cannot open it ({exc.strerror or exc})") from exc


def load_pickle(path: str | os.PathLike) -> Any:
    """The object in the pickle file ``path``: scanned for bounds, then read by :class:`SafeUnpickler` (so no
    code in it runs)."""
    return _unpickle(_read_file(path), str(path))


def _npy_header(fh: BinaryIO) -> tuple[tuple[int, ...], np.dtype] | None:
    """(shape, dtype) from an ``.npy`` header, the stream left at the data; None when numpy's own reader should
    report what is wrong with it."""
    try:
        version = np.lib.format.read_magic(fh)
        if version not in ((1, 0), (2, 0), (3, 0)):
            return None
        read = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
        shape, _, dtype = read(fh)
    except (ValueError, EOFError):
        return None
    return shape, dtype


def _check_declared(source: str, shape: tuple[int, ...], dtype: np.dtype, available: int) -> None:
    """Refuse zero-size items and an array larger than the ``available`` bytes that could hold its data."""
    if dtype.itemsize == 0:
        raise PickleReadError(f"{source}: refused: dtype {dtype} has zero-size items")
    declared = math.prod(shape) * dtype.itemsize
    if declared > available:
        raise PickleReadError(f"{source}: refused: its header declares a {tuple(shape)} {dtype} array of "
                              f"{declared:,} bytes where the file holds {max(available, 0):,}")


def _pickled_payload(fh: BinaryIO, source: str, shape: tuple[int, ...], limit: int) -> np.ndarray:
    """The object array after an ``.npy`` header: a pickle of at most ``limit`` bytes, read safely."""
    data = fh.read(min(limit, MEMORY_BUDGET) + 1)
    if len(data) > min(limit, MEMORY_BUDGET):
        raise PickleReadError(f"{source}: refused: a pickled entry larger than MEMORY_BUDGET ({MEMORY_BUDGET:,})")
    array = _unpickle(data, source)
    if not isinstance(array, np.ndarray) or array.shape != tuple(shape):
        raise PickleReadError(f"{source}: the pickle does not hold the {tuple(shape)} array its header names")
    return array


def read_npy_object(fh: BinaryIO, source: str) -> np.ndarray:
    """The object array of an ``.npy`` stream: numpy writes it as a header then a pickle, read here safely."""
    header = _npy_header(fh)
    if header is None or not header[1].hasobject:
        raise PickleReadError(f"{source}: not an .npy object array (read numeric arrays with allow_pickle=False)")
    return _pickled_payload(fh, source, header[0], MEMORY_BUDGET)


def load_npy(path: str | os.PathLike) -> np.ndarray:
    """A numeric ``.npy`` file, its header checked against the file's size first (numpy allocates what the header
    declares before reading); PickleReadError naming the file for anything else."""
    try:
        with open(path, "rb") as fh:
            header = _npy_header(fh)
            if header is not None:
                if header[1].hasobject:
                    raise PickleReadError(f"{path}: holds Python objects, not numbers; not read")
                _check_declared(str(path), *header, os.fstat(fh.fileno()).st_size - fh.tell())
            fh.seek(0)
            return np.lib.format.read_array(fh, allow_pickle=False)
    except PickleReadError:
        raise
    except OSError as exc:
        raise PickleReadError(f"{path}: cannot open it ({exc.strerror or exc})") from exc
    except (ValueError, EOFError) as exc:
        raise PickleReadError(f"{path}: truncated or corrupt .npy file ({exc})") from None


def _member_capacity(info: zipfile.ZipInfo) -> int:
    """The most bytes a zip member can inflate to: its size as stored, x1032 deflated, the budget otherwise."""
    if info.compress_type == zipfile.ZIP_STORED:
        return min(info.file_size, info.compress_size)
    if info.compress_type == zipfile.ZIP_DEFLATED:
        return min(info.file_size, info.compress_size * DEFLATE_MAX_RATIO)
    return min(info.file_size, MEMORY_BUDGET)


def _npz_entry(npz, key: str, path: str | os.PathLike) -> Any:
    """One entry of an open ``np.load`` archive: its header checked, a pickled one read safely."""
    info = npz.zip.getinfo(key if key in npz.zip.namelist() else f"{key}.npy")
    source = f"{path}: entry {key!r}"
    with npz.zip.open(info) as fh:
        header = _npy_header(fh)
        if header is not None and header[1].hasobject:
            return _pickled_payload(fh, source, header[0], _member_capacity(info) - fh.tell())
        if header is not None:
            _check_declared(source, *header, min(_member_capacity(info) - fh.tell(), MEMORY_BUDGET))
    return npz[key]


def load_npz(path: str | os.PathLike, keys: tuple[str, ...] | None = None) -> dict[str, Any]:
    """The entries of an ``.npz`` (all, or those of ``keys`` it has), never with ``allow_pickle=True``.

    Numeric entries are read by numpy after their headers are checked against what the archive holds;
    object entries (e.g. a 0-d array holding a sparse matrix) through the scan and :class:`SafeUnpickler`.
    Errors are PickleReadError naming the file and entry.
    """
    try:
        with np.load(path, allow_pickle=False) as npz:
            return {key: _npz_entry(npz, key, path)
                    for key in [k for k in (npz.files if keys is None else keys) if k in npz.files]}
    except PickleReadError:
        raise
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
        raise PickleReadError(f"{path}: cannot read it as .npz ({exc})") from exc


# ------------------------------------------------------------------------------------------------------------------
# torch files: the pickles inside are scanned, then torch.load(weights_only=True) reads them


def _scan_torch_zip(path: str | os.PathLike) -> None:
    """Scan every ``*.pkl`` member of a torch zip checkpoint (``data.pkl``, whatever folder holds it)."""
    try:
        with zipfile.ZipFile(path) as z:
            for info in z.infolist():
                if info.filename.endswith(".pkl"):
                    if _member_capacity(info) > MEMORY_BUDGET:
                        raise PickleReadError(f"{path}: refused: {info.filename} declares {info.file_size:,} bytes, "
                                              f"more than MEMORY_BUDGET ({MEMORY_BUDGET:,})")
                    check_pickle(z.read(info), f"{path}: {info.filename}")
    except (zipfile.BadZipFile, zlib.error, EOFError, NotImplementedError) as exc:
        raise PickleReadError(f"{path}: truncated or corrupt ({exc})") from None


def _scan_torch_legacy(data: bytes, path: str) -> None:
    """Scan the pickles of torch's format before 1.6 (magic, protocol, system info, the object, storage keys);
    the storages it declares (torch allocates them before reading their data) must fit in what follows."""
    scan, pos = _Scan(), 0
    for _ in range(5):
        if pos >= len(data):
            break
        pos = check_pickle(data, path, pos, scan)
    numels: dict[str, int] = {}
    for key, n in scan.storages:
        if type(key) is not str or type(n) is not int or n < 0:
            raise PickleReadError(f"{path}: refused: a storage without a plain key and element count")
        numels[key] = max(numels.get(key, 0), n)  # tensors sharing a storage name it again
    if sum(numels.values()) > len(data) - pos:
        raise PickleReadError(f"{path}: refused: its storages declare {sum(numels.values()):,} elements where "
                              f"{len(data) - pos:,} bytes remain")


def load_torch(path: str | os.PathLike) -> Any:
    """``torch.load(path, weights_only=True)`` on the CPU, after its pickles passed :func:`check_pickle`;
    PickleReadError (a ValueError) naming the file when it is refused or damaged."""
    try:
        with open(path, "rb") as fh:
            is_zip = fh.read(4) == b"PK\x03\x04"  # torch's own test for its zip format
    except OSError as exc:
        raise PickleReadError(f"{path}: cannot read it ({exc.strerror or exc})") from exc
    if is_zip:
        _scan_torch_zip(path)
    else:
        _scan_torch_legacy(_read_file(path), str(path))
    return _torch_load(path)


def _torch_error_detail(text: str) -> str:
    """The cause in one of torch's load errors, without its advice to load the file with weights_only=False."""
    found = re.search(r"GLOBAL (\S+)", text)
    if found:
        return found.group(1)
    lines = [ln.strip() for ln in text.replace("WeightsUnpickler error:", "\n").splitlines()]
    lines = [ln for ln in lines if ln and not re.search(r"weights_only|torch\.load|pytorch\.org", ln)]
    return (lines[0] if lines else "no detail")[:200]


def _torch_load(path: str | os.PathLike) -> Any:
    """torch.load with weights_only=True, its errors as one line naming the file (never its weights_only advice)."""
    import torch

    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        detail = _torch_error_detail(str(exc))
        if re.search(r"GLOBAL|Unsupported (global|class)|blocked|not an allowed", str(exc)):
            raise PickleReadError(f"{path}: refused: it holds objects other than tensors and plain values "
                                  f"({detail})") from None
        raise PickleReadError(f"{path}: truncated or corrupt ({detail})") from None
    except RuntimeError as exc:
        if "TorchScript" in str(exc):
            raise PickleReadError(f"{path}: refused: it is a TorchScript archive, not tensors and plain "
                                  "values") from None
        raise PickleReadError(f"{path}: truncated or corrupt ({_torch_error_detail(str(exc))})") from None
    except OSError as exc:
        raise PickleReadError(f"{path}: cannot read it ({exc.strerror or exc})") from exc
    except Exception as exc:  # noqa: BLE001 - whatever else a damaged file raises (EOFError, KeyError...)
        raise PickleReadError(f"{path}: truncated or corrupt ({type(exc).__name__}: {exc})") from None
