"""Compositing's cost and seam quality (docs/compositing.md), side by side in one run:

    gt-bench --composite --checkpoint out/speaker.ckpt --seconds 4 --rounds 3 --out docs/bench
    python -m gaussiantalker.exporter.bench_composite --checkpoint out/speaker.ckpt --bundle out/speaker.gtb

* frames per second through `TalkingHead.frames` (audio to pixels) at the clip's size and at 512x512, composited
  and bare, alternating the four cases over `--rounds` rounds (medians; the machine's noise falls on all);
* F alone on the clip's crops (the `inpaint` graph, median ms), and the OpenCV fallback on the same crops;
* seam quality: on clip frames re-rendered with a jaw that differs from the frame's own by at least
  `MIN_JAW_CHANGE`, the mean absolute colour step across the mask's 0.5 contour (`sdk.image.seam_step`) of the
  composite with F, with the fallback and of the plain paste (1 - M) I_ori + M I_gau, beside the true frame's.
"""

from __future__ import annotations

import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import typer

from gaussiantalker.runtime.composite import composite, crop_box, graph_inpainter, opencv_fallback
from gaussiantalker.runtime.head import TalkingHead
from gaussiantalker.sdk.image import seam_step, to_uint8

from .checkpoint import load_checkpoint
from .compositing import torch_inpainter
from .demo_audio import synth_speech
from .demo_clip import ClipComposer

MIN_JAW_CHANGE = 0.1  # radians between the re-rendered jaw and the clip frame's own
app = typer.Typer(add_completion=False)


def _fps(bundle: Path, resolution, composite_frames: bool, audio: np.ndarray, rate: int) -> float:
    with TalkingHead(bundle, resolution=resolution, composite=composite_frames) as head:
        start = time.perf_counter()
        count = sum(1 for _ in head.frames(audio, rate))
        return count / (time.perf_counter() - start)


def _crop_ms(head: TalkingHead, inpaint, frames: int = 30) -> float:
    seconds = []
    for index in range(frames):
        mask, picture = head.reference.mask(index), head.reference.frame(index)
        box = crop_box(mask)
        x = picture[box.rows, box.columns].astype(np.float32) / 255 * (1 - mask[box.rows, box.columns, None])
        render = np.zeros((*x.shape[:2], 4), np.float32)
        start = time.perf_counter()
        inpaint(x, mask[box.rows, box.columns], render)
        seconds.append(time.perf_counter() - start)
    return 1e3 * statistics.median(seconds)


def _seams(checkpoint: Path, pairs: int, seed: int) -> dict[str, float]:
    speaker = load_checkpoint(checkpoint)
    composer = ClipComposer(speaker)
    rng = np.random.default_rng(seed)
    steps: dict[str, list[float]] = {"F": [], "fallback": [], "plain paste": [], "true frame": []}
    while len(steps["F"]) < pairs:
        index = int(rng.integers(len(composer.track)))
        jaw = float(rng.uniform(0.0, 0.34))
        if abs(jaw - composer.jaw[index]) < MIN_JAW_CHANGE:
            continue
        original, _ = composer.frame(index)
        head = composer.render_head(composer.drive(index, jaw))
        truth = composer.compose(index, head).image
        picture, mask = to_uint8(original.image), original.mask
        cases = {"F": composite(head, picture, mask, torch_inpainter(speaker.inpaint)),
                 "fallback": composite(head, picture, mask, opencv_fallback),
                 "plain paste": to_uint8((1 - mask[..., None]) * picture / 255.0 + mask[..., None] * head[..., :3]),
                 "true frame": to_uint8(truth)}
        for name, frame in cases.items():
            steps[name].append(seam_step(frame / 255.0, mask))
    composer.splatter.release()
    return {name: float(np.mean(values)) for name, values in steps.items()}


def run_composite_bench(checkpoint: Path, bundle: Path | None, seconds: float, rounds: int, pairs: int,
                        out: Path) -> str:
    """Measure, write the Markdown table to `out` and return it (`bundle` None: the checkpoint exported afresh)."""
    if bundle is None:
        from .export import export_bundle

        with tempfile.TemporaryDirectory() as tmp:
            bundle = Path(tmp) / "composite.gtb"
            export_bundle(load_checkpoint(checkpoint), bundle, progress=False)
            return run_composite_bench(checkpoint, bundle, seconds, rounds, pairs, out)
    with TalkingHead(bundle) as head:
        if head.reference is None:
            raise typer.BadParameter(f"{checkpoint} has no reference clip to composite into", param_hint="--checkpoint")
        clip_size = (head.camera.width, head.camera.height)
        rate = head.config.sample_rate
        audio = synth_speech(seconds, seed=3, sample_rate=rate)
        f_ms = _crop_ms(head, graph_inpainter(head.graphs.run))
        fallback_ms = _crop_ms(head, opencv_fallback)
        crop = crop_box(head.reference.mask(0))
    cases = [(f"{w}x{h} {'composited' if c else 'bare'}", (w, h), c) for (w, h) in (clip_size, (512, 512))
             for c in (True, False)]
    fps: dict[str, list[float]] = {name: [] for name, _, _ in cases}
    for _ in range(rounds):
        for name, size, composite_frames in cases:
            fps[name].append(_fps(bundle, size, composite_frames, audio, rate))
    seams = _seams(checkpoint, pairs, seed=11)
    lines = [f"Compositing, {checkpoint} ({rounds} alternating rounds of {seconds:g} s of audio; medians).", "",
             "| case | FPS (audio to pixels) | x bare |", "|---|---|---|"]
    for (w, h) in (clip_size, (512, 512)):
        bare = statistics.median(fps[f"{w}x{h} bare"])
        for kind in ("composited", "bare"):
            value = statistics.median(fps[f"{w}x{h} {kind}"])
            lines.append(f"| {w}x{h} {kind} | {value:.1f} | {value / bare:.2f} |")
    lines += ["", f"F alone on the clip's crops ({crop.width}x{crop.height} for frame 0): {f_ms:.1f} ms median; "
              f"the OpenCV fallback: {fallback_ms:.1f} ms.", "",
              f"Seam step across the mask's contour ({pairs} clip frames re-rendered with a jaw at least "
              f"{MIN_JAW_CHANGE} rad from the frame's own; mean |colour step| in [0, 1] units):", "",
              "| composite | seam step | x plain paste |", "|---|---|---|"]
    for name, value in seams.items():
        lines.append(f"| {name} | {value:.4f} | {value / seams['plain paste']:.2f} |")
    text = "\n".join(lines) + "\n"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text)
    return text


@app.command()
def main(checkpoint: Path = typer.Option(Path("out/speaker.ckpt"), help="speaker with a reference clip and F"),
         bundle: Path = typer.Option(Path("out/speaker.gtb"), help="its exported bundle"),
         seconds: float = typer.Option(4.0, help="audio per FPS case"),
         rounds: int = typer.Option(3, min=1, help="alternating rounds"),
         pairs: int = typer.Option(12, min=1, help="re-rendered frames for the seam measure"),
         out: Path = typer.Option(Path("docs/bench/composite.md"), help="Markdown table written here")) -> None:
    """Measure and write the table."""
    typer.echo(run_composite_bench(checkpoint, bundle, seconds, rounds, pairs, out))


if __name__ == "__main__":
    app()
