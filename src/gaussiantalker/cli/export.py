"""`gt-export speaker.ckpt -o speaker.gtb [--verify] [--report report.json]`: the exporter's command line."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import typer

from gaussiantalker.exporter.export.presets import PRESETS, settings_with
from gaussiantalker.sdk.errors import GaussianTalkerError
from gaussiantalker.sdk.files import StagedFile, atomic_path, atomic_write

app = typer.Typer(add_completion=False, help=__doc__)

# JSON has no infinity: identical frames (PSNR = +inf) are written as this many dB.
PSNR_CAP_DB = 200.0


def _json_safe(value):
    if isinstance(value, float) and math.isinf(value):
        return PSNR_CAP_DB if value > 0 else -PSNR_CAP_DB
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_json_safe(v) for v in value]
    return value


def _resolution(text: str) -> tuple[int, int]:
    parts = text.lower().split("x")
    try:
        size = tuple(int(p) for p in parts)
    except ValueError:
        raise typer.BadParameter(f"resolution must be N or WxH, got {text!r}") from None
    if len(size) == 1:
        size = (size[0], size[0])
    if len(size) != 2 or min(size) < 1:
        raise typer.BadParameter(f"resolution must be N or WxH with positive sides, got {text!r}")
    return size


@app.command()
def export(
    checkpoint: Path = typer.Argument(..., help="speaker checkpoint (torch.save file, read weights-only)"),
    output: Path = typer.Option(None, "-o", "--output", help="bundle to write [default: CHECKPOINT with .gtb]"),
    verify: bool = typer.Option(False, "--verify", help="prove the bundle against the torch speaker"),
    report: Path = typer.Option(None, "--report", help="write the verification report as JSON (implies --verify)"),
    frames: int = typer.Option(25, "--frames", min=1, help="audio-driven frames to compare when verifying"),
    resolution: str = typer.Option(None, "--resolution", help="verification frame size, N or WxH [default: 256, "
                                   "or the scene's]"),
    min_psnr: float = typer.Option(None, "--min-psnr",
                                   help="required 8-bit PSNR (dB) of every frame [default: the label's]"),
    min_float_psnr: float = typer.Option(None, "--min-float-psnr",
                                         help="required float-frame PSNR (dB) [default: the label's]"),
    preset: str = typer.Option(None, "--preset", help=f"speed/accuracy preset: {', '.join(PRESETS)} "
                                                      "(docs/precision.md); the knobs below override its settings"),
    codec: str = typer.Option(None, "--codec", help="one codec for every buffer: raw (fp32), fp16, q16, q8, q4"),
    gaussians: str = typer.Option(None, "--gaussian-codec", help="codec of the per-Gaussian attributes"),
    sh: str = typer.Option(None, "--sh-codec", help="codec of the SH bands 1-3"),
    blendshapes: str = typer.Option(None, "--blendshape-codec", help="codec of the speaker blendshape weights"),
    flame: str = typer.Option(None, "--flame-codec", help="codec of the FLAME bases"),
    translator: str = typer.Option(None, "--translator-codec", help="codec of the translator weights"),
    inpaint: str = typer.Option(None, "--inpaint-codec", help="codec of the inpainting generator's weights"),
    translator_precision: str = typer.Option(None, "--translator-precision", help="translator graph: fp32, fp16, "
                                             "int8 (onnxruntime dynamic quantisation)"),
    sh_degree: int = typer.Option(None, "--sh-degree", min=0, max=3, help="keep SH bands up to this degree"),
    blendshape_rank: int = typer.Option(None, "--blendshape-rank", min=1, help="rank of the blendshape matrix"),
    gaussian_budget: str = typer.Option(None, "--gaussian-budget", help="keep N Gaussians (or P%), the largest "
                                        "contributors over a driven clip and a head-pose sweep"),
    refit_steps: int = typer.Option(None, "--refit-steps", min=0, help="fit the Gaussians a budget keeps to the "
                                    "full speaker's frames for N steps (colours, opacities, scales; about 0.2 s a "
                                    "step for 8k Gaussians; fast and mobile do 400 for an ARKit avatar)"),
    reference: str = typer.Option(None, "--reference-codec", help="the reference clip: keep (as the checkpoint "
                                  "stores it) or crf:N[,gop:K][,mask-crf:M]: frames re-encoded with x264 at CRF N "
                                  "(0-51: larger is smaller and coarser), in groups of K pictures (default 1: each "
                                  "frame alone), masks as H.264 at CRF M (default: kept lossless; "
                                  "docs/compositing.md)"),
    midpoints: bool = typer.Option(None, "--midpoints/--no-midpoints", help="an imported avatar's subdivided mesh: "
                                   "derive its edge vertices' morph targets from their ends instead of storing them "
                                   "(within 10 µm; the reduced presets do)"),
    spatial_order: bool = typer.Option(None, "--spatial-order/--no-spatial-order", help="the Gaussians in the "
                                       "Morton order of their positions: neighbours share quantisation chunks, the "
                                       "same frames (compact does for ARKit avatars)"),
    deflate: bool = typer.Option(None, "--deflate/--no-deflate", help="store every buffer zlib-compressed where that "
                                 "is smaller (lossless; compact does for ARKit avatars)"),
    buffer_codec: list[str] = typer.Option(None, "--buffer-codec", help="one buffer's codec, NAME=CODEC (repeat "
                                           "for more), over its group's, e.g. deform/rotation=vq/256"),
    scene: Path = typer.Option(None, "--scene", help="compile the bundle for a scene (TOML/JSON, docs/scene.md): "
                               "leave out what it never uses, record it in the bundle"),
    mnn: bool = typer.Option(False, "--mnn", help="also store every graph as an MNN model, for "
                             "TalkingHead(backend='mnn') and native ports (docs/mnn.md; needs the mnn extra)"),
    short_stream: bool = typer.Option(False, "--short-stream", help="also a trained translator's short stream, whose "
                                      "rows lag 80 ms: live sessions with less than 160 ms of lookahead may run it "
                                      "(stream_delay_ms=80), cheaper and less accurate (docs/live.md)"),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="no progress bars"),
) -> None:
    """Export a speaker checkpoint to a bundle; with --verify, place it only if it reproduces the torch frames.

    Codec values: raw, fp16, q16, q8, q4, vq; a quantised codec may name its chunk size (q4/64), the codebook vq
    its entries (vq/1024)."""
    from gaussiantalker.exporter.export.bundle_export import export_bundle, rig_of
    from gaussiantalker.exporter.export.checkpoint import load_checkpoint

    output = output or checkpoint.with_suffix(".gtb")
    verify = verify or report is not None
    size = None if resolution is None and scene is not None else _resolution(resolution or "256")
    try:
        from gaussiantalker.sdk.scene import load_scene

        scene_spec = None if scene is None else load_scene(scene)  # a bad scene fails before the checkpoint loads
        knobs = {"gaussians": gaussians, "sh": sh, "blendshapes": blendshapes, "flame": flame,
                 "translator": translator, "inpaint": inpaint, "translator_precision": translator_precision,
                 "sh_degree": sh_degree, "blendshape_rank": blendshape_rank,
                 "gaussian_budget": _budget(gaussian_budget), "refit_steps": refit_steps, "reference": reference,
                 "midpoints": midpoints,
                 "spatial_order": spatial_order, "deflate": deflate, "buffer_codecs": _buffer_codecs(buffer_codec)}
        _settings(preset, codec, knobs, "flame")  # a bad knob fails before the checkpoint loads
        speaker = load_checkpoint(checkpoint)
        settings, chosen = _settings(preset, codec, knobs, rig_of(speaker))
        # The bundle is staged beside the output and placed there only once it is complete (and, with --verify,
        # has passed), so a failed or interrupted run never replaces a good bundle.
        with atomic_path(output) as staged:
            result = export_bundle(speaker, staged, settings=settings, preset=chosen, progress=not quiet,
                                   scene=scene_spec, mnn=mnn, short_stream=short_stream)
            if result.specialisation is not None:
                from gaussiantalker.exporter.export.specialise import format_removals

                typer.echo(format_removals(result.specialisation.removals))
            clip = (f", reference clip {result.reference_bytes / 1e6:.2f} MB ({result.settings.reference})"
                    if result.reference_bytes else "")
            typer.echo(f"wrote {result.bytes_written / 1e6:.2f} MB bundle ({result.gaussians} Gaussians, "
                       f"tier {result.label}, graphs: {', '.join(result.graphs)}{clip})")
            if result.mnn:
                typer.echo("MNN graphs: " + ", ".join(f"{name} {size / 1e6:.2f} MB" for name, size in
                                                      result.mnn.items()))
            if verify:
                from gaussiantalker.exporter.verify.bundle_verify import Tolerances

                tolerances = Tolerances.for_settings(settings, chosen)
                tolerances = tolerances if scene_spec is None else tolerances.for_scene()
                _verify(speaker, staged, output, tolerances, frames, size, min_psnr, min_float_psnr, report, quiet)
        typer.echo(f"bundle: {output}" + (" (verified)" if verify else ""))
    except GaussianTalkerError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None


def _budget(text: str | None) -> float | None:
    """--gaussian-budget: a number of Gaussians or a percentage ("60%")."""
    if text is None:
        return None
    try:
        return float(text[:-1]) / 100 if text.endswith("%") else float(int(text))
    except ValueError:
        raise typer.BadParameter(f"--gaussian-budget must be a whole number or a percentage, got {text!r}") from None


def _buffer_codecs(pairs: list[str] | None) -> tuple[tuple[str, str], ...] | None:
    """--buffer-codec NAME=CODEC values as (name, codec) pairs (None: none given)."""
    if not pairs:
        return None
    parsed = []
    for pair in pairs:
        name, equals, codec = pair.partition("=")
        if not (name and equals and codec):
            raise typer.BadParameter(f"--buffer-codec takes NAME=CODEC (e.g. deform/rotation=vq/256), got {pair!r}")
        parsed.append((name, codec))
    return tuple(parsed)


def _settings(preset: str | None, codec: str | None, knobs: dict, rig: str):
    """The export settings for a speaker of `rig`: a preset's (or every buffer with --codec, or fp32) with the given
    knobs replacing its values (the bundle then records the preset's runtime defaults and "NAME+custom" as its
    label)."""
    from gaussiantalker.exporter.export.bundle_export import resolve_settings

    if preset is not None and codec is not None:
        raise typer.BadParameter("give --preset or --codec, not both (--codec sets every buffer's codec)")
    base, chosen, _ = resolve_settings(codec=codec, preset=preset, rig=rig)
    return settings_with(base, **knobs), chosen


def _verify(speaker, staged: StagedFile, output: Path, defaults, frames: int, size: tuple[int, int] | None,
            min_psnr: float | None, min_float_psnr: float | None, report: Path | None, quiet: bool) -> None:
    """Verify the staged bundle; a failure keeps it as NAME.unverified.gtb (not at `output`) and exits 1."""
    from dataclasses import replace

    from gaussiantalker.exporter.verify.bundle_verify import format_report, verify_bundle

    tolerances = replace(
        defaults, min_psnr_float_db=defaults.min_psnr_float_db if min_float_psnr is None else min_float_psnr,
        min_psnr_uint8_db=defaults.min_psnr_uint8_db if min_psnr is None else min_psnr)
    outcome = verify_bundle(speaker, staged.path, frames=frames, resolution=size, tolerances=tolerances,
                            progress=not quiet)
    typer.echo(format_report(outcome))
    outcome["bundle"] = str(output)
    if report is not None:
        with atomic_write(report, "w") as handle:
            handle.write(json.dumps(_json_safe(outcome), indent=2))
        typer.echo(f"report: {report}")
    if not outcome["passed"]:
        failed = staged.commit(output.with_name(output.stem + ".unverified.gtb"))
        typer.echo(f"verification failed: bundle kept at {failed}, not at {output}", err=True)
        raise typer.Exit(1)


def main() -> None:
    """Console-script entry point."""
    app(prog_name="gt-export")


if __name__ == "__main__":
    sys.exit(main())
