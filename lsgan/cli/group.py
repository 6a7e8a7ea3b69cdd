"""The ``lsgan`` command group: every command runs under it, and every failure becomes one line and an exit code."""
from __future__ import annotations

import os
import sys

import click

from lsgan import __version__
from lsgan.cli.options import LsganCommand, say_error, say_interrupted
from lsgan.cli.startup import startup_guard
from lsgan.cli.streams import named_streams
from lsgan.errors import debugging, describe
from lsgan.interrupts import InterruptGuard


class CommandInterrupted(Exception):
    """A command's KeyboardInterrupt on its way out of click, which would print a blank line for it (its ``__cause__``
    is the interrupt)."""


class LsganGroup(click.Group):
    """Runs a command and turns every failure into one ``error: FILE: problem`` line and a non-zero exit.

    Usage errors exit 2, other errors 1, Ctrl-C 130, SIGTERM 143; tracebacks only with ``--debug`` or
    ``LSGAN_DEBUG=1``. A Ctrl-C is never lost (:class:`lsgan.interrupts.InterruptGuard`): one that Python swallowed
    in a finaliser is raised again, and a run that received one exits 130 whatever became of the exception. A
    write to stdout that fails (a full disk, a closed pipe or descriptor) is an error naming stdout
    (:mod:`lsgan.cli.streams`), also when it fails only at the last flush.
    """

    command_class = LsganCommand

    def main(self, *args, **kwargs):
        from lsgan.outputs import claims

        guard = startup_guard.pop() if startup_guard else InterruptGuard()
        try:
            with named_streams(), claims():  # claims: what the command writes, noted for other lsgan processes
                code = self._run(guard, *args, **kwargs)
                if guard.stop() and code not in (130, 143):
                    code = say_interrupted(signum=guard.signum, came_at=guard.first_at)
        except BaseException:  # --debug: the traceback, with the caller's handler back
            guard.stop()
            raise
        sys.exit(code)

    def invoke(self, ctx: click.Context):
        try:
            return super().invoke(ctx)
        except KeyboardInterrupt as e:
            raise CommandInterrupted() from e

    def _run(self, guard, *args, **kwargs) -> int:
        """The command under ``guard``; its exit code, every failure reported as one line."""
        kwargs["standalone_mode"] = False

        def command() -> object:
            result = super(LsganGroup, self).main(*args, **kwargs)
            sys.stdout.flush()  # a failure still held in its buffer is this command's
            return result

        try:
            code = guard.call(command)
        except SystemExit as e:  # a command's own fail or stopped
            code = e.code
        except click.exceptions.Exit as e:
            code = e.exit_code
        except click.exceptions.NoArgsIsHelpError as e:  # `lsgan` alone asks for the help: no error to report
            click.echo(e.ctx.get_help())
            code = 0
        except click.ClickException as e:
            ctx, names = getattr(e, "ctx", None), []
            while ctx is not None and ctx.parent is not None:  # the command's names below the program's
                names.insert(0, ctx.info_name)
                ctx = ctx.parent
            hint = "" if ctx is None else f" (see '{' '.join(['lsgan', *names])} --help')"
            say_error(f"{e.format_message()}{hint}")
            code = e.exit_code
        except (click.Abort, KeyboardInterrupt, CommandInterrupted):
            code = say_interrupted()
        except Exception as e:  # noqa: BLE001 - the promise: one line, no traceback unless asked
            if debugging():
                raise
            say_error(describe(e))
            code = 1
        return code if isinstance(code, int) else 0


@click.group(cls=LsganGroup, context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.version_option(__version__, prog_name="lsgan")
@click.option("--debug", is_flag=True, help="Show Python tracebacks on errors (also LSGAN_DEBUG=1).")
@click.option("--threads", type=click.IntRange(1), default=None,
              help="Fix the CPU threads of torch and onnxruntime (also LSGAN_THREADS=N). Default: lsgan picks them "
                   "per job and lowers them while other processes keep cores busy.")
def main(debug: bool, threads: int | None) -> None:
    """lsgan: text- and action-to-motion synthesis with a GAN in the latent space of a motion VAE.

    \b
    Everything at once, on built-in synthetic data (about 6 minutes on a 2-core CPU):
      lsgan demo
    \b
    Pipeline:
      lsgan preprocess --source synthetic -o synth.h5
      lsgan inspect synth.h5
      lsgan train-vae --data synth.h5 --recipe demo --out runs/vae
      lsgan encode-latents --data synth.h5 --vae runs/vae -o cache.h5
      lsgan train-gan --cache cache.h5 --recipe demo --out runs/gan
      lsgan train-diffusion --cache cache.h5 --recipe demo --out runs/diffusion   # the MLD baseline
      lsgan generate --gan runs/gan --vae runs/vae --text "a person walks forward" -o out/
    \b
    Errors are one line on stderr (`error: FILE: problem`) with exit code 1 (2 for a wrong option, 130 after
    Ctrl-C, 143 after SIGTERM); `lsgan --debug COMMAND` (or LSGAN_DEBUG=1) shows the traceback. CPU threads: lsgan picks them per
    job and uses fewer while other processes keep cores busy; `lsgan --threads N COMMAND` fixes them. No command replaces a file it
    did not write: an existing output needs --force, which replaces only lsgan's own files.
    """
    if debug:
        os.environ["LSGAN_DEBUG"] = "1"
    if threads:
        os.environ["LSGAN_THREADS"] = str(threads)
