"""Build the deterministic demo speaker: `python samples/make_demo_speaker.py -o speaker.ckpt`.

Generates the procedural FLAME-structured head, binds ~20k region-coloured Gaussians to it, trains the motion
translator briefly on synthetic speech (jaw, lips, brows and blinks follow the audio; docs/demo-speaker.md),
renders its reference clip (the speaker's own "video": background, shoulders and the head, with masks) and trains
the inpainting generator on it (docs/compositing.md), and writes a weights-only checkpoint.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import typer

from gaussiantalker.exporter.demo.speaker import make_demo_speaker
from gaussiantalker.exporter.export.checkpoint import save_checkpoint

app = typer.Typer(add_completion=False)


@app.command()
def main(
    output: Path = typer.Option(Path("speaker.ckpt"), "-o", "--output", help="checkpoint to write"),
    gaussians: int = typer.Option(20_000, "--gaussians", "-n", min=1, help="number of Gaussians"),
    train_seconds: float = typer.Option(150.0, "--train-seconds", min=0.0,
                                        help="time cap for translator training (0 = untrained)"),
    seed: int = typer.Option(0, "--seed", help="seed of everything random"),
    no_reference: bool = typer.Option(False, "--no-reference", help="no reference clip (a bare-head speaker)"),
    inpaint_seconds: float = typer.Option(60.0, "--inpaint-seconds", min=0.0,
                                          help="time cap for training the inpainting generator (0 = none: the "
                                               "OpenCV fallback composites)"),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="no progress bars"),
) -> None:
    """Write a demo speaker checkpoint and print its training metrics."""
    start = time.perf_counter()
    speaker, metrics = make_demo_speaker(gaussians, seed=seed, train_seconds=train_seconds, progress=not quiet,
                                         reference_clip=not no_reference, inpaint_seconds=inpaint_seconds)
    save_checkpoint(speaker, output)
    metrics["seconds"] = round(time.perf_counter() - start, 1)
    typer.echo(json.dumps(metrics, indent=2, default=float))
    typer.echo(f"wrote {output}")


if __name__ == "__main__":
    app()
