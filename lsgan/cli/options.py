"""Shared pieces of the commands: path parameters that declare what a command reads and writes, and the
one-line failure and Ctrl-C helpers every command uses."""
from __future__ import annotations

import os
import sys
import unicodedata

import click

from lsgan.errors import debugging, describe


class In(click.Path):
    """A path the command reads. Every path option is an :class:`In` or an :class:`Out` (tests/test_outputs.py
    checks it), so that :class:`LsganCommand` can refuse an output that is, holds or lies inside an input."""

    role = "input"

    def paths(self, value: str) -> list[str]:
        return [value]


class Out(In):
    """A path the command writes (a file, a folder, or the stem of several files)."""

    role = "output"


def setting(name: str) -> click.IntRange:
    """The bounds of the recipe setting ``name`` (lsgan.recipes.BOUNDS) as a click type: an override beyond them
    is a usage error (exit 2) before anything runs, by the same table that checks the recipe."""
    from lsgan.recipes import BOUNDS

    bounds = BOUNDS[name]
    return click.IntRange(int(bounds.low), int(bounds.high), min_open=bounds.open_low)


class Finite(click.FloatRange):
    """A float in a range that is also a number: click's FloatRange lets nan through (no comparison holds)."""

    def convert(self, value, param, ctx):
        number = super().convert(value, param, ctx)
        if number != number:
            self.fail(f"{value!r} is not a number", param, ctx)
        return number


class NamedIn(click.ParamType):
    """``[NAME=]PATH``: an input path with an optional row name."""

    name = "[NAME=]PATH"
    role = "input"

    def paths(self, value: str) -> list[str]:
        return [value.rpartition("=")[2]] if "=" in value and not os.path.exists(value) else [value]


class MaybeIn(click.ParamType):
    """An input file when the value names an existing path; else a name (a built-in recipe) or inline text."""

    name = "TEXT"
    role = "input"

    def paths(self, value: str) -> list[str]:
        return [value] if os.path.exists(value) else []


def declared_paths(command: click.Command, params: dict) -> tuple[list[str], list[str]]:
    """The input and output paths given to ``command`` (``params`` as parsed), from its parameters' types."""
    found: dict[str, list[str]] = {"input": [], "output": []}
    for p in command.params:
        role = getattr(p.type, "role", None)
        values = params.get(p.name)
        if role is None or values is None:
            continue
        for v in values if isinstance(values, (tuple, list)) else [values]:
            found[role] += p.type.paths(os.fspath(v))
    return found["input"], found["output"]


def check_declared_paths(command: click.Command, params: dict) -> None:
    """Refuse an output that is, holds or lies inside an input, or that overlaps another output."""
    from lsgan.outputs import check_apart, check_inputs

    ins, outs = declared_paths(command, params)
    for out in outs:
        check_inputs(out, ins)
    check_apart(*outs)


class LsganCommand(click.Command):
    """A command whose declared outputs are checked against its declared inputs before it runs."""

    def invoke(self, ctx: click.Context):
        check_declared_paths(self, ctx.params)
        return super().invoke(ctx)


def fail(message: str) -> None:
    """Print ``error: MESSAGE`` and exit 1; under --debug re-raise the exception being handled instead."""
    if debugging() and sys.exc_info()[1] is not None:
        raise sys.exc_info()[1]
    say_error(message)
    sys.exit(1)


def say_error(message: str) -> None:
    """Print a failure as the one line ``error: MESSAGE`` on stderr (:func:`one_line`): the only place lsgan words
    an error line (a test fails if another appears)."""
    close_progress_bars()
    click.echo("error: " + one_line(str(message)), err=True)


def one_line(text: str) -> str:
    """``text`` with every character a terminal would act on written as its escape (a line break as ``\\n``, an
    ESC as ``\\x1b``), and a byte of a file name that was not UTF-8 as ``\\xNN``: one line that says exactly
    what the name holds, which no name can move or wipe."""
    def shown(c: str) -> str:
        if "\udc80" <= c <= "\udcff":  # os.fsdecode's escape of an undecodable byte
            return f"\\x{ord(c) - 0xDC00:02x}"
        if c == "\t" or unicodedata.category(c) not in ("Cc", "Cf", "Cs", "Zl", "Zp"):
            return c
        return repr(c)[1:-1] if len(repr(c)) > 3 else f"\\u{ord(c):04x}"

    return "".join(map(shown, text))


def close_progress_bars() -> None:
    """Close unfinished tqdm bars, so the error line starts a line of its own."""
    from tqdm import tqdm

    for bar in list(getattr(tqdm, "_instances", ())):
        bar.close()


def say_interrupted(hint: str = "", signum: int | None = None, came_at: float | None = None) -> int:
    """After Ctrl-C or SIGTERM: one line, ``interrupted`` or ``terminated`` and what is kept and how to go on; the
    exit code (128 + the signal). The signal and its time come from the :class:`lsgan.interrupts.Interrupted` being
    handled, or are given. Progress bars close first; the line starts a line of its own with no blank line before
    it: after a line break only if the last line printed is unfinished, or, for Ctrl-C on a terminal (which echoed
    ``^C`` where its cursor was), unless what was printed since the signal (a closed bar) ended a line."""
    import signal

    from lsgan.interrupts import Interrupted

    error = sys.exc_info()[1]
    while error is not None and not isinstance(error, Interrupted):
        error = error.__cause__ or error.__context__
    signum = signum or getattr(error, "signum", signal.SIGINT)
    came_at = getattr(error, "came_at", 0.0) if came_at is None else came_at
    close_progress_bars()
    err = sys.stderr
    if signum == signal.SIGINT and getattr(err, "isatty", lambda: False)():
        fresh = 0.0 < came_at < getattr(err, "line_ended", 0.0)
    else:
        fresh = getattr(err, "at_line_start", False)
    word = "terminated" if signum == signal.SIGTERM else "interrupted"
    click.echo(("" if fresh else "\n") + word + (f": {hint}" if hint else ""), err=True)
    return 128 + signum


def stopped(hint: str) -> None:
    """Ctrl-C or SIGTERM: say what is kept and how to go on, and exit 130 (143)."""
    sys.exit(say_interrupted(hint))


def stopped_keeping(kept: str | os.PathLike, what: str) -> None:
    """:func:`stopped` for work that resumes from ``kept`` (a run's ``last/`` checkpoint, preprocess's parts): the
    hint says so only when it exists, else that nothing was kept yet."""
    if os.path.exists(kept):
        stopped(f"{what} so far are kept in {kept}; run the same command with --resume to continue")
    stopped(f"no {what} were kept yet; run the same command again")


def plainly(error: Exception) -> str:
    """A command's failure as :func:`describe` words it; a missing text encoder's message says how to get it."""
    from lsgan.models.text import TextEncoderUnavailable

    return str(error) if isinstance(error, TextEncoderUnavailable) else describe(error)


def load_recipe_or_fail(recipe: str | None) -> dict:
    from lsgan.recipes import load_recipe

    if recipe is None:
        return {}
    try:
        return load_recipe(recipe)
    except (FileNotFoundError, ValueError) as e:
        fail(str(e))
