"""`gt-render JOBS -o OUTDIR [--workers N] [--force]`: render a job list (docs/batch.md). Exit 0 when every job
is done, 1 when any failed (each named with its reason), 2 for a job list with bad lines (each named)."""

from __future__ import annotations

import sys
from pathlib import Path

import typer

render_command = typer.Typer(add_completion=False)


@render_command.command()
def render(
    jobs: Path = typer.Argument(..., help="the job list: .jsonl (one JSON object a line) or .csv (a header row)"),
    outdir: Path = typer.Option(..., "-o", "--out", help="the output folder (outputs, manifest.jsonl)"),
    workers: int = typer.Option(None, "--workers", min=1, help="worker processes [default: one per core]"),
    force: bool = typer.Option(False, "--force", help="redo every job, even those the manifest proves done"),
    progress: bool = typer.Option(True, "--progress/--no-progress", help="a bar over the jobs on stderr"),
) -> None:
    """Render every job of JOBS into OUTDIR, skipping those already done."""
    from gaussiantalker.batch import BatchError, render_jobs

    try:
        summary = render_jobs(jobs, outdir, workers=workers, force=force, progress=progress)
    except BatchError as exc:
        sys.stderr.write(f"gt-render: {exc}\n")
        raise typer.Exit(2) from None
    for out, reason in summary.failed.items():
        sys.stderr.write(f"failed: {out}: {reason}\n")
    typer.echo(summary.describe())
    if summary.failed:
        raise typer.Exit(1)


def main() -> None:
    """`gt-render`."""
    render_command(prog_name="gt-render")


if __name__ == "__main__":
    main()
