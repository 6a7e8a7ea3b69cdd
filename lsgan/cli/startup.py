"""Ctrl-C from the first instant: the lsgan program counts it before click and the commands are imported (~50 ms);
:class:`lsgan.cli.group.LsganGroup` takes this guard over. Importing lsgan.cli from other code installs nothing."""
from __future__ import annotations

import os
import sys

from lsgan.interrupts import InterruptGuard


def started_as_lsgan() -> bool:
    """Whether this process is the lsgan program (the console script, or ``python -m lsgan.cli``), by the command
    line the interpreter was given: not a ``python -c`` worker that multiprocessing spawned, which imports the
    program's main module (and so this one) with the program's sys.argv, and must keep SIGTERM's default so that its
    pool can stop it."""
    argv = getattr(sys, "orig_argv", [])
    flags = []
    for arg in argv[1:]:  # the interpreter's own options, up to the script, -c or -m
        if not arg.startswith("-"):
            break
        flags.append(arg)
        if arg in ("-c", "-m"):
            break
    if "-c" in flags:
        return False
    as_module = any(flag == "-m" and name == "lsgan.cli" for flag, name in zip(argv, argv[1:]))
    return as_module or os.path.splitext(os.path.basename(sys.argv[0]))[0] == "lsgan"


startup_guard = [InterruptGuard(exiting=True)] if started_as_lsgan() else []
