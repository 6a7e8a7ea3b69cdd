"""The ``lsgan`` command line: thin wrappers that parse options and call one library function each, one module per
command family (data, training, generation and export, evaluation, serving); :mod:`lsgan.cli.group` runs them."""
from lsgan.cli.startup import startup_guard  # noqa: F401  (first: it counts Ctrl-C while the rest is imported)
from lsgan.cli import data, evaluation, generation, serving, training  # noqa: E402,F401  (each adds its commands)
from lsgan.cli.group import main  # noqa: E402

__all__ = ["main"]
