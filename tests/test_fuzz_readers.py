"""Fuzzing the readers (issue 28): hostile pickles and BVH files either read or raise the reader's one-line error.

Hypothesis makes pickle opcode streams (random bytes, real pickles mutated byte by byte, containers nested up
to 1,000,000 deep, string/frame/memo arguments declaring up to 2**63 bytes) and feeds each to every loader of
lsgan.pickles: a bare pickle file, an object entry of an .npz, the data.pkl of a torch zip checkpoint and a
bare (legacy-format) torch file. It makes BVH files (random hierarchies and channel orders, frame counts from
-5 to 10**12, frame times from 0, negative, NaN and 100000 to 1e-9 s, bodies that match or not, LF, CRLF or
CR line ends, a UTF-8 byte-order mark, gzip, then random byte damage) and feeds each to the BVH reader, and
what it reads to forward kinematics and to the resampling to 20 fps.

Each example must read, or raise the reader's error type (PickleReadError, ClipError) with one line that
starts with the file name and does not hide a MemoryError. The examples run in a child Python whose address
space is limited to what it uses after its imports plus ALLOC_HEADROOM (resource.setrlimit RLIMIT_AS): a
crash kills the child, not pytest, and an allocation of more than the headroom fails the example.

Budgets: PICKLE_EXAMPLES (500) and BVH_EXAMPLES (800) examples, DEADLINE (5 s) per example, no example
database (nothing is written to the repository). Each test takes about 10 s on the 2-core machine (7.5-10.5 s
measured, child start-up included).
"""
from __future__ import annotations

import gzip
import io
import os
import pickle
import resource
import struct
import subprocess
import sys
import tempfile
import zipfile
from datetime import timedelta
from pathlib import Path

import numpy as np
import scipy.sparse as sp
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

PICKLE_EXAMPLES = 500
BVH_EXAMPLES = 800
DEADLINE = timedelta(seconds=5)
ALLOC_HEADROOM = 2 << 30
SETTINGS = {"deadline": DEADLINE, "database": None, "suppress_health_check": [HealthCheck.too_slow],
            "print_blob": True}


def limit_memory() -> None:
    """Cap this process's address space at what it maps now plus ALLOC_HEADROOM."""
    with open("/proc/self/status") as status:
        vm = next(int(line.split()[1]) * 1024 for line in status if line.startswith("VmSize:"))
    resource.setrlimit(resource.RLIMIT_AS, (vm + ALLOC_HEADROOM, vm + ALLOC_HEADROOM))


def assert_one_line(error: BaseException, path: Path) -> None:
    message = str(error)
    assert message.startswith(str(path)), message
    assert "\n" not in message and "MemoryError" not in message, message


# ------------------------------------------------------------------------------------------------------------------
# Pickles


def _seeds() -> list[bytes]:
    """Real pickles of what the readers meet (arrays, scalars, sparse matrices, plain values), protocols 0-5."""
    rng = np.random.default_rng(0)
    values = [{"v": rng.normal(size=(3, 2)), "f": np.arange(6, dtype=np.uint32), "s": np.float64(1.5)},
              {"J": sp.csc_matrix(np.eye(3)), "c": sp.coo_matrix(np.eye(2)), "r": sp.csr_matrix(np.eye(2))},
              [["walk", "run"], {"k": (1, 2.5, None, b"x")}], np.array(["a", 1], dtype=object)]
    return [pickle.dumps(v, protocol=p) for v in values for p in range(pickle.HIGHEST_PROTOCOL + 1)]


SEEDS = _seeds()


@st.composite
def mutated(draw) -> bytes:
    data = bytearray(draw(st.sampled_from(SEEDS)))
    for _ in range(draw(st.integers(0, 4))):
        pos = draw(st.integers(0, len(data)))
        kind = draw(st.sampled_from(["flip", "insert", "delete", "truncate"]))
        if kind == "flip" and pos < len(data):
            data[pos] = draw(st.integers(0, 255))
        elif kind == "insert":
            data[pos:pos] = draw(st.binary(min_size=1, max_size=12))
        elif kind == "delete":
            del data[pos:pos + draw(st.integers(1, 16))]
        elif kind == "truncate":
            del data[pos:]
    return bytes(data)


@st.composite
def nested(draw) -> bytes:
    """Containers nested ``depth`` deep: tuples, lists, or a nested tuple as a dict key."""
    depth = draw(st.one_of(st.integers(0, 300), st.integers(0, 1_000_000)))
    kind = draw(st.sampled_from(["tuple", "list", "key", "frozenset"]))
    if kind == "tuple":
        return b"\x80\x02)" + b"\x85" * depth + b"."
    if kind == "list":
        return b"\x80\x02" + b"]" * (depth + 1) + b"a" * depth + b"."
    if kind == "frozenset":
        return b"\x80\x04" + b"(" * depth + b")" + b"\x91" * depth + b"."
    return b"\x80\x02})" + b"\x85" * depth + b"Ns."


@st.composite
def declared(draw) -> bytes:
    """One opcode whose argument claims a size or memo index, from 0 to 2**63, then a few bytes."""
    n = draw(st.one_of(st.integers(0, 64), st.integers(0, 2**63 - 1)))
    op = draw(st.sampled_from(["BINBYTES8", "BINUNICODE8", "BYTEARRAY8", "FRAME", "LONG_BINPUT", "BINBYTES",
                               "BINUNICODE", "LONG4", "BINSTRING"]))
    arg = {"BINBYTES8": b"\x8e", "BINUNICODE8": b"\x8d", "BYTEARRAY8": b"\x96", "FRAME": b"\x95"}.get(op)
    if arg is not None:
        head = arg + struct.pack("<Q", n)
    elif op == "LONG_BINPUT":
        head = b"N" + b"r" + struct.pack("<I", n % 2**32)
    else:
        head = {"BINBYTES": b"B", "BINUNICODE": b"X", "LONG4": b"\x8b", "BINSTRING": b"T"}[op] + \
            struct.pack("<i" if op in ("LONG4", "BINSTRING") else "<I", n % 2**31)
    return b"\x80\x05" + head + draw(st.binary(max_size=16)) + b"."


KNOWN = {  # the hostile inputs of issue 28, always among the examples
    "nested tuple as a dict key, 1 MB": b"\x80\x02})" + b"\x85" * 1_000_000 + b"Ns.",
    "frozensets nested 200,000 deep": b"\x80\x04" + b"(" * 200_000 + b")" + b"\x91" * 200_000 + b".",
    "S0 array of 2**32 items": b"\x80\x02cnumpy._core.multiarray\n_reconstruct\ncnumpy\nndarray\nK\x00\x85C\x01b\x87R"
    b"(K\x01\x8a\x05\x00\x00\x00\x00\x01\x85cnumpy\ndtype\nX\x02\x00\x00\x00S0\x89\x88\x87R"
    b"(K\x03X\x01\x00\x00\x00|NNNK\x00K\x01K\x00tb\x89C\x00tb.",
    "179 GiB sparse matrix": pickle.dumps(sp.csc_matrix((3_000_000, 8_000)), protocol=4),
    "BINBYTES8 of 2**40 bytes": b"\x80\x04\x8e" + struct.pack("<Q", 1 << 40) + b"ab.",
    "memo index 2**32-1": b"\x80\x02Nr\xff\xff\xff\xff.",
}

PICKLES = st.one_of(st.binary(max_size=512), st.binary(max_size=512).map(lambda b: b"\x80\x04" + b), mutated(),
                    nested(), declared())


def _torch_zip(payload: bytes) -> bytes:
    """A torch zip checkpoint (torch.save's own members) whose data.pkl is ``payload``."""
    import torch

    buf = io.BytesIO()
    torch.save({}, buf)
    out = io.BytesIO()
    with zipfile.ZipFile(io.BytesIO(buf.getvalue())) as src, zipfile.ZipFile(out, "w") as dst:
        for name in src.namelist():
            dst.writestr(name, payload if name.endswith("/data.pkl") else src.read(name))
    return out.getvalue()


def _npz_with(payload: bytes) -> bytes:
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {"descr": "|O", "fortran_order": False, "shape": ()})
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w") as z:
        z.writestr("J_regressor.npy", header.getvalue() + payload)
    return out.getvalue()


def _with_known(fuzz):
    for data in KNOWN.values():
        fuzz = example(data)(fuzz)
    return fuzz


@settings(max_examples=PICKLE_EXAMPLES, **SETTINGS)
@_with_known
@given(PICKLES)
def fuzz_pickle_readers(payload: bytes) -> None:
    from lsgan.pickles import PickleReadError, load_npz, load_pickle, load_torch

    with tempfile.TemporaryDirectory() as d:
        files = {"x.pkl": (payload, load_pickle), "x.npz": (_npz_with(payload), load_npz),
                 "zip.pt": (_torch_zip(payload), load_torch), "legacy.pt": (payload, load_torch)}
        for name, (data, read) in files.items():
            path = Path(d) / name
            path.write_bytes(data)
            try:
                read(path)
            except PickleReadError as e:
                assert_one_line(e, path)


# ------------------------------------------------------------------------------------------------------------------
# BVH

CHANNELS = ("Xposition", "Yposition", "Zposition", "Xrotation", "Yrotation", "Zrotation")
GOOD_FRAME_TIMES = ("0.0333333", "0.008333", "0.05", "1", "1e-4")
BAD_FRAME_TIMES = ("100000", "0", "-1", "nan", "inf", "1e-9", "x")


@st.composite
def hierarchies(draw) -> tuple[str, int]:
    """A random hierarchy (1-12 joints, each with 0-6 channels in any order); returns it and its channel count."""
    n = draw(st.integers(1, 12))
    lines, total, depth = ["HIERARCHY"], 0, 0
    for j in range(n):
        chans = draw(st.lists(st.sampled_from(CHANNELS), unique=True, max_size=6))
        total += len(chans)
        if j and draw(st.booleans()) and depth > 1:
            lines.append("}")
            depth -= 1
        lines += [f"{'ROOT' if j == 0 else 'JOINT'} j{j}", "{", f"OFFSET {draw(st.integers(-50, 50))} 1.5 0",
                  f"CHANNELS {len(chans)} {' '.join(chans)}"]
        depth += 1
    lines += ["End Site", "{", "OFFSET 0 1 0", "}"] + ["}"] * depth
    return "\n".join(lines), total


def _sometimes(draw, good, bad, odds: int = 4):
    """``good`` (a strategy) ``odds`` times out of ``odds + 1``, else ``bad``."""
    return draw(bad if draw(st.integers(0, odds)) == 0 else good)


@st.composite
def bvh_files(draw) -> bytes:
    """A BVH file, well-formed most of the time, each part hostile now and then (then damaged bytes, sometimes)."""
    hierarchy, channels = draw(hierarchies())
    rows = draw(st.integers(1, 30))
    frames = _sometimes(draw, st.just(rows), st.one_of(st.integers(-5, 50), st.integers(10**6, 10**12),
                                                       st.just("1e9")))
    frame_time = _sometimes(draw, st.sampled_from(GOOD_FRAME_TIMES), st.sampled_from(BAD_FRAME_TIMES))
    width = channels + _sometimes(draw, st.just(0), st.sampled_from([-1, 1]))
    values = st.lists(st.floats(-360, 360), min_size=max(width, 0), max_size=max(width, 0))
    body = [" ".join(f"{v:.4f}" for v in draw(values)) for _ in range(rows)]
    text = f"{hierarchy}\nMOTION\nFrames: {frames}\nFrame Time: {frame_time}\n" + "\n".join(body) + "\n"
    text = text.replace("\n", draw(st.sampled_from(["\n", "\r\n", "\r"])))
    data = bytearray((b"\xef\xbb\xbf" if draw(st.booleans()) else b"") + text.encode())
    anywhere = st.integers(0, 2**31).map(lambda k: k % len(data))  # spread over the file, not crowded at 0
    byte = st.sampled_from(b"\x00\r\n\t {}-.9eE\xff")
    damage = _sometimes(draw, st.just([]), st.lists(st.tuples(anywhere, byte), min_size=1, max_size=3))
    for pos, byte in damage:
        data[pos] = byte
    return gzip.compress(bytes(data)) if draw(st.booleans()) else bytes(data)


@settings(max_examples=BVH_EXAMPLES, **SETTINGS)
@given(bvh_files())
def fuzz_bvh_reader(data: bytes) -> None:
    from lsgan.data.bvh import ClipError, forward_kinematics, read_bvh
    from lsgan.data.resample import resample

    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "clip.bvh"
        path.write_bytes(data)
        try:
            bvh = read_bvh(path)
        except ClipError as e:
            assert_one_line(e, path)
            return
        positions = forward_kinematics(bvh)
        assert positions.shape == (bvh.num_frames, len(bvh.names), 3)
        assert len(resample(positions, bvh.fps, 20.0)) <= 20 * bvh.num_frames


# ------------------------------------------------------------------------------------------------------------------
# The tests: each fuzz run in a child Python under the memory cap


def _run_in_child(fuzz: str, modules: str, cwd: Path) -> None:
    """``fuzz()`` of this module in a child Python that has imported ``modules`` before its memory is capped; it
    runs in ``cwd``, where Hypothesis keeps its .hypothesis folder."""
    code = (f"import sys; sys.path.insert(0, {str(Path(__file__).parent)!r})\n"
            f"import test_fuzz_readers as t\nimport {modules}\nt.limit_memory()\nt.{fuzz}()\nprint('fuzzed')")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600, cwd=cwd,
                         env=dict(os.environ, OMP_NUM_THREADS="1"))
    assert run.returncode == 0 and run.stdout.strip().endswith("fuzzed"), \
        f"{fuzz} failed (exit {run.returncode}):\n{run.stdout[-3000:]}\n{run.stderr[-6000:]}"


def test_pickle_loaders_read_or_refuse_in_one_line(tmp_path):
    _run_in_child("fuzz_pickle_readers", "lsgan.pickles, torch", tmp_path)


def test_bvh_reader_reads_or_refuses_in_one_line(tmp_path):
    _run_in_child("fuzz_bvh_reader", "lsgan.data.bvh, lsgan.data.resample", tmp_path)
