"""`gt-render JOBS -o OUTDIR [--workers N] [--ray [ADDRESS]] [--segment-s S] [--force]`: render a job list
(docs/batch.md). Exit 0 when every job is done, 1 when any failed (each named with its reason), 2 for a job list
with bad lines (each named) or an engine that cannot start."""

from __future__ import annotations

import re
import sys
from pathlib import Path

import typer

render_command = typer.Typer(add_completion=False)

# What `--ray` takes as its address when one follows it: host:port, ray://host:port, or Ray's own "auto"/"local".
_RAY_ADDRESS = re.compile(r"^(ray://)?[A-Za-z0-9_.\-\[\]:]+:\d+$|^auto$|^local$")
_LOCAL_RAY = "-"  # `--ray` given without an address: RAY_ADDRESS, else a local Ray


@render_command.command()
def render(
    jobs: Path = typer.Argument(..., help="the job list: .jsonl (one JSON object a line) or .csv (a header row)"),
    outdir: Path = typer.Option(..., "-o", "--out", help="the output folder (outputs, manifest.jsonl)"),
    workers: int = typer.Option(None, "--workers", min=1, help="worker processes, or Ray actors with --ray "
                                "[default: one per core; with --ray, one per CPU of the cluster]"),
    ray: str = typer.Option(None, "--ray", metavar="[ADDRESS]", help="run on a Ray cluster: ADDRESS, else "
                            "RAY_ADDRESS, else a local Ray started for the run (needs the ray extra)"),
    segment_s: float = typer.Option(60.0, "--segment-s", help="render jobs longer than this many seconds in "
                                    "segments on several workers, joined into one file (0: never split)"),
    force: bool = typer.Option(False, "--force", help="redo every job, even those the manifest proves done"),
    progress: bool = typer.Option(True, "--progress/--no-progress", help="a bar over the jobs on stderr"),
) -> None:
    """Render every job of JOBS into OUTDIR, skipping those already done."""
    from gaussiantalker.batch import BatchError, render_jobs

    engine = False if ray is None else (True if ray == _LOCAL_RAY else ray)
    try:
        summary = render_jobs(jobs, outdir, workers=workers, force=force, progress=progress,
                              segment_s=segment_s or None, ray=engine)
    except BatchError as exc:
        sys.stderr.write(f"gt-render: {exc}\n")
        raise typer.Exit(2) from None
    for out, reason in summary.failed.items():
        sys.stderr.write(f"failed: {out}: {reason}\n")
    typer.echo(summary.describe())
    if summary.failed:
        raise typer.Exit(1)


def ray_flag_arguments(argv: list[str]) -> list[str]:
    """`--ray` with its address optional: a bare `--ray` (no address after it) becomes `--ray=-`."""
    out = []
    for index, arg in enumerate(argv):
        following = argv[index + 1] if index + 1 < len(argv) else None
        if arg == "--ray" and (following is None or not _RAY_ADDRESS.match(following)):
            out.append(f"--ray={_LOCAL_RAY}")
        else:
            out.append(arg)
    return out


def main() -> None:
    """`gt-render`."""
    render_command(args=ray_flag_arguments(sys.argv[1:]), prog_name="gt-render")


if __name__ == "__main__":
    main()
