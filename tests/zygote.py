"""A process that has imported lsgan's heavy dependencies and forks one child per ``lsgan`` command (tests only).

Importing torch, numpy, scipy and h5py takes about two seconds of the few that a refused command runs for; a child
forked from here starts with them loaded. Nothing of lsgan is imported here, so each child imports lsgan afresh
under its own environment, working folder, arguments and standard streams, and runs ``python -m lsgan.cli`` as a
fresh process would, at-exit handlers included. It never computes with torch, so no thread pool exists at the fork.

Protocol, one JSON line each way on stdin / stdout: {"args", "cwd", "env", "stdout", "stderr"} (the last two are
files for the child's streams; optionally "preload", modules the child imports first, and "headroom", bytes: the
child's address space is then capped at what it maps plus that) -> {"pid"} at once, then {"status"}: the exit code,
or -N for signal N, as subprocess.
"""
from __future__ import annotations

import atexit
import importlib
import json
import os
import resource
import runpy
import sys
import tempfile
import traceback

import h5py
import numpy as np
import scipy.ndimage
import torch
import yaml

LOADED = (h5py, np, scipy.ndimage, torch, yaml)  # what every child starts with


def child(request: dict) -> None:
    """In the forked child: become ``lsgan ARGS`` in the request's folder and environment, and exit as it does."""
    os.chdir(request["cwd"])
    os.environ.clear()
    os.environ.update(request["env"])
    tempfile.tempdir = None  # TMPDIR as this environment says
    np.random.seed()  # a fresh process's entropy, not the zygote's state
    for fd, path, flags in ((0, os.devnull, os.O_RDONLY), (1, request["stdout"], os.O_WRONLY | os.O_TRUNC),
                            (2, request["stderr"], os.O_WRONLY | os.O_TRUNC)):
        opened = os.open(path, flags)
        os.dup2(opened, fd)
        os.close(opened)
    sys.stdin = open(0, closefd=False)  # nothing the zygote read ahead of its requests
    sys.path[0] = os.getcwd()  # as `python -m` puts it, rather than this file's folder
    sys.argv = ["lsgan", *request["args"]]
    for name in request.get("preload", ()):
        importlib.import_module(name)
    if request.get("headroom") is not None:  # cap the address space at what is mapped now plus this
        with open("/proc/self/status") as status:
            vm = next(int(line.split()[1]) * 1024 for line in status if line.startswith("VmSize:"))
        resource.setrlimit(resource.RLIMIT_AS, (vm + request["headroom"], vm + request["headroom"]))
    code = 0
    try:
        runpy.run_module("lsgan.cli", run_name="__main__", alter_sys=True)
    except SystemExit as e:
        code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
        if not isinstance(e.code, int) and e.code is not None:
            print(e.code, file=sys.stderr)
    except BaseException:  # noqa: BLE001 - as the interpreter would: the traceback, exit 1
        traceback.print_exc()
        code = 1
    atexit._run_exitfuncs()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


def main() -> None:
    control_in, control_out = sys.stdin, sys.stdout
    for line in control_in:
        request = json.loads(line)
        control_out.flush()
        sys.stderr.flush()
        pid = os.fork()
        if pid == 0:
            child(request)
        control_out.write(json.dumps({"pid": pid}) + "\n")
        control_out.flush()
        _, status = os.waitpid(pid, 0)
        code = os.waitstatus_to_exitcode(status)
        control_out.write(json.dumps({"status": code}) + "\n")
        control_out.flush()


if __name__ == "__main__":
    main()
