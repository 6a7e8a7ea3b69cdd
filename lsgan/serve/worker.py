"""The engine in a process of its own, so that its torch operations never wait for the server's GIL.

Between two operations torch takes Python's GIL back, and in the server's process the event loop and the threads
that format answers hold it for much of a pass under load. Measured with the Bandai demo-size models, 16 motions
a pass: a busy Python thread beside the engine doubled the decoder's pass (34 -> 69 ms), the same busy loop in
another process cost 17% (40 ms). So ``lsgan serve`` runs :func:`lsgan.serve.engine.load_engine` in a child
(``python -m lsgan.serve.worker``) behind :class:`EngineProcess`, which keeps the :class:`Engine` interface
(on POSIX systems: the child inherits its pipes by ``pass_fds``; elsewhere the server keeps the engine itself).

They talk over two pipes in frames of a JSON header and raw bytes: requests as JSON, motions back as float32
joints; nothing is unpickled. The child ignores SIGINT and SIGTERM (the server drains its requests, then closes
the pipe) and exits when its pipe closes, also when the server dies.
"""
from __future__ import annotations

import gc
import json
import os
import signal
import struct
import subprocess
import sys
import traceback
from dataclasses import asdict
from typing import BinaryIO

import numpy as np

from lsgan.interrupts import sigint_held
from lsgan.serve.engine import Engine, Item, Result

_SIZES = struct.Struct("<II")  # header bytes, payload bytes
_META = ("backend", "device", "condition", "actions", "fps", "max_frames", "load_s", "reach", "steers")


def send(stream: BinaryIO, header: dict, payload: bytes = b"") -> None:
    """One frame: the sizes, the JSON header, the payload."""
    head = json.dumps(header).encode()
    stream.write(_SIZES.pack(len(head), len(payload)) + head + payload)
    stream.flush()


def _read(stream: BinaryIO, n: int) -> bytes:
    data = stream.read(n)
    if len(data) != n:
        raise EOFError("the pipe closed")
    return data


def receive(stream: BinaryIO) -> tuple[dict, bytes]:
    """One frame sent by :func:`send`: (header, payload); EOFError when the other side has gone."""
    n_head, n_payload = _SIZES.unpack(_read(stream, _SIZES.size))
    return json.loads(_read(stream, n_head)), _read(stream, n_payload)


def _failure(error: BaseException) -> dict:
    """The header of a failure: the one line ``lsgan`` prints for it, and whether the input was at fault (with
    ``LSGAN_DEBUG=1`` the child prints the traceback too)."""
    from lsgan.errors import debugging, describe

    if debugging():
        traceback.print_exc()
    return {"error": describe(error) or type(error).__name__, "input": isinstance(error, (ValueError, LookupError))}


def _raise(header: dict) -> None:
    """Raise the child's failure in the server: ValueError when the input was at fault (a 4xx), else
    RuntimeError; the same one line either way."""
    raise (ValueError if header.get("input") else RuntimeError)(header["error"])


def _pack(results: list[Result]) -> tuple[dict, bytes]:
    joints = [np.ascontiguousarray(j, np.float32) for r in results for j in r.joints]
    header = {"results": [{"frames": [len(j) for j in r.joints], "timings_ms": r.timings_ms,
                           "batch_size": r.batch_size, "control": r.control} for r in results]}
    return header, b"".join(j.tobytes() for j in joints)


def _unpack(header: dict, payload: bytes) -> list[Result]:
    flat, at, results = np.frombuffer(payload, np.float32), 0, []
    for r in header["results"]:
        joints = []
        for t in r["frames"]:
            joints.append(flat[at:at + t * 66].reshape(t, 22, 3).copy())
            at += t * 66
        results.append(Result(joints=joints, timings_ms=r["timings_ms"], batch_size=r["batch_size"],
                              control=r["control"]))
    return results


class EngineProcess(Engine):
    """An engine loaded and run by a child process; ``load_args`` are :func:`load_engine`'s keywords."""

    def __init__(self, **load_args) -> None:
        from_server, to_child = os.pipe()  # (read end, write end)
        from_child, to_server = os.pipe()
        with sigint_held():  # Ctrl-C is the server's alone, also while the child starts (before it ignores it)
            self._proc = subprocess.Popen(
                [sys.executable, "-m", "lsgan.serve.worker", str(from_server), str(to_server), json.dumps(load_args)],
                pass_fds=(from_server, to_server), stdin=subprocess.DEVNULL)
        os.close(from_server)
        os.close(to_server)
        self._out, self._in = os.fdopen(to_child, "wb"), os.fdopen(from_child, "rb")
        try:
            header, _ = receive(self._in)
        except EOFError:
            raise RuntimeError(f"the engine process stopped while loading (exit code {self._proc.wait()})") from None
        if "error" in header:
            self._proc.wait()
            _raise(header)
        for name in _META:
            setattr(self, name, header[name])

    def run(self, items: list[Item], *, threads: int | None = None) -> list[Result]:
        try:
            send(self._out, {"items": [asdict(it) for it in items], "threads": threads})
            header, payload = receive(self._in)
        except (EOFError, BrokenPipeError):
            raise RuntimeError(f"the engine process stopped (exit code {self._proc.poll()})") from None
        if "error" in header:
            _raise(header)
        return _unpack(header, payload)

    def close(self, timeout: float = 30.0) -> None:
        """Close the pipe; the child finishes and exits."""
        self._out.close()
        try:
            self._proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait()
        self._in.close()


def _serve(requests: BinaryIO, replies: BinaryIO, load_args: dict) -> None:
    """The child's life: load the engine, report what it is, then answer passes until the pipe closes."""
    from lsgan.serve.engine import load_engine

    try:
        engine = load_engine(**load_args)
    except Exception as e:  # noqa: BLE001 - reported to the server, which prints it as its own one-line error
        send(replies, _failure(e))
        return
    gc.collect()
    gc.freeze()  # the models' objects stay out of every later collection: no full-GC pause of ~100 ms mid-pass
    send(replies, {name: getattr(engine, name) for name in _META})
    while True:
        try:
            header, _ = receive(requests)
        except EOFError:
            return
        try:
            results = engine.run([Item(**it) for it in header["items"]], threads=header.get("threads"))
        except Exception as e:  # noqa: BLE001 - the pass fails, the engine keeps serving
            send(replies, _failure(e))
            continue
        send(replies, *_pack(results))


if __name__ == "__main__":
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the server stops us by closing the pipe, after draining
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    try:
        with os.fdopen(int(sys.argv[1]), "rb") as inbox, os.fdopen(int(sys.argv[2]), "wb") as outbox:
            _serve(inbox, outbox, json.loads(sys.argv[3]))
    except BrokenPipeError:  # the server went away (Ctrl-C while loading, or killed): nothing left to answer
        os._exit(0)  # at once: flushing the undelivered frame again at exit would only fail again
