"""``mpd report``: a run's report (``mpd report RUN``), and the pages built from every committed report
(``mpd report paper``: docs/RESULTS.md; ``mpd report index``: reports/README.md)."""

from __future__ import annotations

from pathlib import Path

import click

from mpd.cli.viz import report as run_report
from mpd.paths import REPO_ROOT


class _DefaultToRun(click.Group):
    """A group whose first argument, when it names no subcommand, is a run: ``mpd report RUN`` is
    ``mpd report run RUN``."""

    def parse_args(self, ctx, args):
        if not args or (args[0] not in self.commands and args[0] not in ctx.help_option_names):
            args = ["run", *args]
        return super().parse_args(ctx, args)


@click.group("report", cls=_DefaultToRun)
def report() -> None:
    """A run's report (`mpd report RUN`, the default), or a page built from every committed report under
    reports/ (`mpd report paper`, `mpd report index`)."""


report.add_command(run_report, "run")


def _write_page(text: str, out: Path, check: bool) -> None:
    old = out.read_text() if out.exists() else None
    if check:
        if old != text:
            raise click.ClickException(f"{out} differs from what the committed reports give (rerun without --check)")
        click.echo(f"{out}: up to date")
        return
    if old != text:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(text)
    click.echo(f"{out}: {'written' if old != text else 'unchanged'}")


@report.command("paper")
@click.option("--reports", "root", type=click.Path(path_type=Path), default=REPO_ROOT / "reports", show_default=True)
@click.option("--out", type=click.Path(path_type=Path), default=REPO_ROOT / "docs" / "RESULTS.md", show_default=True)
@click.option(
    "--readme",
    type=click.Path(path_type=Path),
    default=REPO_ROOT / "README.md",
    show_default=True,
    help="the page whose results-at-a-glance block is refreshed",
)
@click.option("--no-readme", is_flag=True, help="leave the README alone")
@click.option("--check", is_flag=True, help="exit 1 if a file differs from what the reports give; write nothing")
def paper(root: Path, out: Path, readme: Path, no_readme: bool, check: bool) -> None:
    """Every number the paper states beside ours, with a verdict, and the paper's orderings with their paired
    intervals: one page from the committed reports' results tables; and the README's summary of it."""
    from mpd.viz.results_page import glance, results_page, with_glance

    _write_page(results_page(root), out, check)
    if not no_readme:
        try:
            text = with_glance(readme.read_text(), glance(root), str(readme))
        except (OSError, ValueError) as e:
            raise click.ClickException(str(e)) from None
        _write_page(text, readme, check)


@report.command("index")
@click.option("--reports", "root", type=click.Path(path_type=Path), default=REPO_ROOT / "reports", show_default=True)
@click.option("--out", type=click.Path(path_type=Path), default=None, help="default: README.md in the reports folder")
@click.option("--check", is_flag=True, help="exit 1 if the file differs from what the reports give; write nothing")
def index(root: Path, out: Path | None, check: bool) -> None:
    """The index of the committed reports: each one's question, spec, priors, date, headline number and whether a
    later report supersedes it."""
    from mpd.viz.reports_index import reports_index

    _write_page(reports_index(root), out or root / "README.md", check)
