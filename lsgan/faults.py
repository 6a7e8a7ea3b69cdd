"""Named fault points, so the fault tests can interrupt a real run at an exact place.

``LSGAN_FAULT=NAME[@N][:SIGNAL]`` makes the process send itself SIGNAL (default SIGINT, i.e. Ctrl-C;
SIGKILL for a hard kill) the N-th time (default 1st) it reaches the point NAME. Unset, a point costs one
dictionary look-up. The points are listed where they are used (``grep fault_point``).
"""
from __future__ import annotations

import os
import signal

_seen: dict[str, int] = {}


def fault_point(name: str) -> None:
    """Signal this process here when ``LSGAN_FAULT`` names this point (and this is the chosen visit)."""
    spec = os.environ.get("LSGAN_FAULT")
    if not spec:
        return
    where, _, sig = spec.partition(":")
    point, _, nth = where.partition("@")
    if point != name:
        return
    _seen[name] = _seen.get(name, 0) + 1
    if _seen[name] == int(nth or 1):
        os.kill(os.getpid(), getattr(signal, sig or "SIGINT"))
