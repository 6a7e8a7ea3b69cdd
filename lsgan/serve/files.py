"""What the server sends as files: a stored motion's exports, and the page's own files from the installed package.

Clients never name a path: a download is an id from the store plus one of three extensions, and a page file is
one of the names that exist in ``lsgan/serve/static`` (read with importlib.resources, listed at each request so
that files installed later are served too).
"""
from __future__ import annotations

import functools

import io
import re
from importlib import resources

import numpy as np

from lsgan.generation import _slug
from lsgan.serve.store import Stored

FORMATS = {  # extension -> content type
    "glb": "model/gltf-binary",
    "bvh": "text/plain; charset=utf-8",
    "npy": "application/octet-stream",
}
STATIC_TYPES = {
    ".html": "text/html; charset=utf-8", ".js": "text/javascript; charset=utf-8",
    ".mjs": "text/javascript; charset=utf-8", ".css": "text/css; charset=utf-8", ".svg": "image/svg+xml",
    ".png": "image/png", ".ico": "image/x-icon", ".json": "application/json", ".txt": "text/plain; charset=utf-8",
    ".woff2": "font/woff2", ".map": "application/json",
}
STATIC_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,99}")


def export_bytes(motion: Stored, fmt: str) -> bytes:
    """The motion as ``fmt`` (glb, bvh or npy) by the exporters ``lsgan export`` uses; made once, then kept."""
    if fmt not in motion.files:
        if fmt == "glb":
            from lsgan.export.glb import joints_to_glb

            data = joints_to_glb(motion.joints, fps=motion.fps, name=_slug(motion.title))
        elif fmt == "bvh":
            from lsgan.export.bvh import joints_to_bvh

            data = joints_to_bvh(motion.joints, fps=motion.fps).encode("utf-8")
        else:
            buf = io.BytesIO()
            np.save(buf, motion.joints)
            data = buf.getvalue()
        motion.files[fmt] = data
    return motion.files[fmt]


def download_name(motion: Stored, key: str, fmt: str) -> str:
    """A file name for Content-Disposition: the prompt's slug and the id's start (ASCII only)."""
    return f"{_slug(motion.title)}-{key[:8]}.{fmt}"


def static_files() -> dict[str, str]:
    """Name -> content type of the files in the package's static folder now (plain names only)."""
    try:
        folder = resources.files("lsgan.serve") / "static"
        entries = list(folder.iterdir()) if folder.is_dir() else []
    except (OSError, ModuleNotFoundError):
        return {}
    found = {}
    for e in entries:
        suffix = "." + e.name.rsplit(".", 1)[-1]
        if e.is_file() and STATIC_NAME.fullmatch(e.name) and suffix in STATIC_TYPES:
            found[e.name] = STATIC_TYPES[suffix]
    return found


@functools.lru_cache(maxsize=None)
def static_bytes(name: str) -> tuple[bytes, str] | None:
    """(content, content type) of an allowed static file, or None."""
    allowed = static_files()
    if name not in allowed:
        return None
    return (resources.files("lsgan.serve") / "static" / name).read_bytes(), allowed[name]
