"""Build the deterministic demo speaker: `python samples/make_demo_speaker.py -o speaker.ckpt`.

Generates the procedural FLAME-structured head, binds ~20k region-coloured Gaussians to it, trains the motion
translator briefly on synthetic speech (jaw, lips, brows and blinks follow the audio; docs/demo-speaker.md),
renders its reference clip (the speaker's own "video": background, shoulders and the head, with masks) and trains
the inpainting generator on it (docs/compositing.md), and writes a weights-only checkpoint.

Both trainings run a fixed number of steps, so the same options make the same checkpoint on any machine; the former
time budgets `--train-seconds` and `--inpaint-seconds` are read as steps (docs/demo-speaker.md, "Identical builds").
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import typer

from gaussiantalker.exporter.demo.demo_speaker import make_demo_speaker
from gaussiantalker.exporter.demo.steps import INPAINT_STEPS, STEPS_PER_SECOND, steps_for_seconds
from gaussiantalker.exporter.demo.train_translator import TrainSettings
from gaussiantalker.exporter.export.checkpoint import save_checkpoint

app = typer.Typer(add_completion=False)


@app.command()
def main(
    output: Path = typer.Option(Path("speaker.ckpt"), "-o", "--output", help="checkpoint to write"),
    gaussians: int = typer.Option(20_000, "--gaussians", "-n", min=1, help="number of Gaussians"),
    train_steps: int = typer.Option(None, "--train-steps", min=0,
                                    help=f"translator training steps, at most (0 = untrained; default "
                                         f"{TrainSettings.max_steps}, fewer if it converges first)"),
    train_seconds: float = typer.Option(None, "--train-seconds", min=0.0,
                                        help=f"the former time cap, read as --train-steps = {STEPS_PER_SECOND} per "
                                             f"second (at most {TrainSettings.max_steps}; 0 = untrained)"),
    seed: int = typer.Option(0, "--seed", help="seed of everything random"),
    no_reference: bool = typer.Option(False, "--no-reference", help="no reference clip (a bare-head speaker)"),
    inpaint_steps: int = typer.Option(None, "--inpaint-steps", min=0,
                                      help=f"training steps of the inpainting generator (0 = none: the OpenCV "
                                           f"fallback composites; default {INPAINT_STEPS})"),
    inpaint_seconds: float = typer.Option(None, "--inpaint-seconds", min=0.0,
                                          help=f"the former time cap, read as --inpaint-steps = {STEPS_PER_SECOND} "
                                               "per second (0 = none)"),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="no progress bars"),
) -> None:
    """Write a demo speaker checkpoint and print its training metrics."""
    train_steps = _steps(train_steps, train_seconds, "--train-steps", "--train-seconds", TrainSettings.max_steps)
    inpaint_steps = _steps(inpaint_steps, inpaint_seconds, "--inpaint-steps", "--inpaint-seconds")
    start = time.perf_counter()
    speaker, metrics = make_demo_speaker(gaussians, seed=seed, train_steps=train_steps, progress=not quiet,
                                         reference_clip=not no_reference, inpaint_steps=inpaint_steps)
    save_checkpoint(speaker, output)
    metrics["seconds"] = round(time.perf_counter() - start, 1)
    typer.echo(json.dumps(metrics, indent=2, default=float))
    typer.echo(f"wrote {output}")


def _steps(steps: int | None, seconds: float | None, steps_flag: str, seconds_flag: str,
           cap: int | None = None) -> int | None:
    """A step option, or its former time budget read as steps (saying so on stderr); None: the default."""
    if seconds is None:
        return steps
    if steps is not None:
        raise typer.BadParameter(f"give {steps_flag} or {seconds_flag}, not both", param_hint=seconds_flag)
    try:
        mapped = steps_for_seconds(seconds, cap)
    except ValueError as exc:
        raise typer.BadParameter(f"{exc} ({steps_flag})", param_hint=seconds_flag) from None
    if seconds > 0:
        typer.echo(f"{seconds_flag} {seconds:g} is read as {steps_flag} {mapped} ({STEPS_PER_SECOND} steps per second: "
                   "training stops on a step count, so builds are identical)", err=True)
    return mapped


if __name__ == "__main__":
    app()
