"""`gt-bench clip-crf`: what the reference clip's codec knob saves and costs, and the presets' whole-file sizes.

    gt-bench clip-crf --checkpoint out/speaker.ckpt --crfs 18,23,28,33 --codings "crf:20,gop:25" --out docs/bench

* Per clip setting (`ExportSettings.reference`, `gt-export --reference-codec`: "keep", then "crf:N" for each of
  `--crfs`, then each of `--codings`: groups of pictures, H.264 masks): one bundle of the fp32 speaker with only the
  clip changed. Its clip's MB (frames and masks) and the whole file's MB; the decoded clip frames against the stored
  ones (8-bit PSNR over the whole frame); the composited frames of the same audio (`TalkingHead` composites a bundle
  with a clip) against the "keep" bundle's, over the whole frame, inside the mask (M >= 0.5) and outside it. Each
  PSNR is the minimum and the mean over the frames.
* Per preset (`--presets`): the whole `.gtb` file, with the clip setting the preset stores, against `quality`'s,
  beside the same speaker exported without its clip and inpainting generator (the bare head `gt-bench sweep`
  measures), and each preset's size goal (`report.GOALS`) checked on the whole file; the whole file's composited
  frames against `quality`'s (the clip's, F's and the head's errors together), by region as above.
"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

import numpy as np
import typer

from gaussiantalker.exporter.export.bundle_export import export_bundle
from gaussiantalker.exporter.export.checkpoint import load_checkpoint
from gaussiantalker.exporter.export.presets import PRESETS, ExportSettings
from gaussiantalker.exporter.export.speech import synth_speech
from gaussiantalker.exporter.model.speaker import Speaker
from gaussiantalker.runtime.head import TalkingHead
from gaussiantalker.sdk.drive import track_row
from gaussiantalker.sdk.image import psnr_db
from gaussiantalker.sdk.progress import progress_bar

from .bare_head import without_clip
from .report import GOALS

CLIP_CRFS = (18, 23, 28, 33)  # the knob's values measured after "keep" (18: the CRF the clip is stored at)
REGIONS = ("whole", "inside", "outside")  # composited-frame regions: the frame, M >= 0.5, M < 0.5
MASK_INSIDE = 0.5


def clip_settings(crfs: tuple[int, ...] = CLIP_CRFS, codings: tuple[str, ...] = ()) -> list[ExportSettings]:
    """The export settings of each measured clip setting: the fp32 speaker with only the clip changed ("keep"
    first, the reference of the comparisons; then "crf:N" for each of `crfs`, then each of `codings` as written,
    e.g. "crf:20,gop:25,mask-crf:24"). This bench, not `gt-bench sweep`, sweeps the knob: the sweep plays the bare
    head, which has no clip."""
    return [ExportSettings(reference="keep"), *(ExportSettings(reference=f"crf:{crf}") for crf in crfs),
            *(ExportSettings(reference=coding) for coding in codings)]


def _stats(values: list[float]) -> dict[str, float]:
    return {"min": float(min(values)), "mean": float(np.mean(values))}


def _play(path: Path, audio: np.ndarray) -> tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray]]:
    """The composited frames of `audio`, and the clip picture and mask each frame shows."""
    with TalkingHead(path) as head:
        frames = list(head.frames(audio, head.driver.config.sample_rate))
        rows = [track_row(len(head.reference), index) for index in range(len(frames))]
        pictures = [head.reference.frame(row) for row in range(len(head.reference))]
        masks = [head.reference.mask(row) for row in range(len(head.reference))]
    return frames, [pictures[row] for row in rows], [masks[row] for row in rows]


def _compare(keep: tuple, test: tuple) -> dict:
    """PSNRs of `test`'s clip pictures and composited frames against `keep`'s (what `_play` returns)."""
    frames, pictures, masks = keep
    test_frames, test_pictures, _ = test
    clip = [psnr_db(a, b) for a, b in zip(pictures, test_pictures, strict=True)]
    regions: dict[str, list[float]] = {region: [] for region in REGIONS}
    for want, got, mask in zip(frames, test_frames, masks, strict=True):
        inside = mask >= MASK_INSIDE
        regions["whole"].append(psnr_db(want, got))
        regions["inside"].append(psnr_db(want[inside], got[inside]))
        regions["outside"].append(psnr_db(want[~inside], got[~inside]))
    return {"clip_psnr_db": _stats(clip), **{f"{region}_psnr_db": _stats(v) for region, v in regions.items()}}


def measure_clip_settings(speaker: Speaker, crfs: tuple[int, ...], seconds: float, tmp: Path, bar,
                          codings: tuple[str, ...] = ()) -> list[dict]:
    """One row per clip setting ("keep" first): bytes and PSNRs against "keep" (see the module docstring)."""
    audio = synth_speech(seconds, seed=3, sample_rate=speaker.config.sample_rate)
    rows, keep = [], None
    for index, settings in enumerate(clip_settings(crfs, codings)):
        bar.set_postfix_str(f"clip {settings.reference}")
        path = tmp / f"clip-{index}.gtb"
        result = export_bundle(speaker, path, settings=settings, progress=False)
        played = _play(path, audio)
        keep = keep or played
        frame_bytes = sum(n for name, n in result.buffer_bytes.items() if name.startswith("reference/frame/"))
        rows.append({"reference": settings.reference, "clip_bytes": result.reference_bytes,
                     "frame_bytes": frame_bytes, "bundle_bytes": path.stat().st_size,
                     "frames": len(played[0]), **_compare(keep, played)})
        bar.update()
    return rows


def measure_presets(speaker: Speaker, presets: tuple[str, ...], seconds: float, tmp: Path, bar) -> list[dict]:
    """Per preset: the whole file with its clip and the bare head's file (no clip, no F), in bytes; and the whole
    file's composited frames of `seconds` of audio against the first preset's (PSNR over the whole frame, inside
    the mask and outside it, as for the clip settings)."""
    audio = synth_speech(seconds, seed=3, sample_rate=speaker.config.sample_rate)
    rows, first = [], None
    for name in presets:
        bar.set_postfix_str(f"preset {name}")
        path = tmp / f"preset-{name}.gtb"
        result = export_bundle(speaker, path, preset=name, progress=False)
        with without_clip(speaker):
            export_bundle(speaker, tmp / f"bare-{name}.gtb", preset=name, progress=False)
        played = _play(path, audio)
        first = first or played
        rows.append({"preset": name, "reference": PRESETS[name].export.reference, "bundle_bytes": path.stat().st_size,
                     "clip_bytes": result.reference_bytes, "bare_bytes": (tmp / f"bare-{name}.gtb").stat().st_size,
                     **_compare(first, played)})
        bar.update()
    return rows


def _db(value: float) -> str:
    return "identical" if value == float("inf") else f"{value:.1f}"


def _pair(stats: dict) -> str:
    if stats["min"] == float("inf"):
        return "identical"
    return f"{_db(stats['min'])} / {_db(stats['mean'])}"


def format_tables(checkpoint: Path, gaussians: int, clip_rows: list[dict], preset_rows: list[dict],
                  seconds: float) -> str:
    """The Markdown tables docs/compositing.md and docs/precision.md keep."""
    lines = [f"Reference clip settings, {checkpoint} ({gaussians} Gaussians; {clip_rows[0]['frames']} composited "
             f"frames of {seconds:g} s of audio). PSNR: 8-bit, min / mean over frames, against the \"keep\" "
             "bundle's clip pictures and composited frames; inside: M >= 0.5.", "",
             "| clip setting | clip MB (frames + masks) | bundle MB | clip frames PSNR dB | composited PSNR dB, "
             "whole frame | inside the mask | outside the mask |", "|---|---|---|---|---|---|---|"]
    for row in clip_rows:
        masks = (row["clip_bytes"] - row["frame_bytes"]) / 1e6
        lines.append(f"| {row['reference']} | {row['clip_bytes'] / 1e6:.2f} ({row['frame_bytes'] / 1e6:.2f} + "
                     f"{masks:.2f}) | {row['bundle_bytes'] / 1e6:.2f} | {_pair(row['clip_psnr_db'])} | "
                     f"{_pair(row['whole_psnr_db'])} | {_pair(row['inside_psnr_db'])} | "
                     f"{_pair(row['outside_psnr_db'])} |")
    if preset_rows:
        whole, bare = preset_rows[0]["bundle_bytes"], preset_rows[0]["bare_bytes"]
        lines += ["", f"Presets, whole `.gtb` files against {preset_rows[0]['preset']}'s (with the clip setting each "
                  "preset stores), beside the same speaker without its clip and F (the bare head `gt-bench sweep` "
                  f"measures); composited PSNR: the whole file's frames against {preset_rows[0]['preset']}'s, min / "
                  "mean over frames:", "",
                  "| preset | clip setting | whole file MB | of which clip MB | × smaller (whole file) | size goal "
                  "(whole file) | bare head MB | × smaller (bare head) | composited PSNR dB, whole frame | inside the "
                  "mask | outside the mask |", "|---|---|---|---|---|---|---|---|---|---|---|"]
        for row in preset_rows:
            smaller = whole / row["bundle_bytes"]
            target = GOALS.get(row["preset"], {}).get("smaller")
            goal = "" if target is None else f"≥ {target:g}: {'met' if smaller >= target else 'missed'}"
            lines.append(f"| {row['preset']} | {row['reference']} | {row['bundle_bytes'] / 1e6:.2f} | "
                         f"{row['clip_bytes'] / 1e6:.2f} | {smaller:.1f} | {goal} | "
                         f"{row['bare_bytes'] / 1e6:.2f} | {bare / row['bare_bytes']:.1f} | "
                         f"{_pair(row['whole_psnr_db'])} | {_pair(row['inside_psnr_db'])} | "
                         f"{_pair(row['outside_psnr_db'])} |")
    return "\n".join(lines) + "\n"


def run_clip_crf_bench(checkpoint: Path, crfs: tuple[int, ...], presets: tuple[str, ...], seconds: float,
                       out: Path, progress: bool = True, codings: tuple[str, ...] = ()) -> str:
    """Measure, write the Markdown tables to `out` (and every row, in bytes, to `out` with the suffix .json) and
    return them (`presets` empty: no presets table; the first preset is the reference of the ratios)."""
    speaker = load_checkpoint(checkpoint)
    if speaker.reference is None:
        raise typer.BadParameter(f"{checkpoint} has no reference clip", param_hint="--checkpoint")
    bar = progress_bar(total=len(crfs) + len(codings) + 1 + len(presets), desc="gt-bench clip-crf", unit="bundle",
                       disable=not progress)
    with bar, tempfile.TemporaryDirectory(prefix="gt-clip-crf-") as tmp_name:
        tmp = Path(tmp_name)
        clip_rows = measure_clip_settings(speaker, crfs, seconds, tmp, bar, codings)
        preset_rows = measure_presets(speaker, presets, seconds, tmp, bar)
    text = format_tables(checkpoint, speaker.gaussians.count, clip_rows, preset_rows, seconds)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text)
    out.with_suffix(".json").write_text(json.dumps({"checkpoint": str(checkpoint), "seconds": seconds,
                                                    "clip": clip_rows, "presets": preset_rows}, indent=2,
                                                   default=lambda value: str(value)))
    return text
