"""Compositing's cost and seam quality (docs/compositing.md), side by side in one run:

    gt-bench composite --checkpoint out/speaker.ckpt --bundle out/speaker.gtb --seconds 4 --rounds 3 --out docs/bench

* frames per second through `TalkingHead.frames` (audio to pixels) at the clip's size and at 512x512, composited
  and bare, alternating the four cases over `--rounds` rounds (medians; the machine's noise falls on all);
* F alone on the clip's crops (the `inpaint` graph, median ms), and the OpenCV fallback on the same crops;
* seam quality: on clip frames re-rendered with a jaw that differs from the frame's own by at least
  `MIN_JAW_CHANGE`, the mean absolute colour step across the mask's 0.5 contour (`sdk.image.seam_step`) of the
  composite with F, with the fallback and of the plain paste (1 - M) I_ori + M I_gau, beside the true frame's;
* F's codec knob (`ExportSettings.inpaint`, `gt-export --inpaint-codec`): one bundle per codec in `F_CODECS`,
  each one's F bytes, its composited frames of the same audio against the fp32 F's (8-bit PSNR inside the mask,
  the only pixels F reaches), and the seam step with its F.
"""

from __future__ import annotations

import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import typer
from tqdm import tqdm

from gaussiantalker.exporter.demo.clip import ClipComposer
from gaussiantalker.exporter.export.bundle_export import export_bundle
from gaussiantalker.exporter.export.checkpoint import load_checkpoint
from gaussiantalker.exporter.export.presets import ExportSettings
from gaussiantalker.exporter.export.speech import synth_speech
from gaussiantalker.exporter.model.speaker import Speaker
from gaussiantalker.exporter.verify.compositing import torch_inpainter
from gaussiantalker.runtime.composite import composite, crop_box, graph_inpainter, opencv_fallback
from gaussiantalker.runtime.head import TalkingHead
from gaussiantalker.sdk.drive import track_row
from gaussiantalker.sdk.image import psnr_db, seam_step, to_uint8
from gaussiantalker.sdk.progress import progress_bar

MIN_JAW_CHANGE = 0.1  # radians between the re-rendered jaw and the clip frame's own
F_CODECS = ("raw", "fp16", "q8", "q4")  # the inpaint codec knob's values measured (raw: the reference)


def _fps(bundle: Path, resolution, composite_frames: bool, audio: np.ndarray, rate: int) -> float:
    with TalkingHead(bundle, resolution=resolution, composite=composite_frames) as head:
        start = time.perf_counter()
        count = sum(1 for _ in head.frames(audio, rate))
        return count / (time.perf_counter() - start)


def _crop_ms(head: TalkingHead, inpaint, frames: int = 30) -> float:
    seconds = []
    for index in range(frames):  # a clip shorter than `frames` is played forth and back, as TalkingHead does
        row = track_row(len(head.reference), index)
        mask, picture = head.reference.mask(row), head.reference.frame(row)
        box = crop_box(mask)
        x = picture[box.rows, box.columns].astype(np.float32) / 255 * (1 - mask[box.rows, box.columns, None])
        render = np.zeros((*x.shape[:2], 4), np.float32)
        start = time.perf_counter()
        inpaint(x, mask[box.rows, box.columns], render)
        seconds.append(time.perf_counter() - start)
    return 1e3 * statistics.median(seconds)


def _seams(speaker: Speaker, pairs: int, seed: int, inpainters: dict | None = None) -> dict[str, float]:
    """Mean seam step per composite over `pairs` re-rendered frames; `inpainters` adds named Fs (e.g. a bundle's
    `inpaint` graph at some codec) beside the torch F, the fallback, the plain paste and the true frame."""
    composer = ClipComposer(speaker, size=speaker.reference.layout.size)  # the clip's own frames and masks
    rng = np.random.default_rng(seed)
    inpainters = {"F": torch_inpainter(speaker.inpaint), "fallback": opencv_fallback, **(inpainters or {})}
    steps: dict[str, list[float]] = {name: [] for name in [*inpainters, "plain paste", "true frame"]}
    while len(steps["F"]) < pairs:
        index = int(rng.integers(len(composer.track)))
        jaw = float(rng.uniform(0.0, 0.34))
        if abs(jaw - composer.jaw[index]) < MIN_JAW_CHANGE:
            continue
        original, _ = composer.frame(index)
        head = composer.render_head(composer.drive(index, jaw))
        truth = composer.compose(index, head).image
        picture, mask = to_uint8(original.image), original.mask
        cases = {name: composite(head, picture, mask, inpaint) for name, inpaint in inpainters.items()}
        cases |= {"plain paste": to_uint8((1 - mask[..., None]) * picture / 255.0 + mask[..., None] * head[..., :3]),
                  "true frame": to_uint8(truth)}
        for name, frame in cases.items():
            steps[name].append(seam_step(frame / 255.0, mask))
    composer.splatter.release()
    return {name: float(np.mean(values)) for name, values in steps.items()}


def f_codec_settings(codecs: tuple[str, ...] = F_CODECS) -> list[ExportSettings]:
    """The export settings of each measured F codec: the fp32 speaker with only F's weights changed. (This bench,
    not `gt-bench sweep`, sweeps the knob: only composited frames show F, and the sweep plays the bare head.)"""
    return [ExportSettings(inpaint=codec) for codec in codecs]


def _f_bytes(manifest: dict) -> int:
    """Bytes F takes in a bundle (its `manifest`): its graph entry and its weight buffers."""
    weights = sum(entry["nbytes"] for name, entry in manifest["buffers"].items() if name.startswith("inpaint/"))
    return manifest["graphs"]["inpaint"]["nbytes"] + weights


def _f_codecs(speaker: Speaker, codecs: tuple[str, ...], audio: np.ndarray, rate: int, tmp: Path,
                 bar: tqdm) -> tuple[list[dict], dict]:
    """Per inpaint codec: F's bytes and its composited frames against the first codec's (8-bit, inside M), plus
    each bundle's F as an inpainter (for the seam measure)."""
    rows, inpainters, reference_frames = [], {}, None
    for codec, settings in zip(codecs, f_codec_settings(codecs), strict=True):
        bar.set_postfix_str(f"export, F {codec}")
        path = tmp / f"f-{codec.replace('/', '_')}.gtb"
        export_bundle(speaker, path, settings=settings, progress=False)
        bar.set_postfix_str(f"frames, F {codec}")
        errors, psnrs = [], []
        with TalkingHead(path) as head:
            frames = list(head.frames(audio, rate))
            if reference_frames is None:
                reference_frames = frames
            for index, (reference, frame) in enumerate(zip(reference_frames, frames, strict=True)):
                inside = head.reference.mask(track_row(len(head.reference), index)) > 0
                psnrs.append(psnr_db(reference[inside], frame[inside]))
                errors.append(int(np.abs(reference.astype(np.int16) - frame.astype(np.int16)).max()))
            # The head's graph sessions outlive it (closing a head releases its GL objects only).
            inpainters[f"F {codec}"] = graph_inpainter(head.frame_renderer.graphs.run)
            f_bytes = _f_bytes(head.bundle.manifest)
        rows.append({"codec": codec, "f_bytes": f_bytes, "min_psnr_db": min(psnrs),
                     "mean_psnr_db": float(np.mean(psnrs)), "max_pixel_error": max(errors)})
        bar.update()
    return rows, inpainters


def run_composite_bench(checkpoint: Path, bundle: Path | None, seconds: float, rounds: int, pairs: int,
                        out: Path, codecs: tuple[str, ...] = F_CODECS, progress: bool = True) -> str:
    """Measure, write the Markdown tables to `out` and return them (`bundle` None: the checkpoint exported
    afresh; `codecs` empty: no F-codec table)."""
    speaker = load_checkpoint(checkpoint)
    if speaker.reference is None:
        raise typer.BadParameter(f"{checkpoint} has no reference clip to composite into", param_hint="--checkpoint")
    with tempfile.TemporaryDirectory(prefix="gt-composite-") as tmp_name:
        tmp = Path(tmp_name)
        if bundle is None:
            bundle = tmp / "composite.gtb"
            export_bundle(speaker, bundle, progress=False)
        return _measure(speaker, checkpoint, bundle, seconds, rounds, pairs, out, codecs if speaker.inpaint else (),
                        tmp, progress)


def _measure(speaker: Speaker, checkpoint: Path, bundle: Path, seconds: float, rounds: int, pairs: int, out: Path,
             codecs: tuple[str, ...], tmp: Path, progress: bool) -> str:
    with TalkingHead(bundle) as head:
        clip_size = (head.camera.width, head.camera.height)
        rate = head.driver.config.sample_rate
        audio = synth_speech(seconds, seed=3, sample_rate=rate)
        f_ms = _crop_ms(head, graph_inpainter(head.frame_renderer.graphs.run))
        fallback_ms = _crop_ms(head, opencv_fallback)
        crop = crop_box(head.reference.mask(0))
    cases = [(f"{w}x{h} {'composited' if c else 'bare'}", (w, h), c) for (w, h) in (clip_size, (512, 512))
             for c in (True, False)]
    bar = progress_bar(total=rounds * len(cases) + len(codecs) + 1, desc="gt-bench composite", unit="run",
               disable=not progress)
    with bar:
        fps: dict[str, list[float]] = {name: [] for name, _, _ in cases}
        for round_index in range(rounds):
            for name, size, composite_frames in cases:
                bar.set_postfix_str(f"round {round_index + 1}: {name}")
                fps[name].append(_fps(bundle, size, composite_frames, audio, rate))
                bar.update()
        codec_rows, inpainters = _f_codecs(speaker, codecs, audio, rate, tmp, bar)
        bar.set_postfix_str("seam steps")
        seams = _seams(speaker, pairs, seed=11, inpainters={k: v for k, v in inpainters.items() if k != "F raw"})
        bar.update()
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
              f"{MIN_JAW_CHANGE} rad from the frame's own; mean |colour step| in [0, 1] units; F is the torch "
              "generator, F <codec> the bundle's graph with that codec):", "",
              "| composite | seam step | x plain paste |", "|---|---|---|"]
    for name, value in seams.items():
        lines.append(f"| {name} | {value:.4f} | {value / seams['plain paste']:.2f} |")
    if codec_rows:
        lines += ["", f"F's codec (`--inpaint-codec`): composited frames of the same {seconds:g} s against the "
                  f"{codec_rows[0]['codec']} F's, 8-bit PSNR inside the mask (min and mean over frames):", "",
                  "| F codec | F bytes | PSNR min | PSNR mean | max pixel error |", "|---|---|---|---|---|"]
        for row in codec_rows:
            lines.append(f"| {row['codec']} | {row['f_bytes']:,} | {row['min_psnr_db']:.1f} dB | "
                         f"{row['mean_psnr_db']:.1f} dB | {row['max_pixel_error']} |")
    text = "\n".join(lines) + "\n"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text)
    return text
