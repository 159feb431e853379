"""The ``mpd`` command: the top layer. One module per verb group (``mpd/cli/<group>.py``); nothing below imports
it."""

from __future__ import annotations

import errno
import importlib
import sys

import click

from mpd import __version__
from mpd.schema import ConfigError

# (module, attribute) of each click command or group; imported lazily so that `mpd --help` stays fast and a
# verb's heavy imports (torch, ompl, pybullet, rerun) are paid only when it runs.
COMMANDS = {
    "tasks": ("mpd.cli.tasks", "tasks"),
    "data": ("mpd.cli.data", "data"),
    "train": ("mpd.cli.models", "train"),
    "models": ("mpd.cli.models", "models"),
    "plan": ("mpd.cli.planners", "plan"),
    "planners": ("mpd.cli.planners", "planners"),
    "run": ("mpd.cli.experiments", "run"),
    "runs": ("mpd.cli.experiments", "runs"),
    "report": ("mpd.cli.reports", "report"),
    "view": ("mpd.cli.viz", "view"),
    "bench": ("mpd.cli.bench", "bench"),
}


def check_device(ctx, param, value):
    """click callback of every --device option: a name torch knows and a device this machine has, else a usage
    error naming it (not a traceback from deep inside training or planning)."""
    if value is None:
        return value
    import torch

    try:
        dev = torch.device(value)
    except (RuntimeError, ValueError):
        raise click.BadParameter(f"{value!r} is not a device (cpu, cuda, cuda:1 ...)") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise click.BadParameter(f"{value!r}: no CUDA device on this machine")
    return value


class LazyGroup(click.Group):
    def list_commands(self, ctx):
        return sorted(COMMANDS)

    def get_command(self, ctx, name):
        if name not in COMMANDS:
            return None
        module, attr = COMMANDS[name]
        try:
            return getattr(importlib.import_module(module), attr)
        except (ImportError, AttributeError) as e:  # a verb whose package is not built yet
            msg = f"{type(e).__name__}: {e}"
            return click.Command(name, help=f"(unavailable: {msg})", callback=lambda: sys.exit(f"mpd {name}: {msg}"))


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="mpd")
def cli() -> None:
    """Motion Planning Diffusion, reproducible: tasks, datasets, models, planners, experiments, reports."""


def main() -> None:
    try:
        cli.main(standalone_mode=False)
    except ConfigError as e:
        click.echo(f"error: {e}", err=True)
        sys.exit(2)
    except FileNotFoundError as e:  # a run, model or file named on the command line (or one of its files) is missing
        click.echo(f"error: {f'{e.filename}: {e.strerror}' if e.filename else e.args[-1] if e.args else e}", err=True)
        sys.exit(2)
    except OSError as e:
        if e.errno not in (errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES):
            raise
        # a full disk (or a quota, a read-only or forbidden folder): what was written before is kept (writes are
        # atomic), a rerun resumes
        click.echo(f"error: {e.filename or ''}: {e.strerror}", err=True)
        sys.exit(1)
    except click.exceptions.Abort:
        click.echo("aborted", err=True)
        sys.exit(130)
    except click.ClickException as e:
        e.show()
        sys.exit(e.exit_code)
    except click.exceptions.Exit as e:
        sys.exit(e.exit_code)
