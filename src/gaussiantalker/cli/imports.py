"""`gt-import lam AVATAR.zip -o avatar.ckpt`, `gt-import gaussian-avatars DIR --flame FLAME.pkl -o avatar.ckpt`:
avatars trained elsewhere become speaker checkpoints (docs/import.md), with the built-in voice driver attached
(docs/voice.md), which `gt-export` then turns into bundles like any other; `gt-import voice CKPT` attaches that
driver to a speaker imported without it; `gt-import flame FLAME.pkl -o flame.npz` converts FLAME's model pickle
safely."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import typer

from gaussiantalker.sdk.errors import GaussianTalkerError
from gaussiantalker.sdk.rig import COVARIANCE_MODES

app = typer.Typer(add_completion=False, help=__doc__, no_args_is_help=True)


@app.callback()
def main_callback() -> None:
    """Import an avatar as a speaker checkpoint (then: gt-export CHECKPOINT -o BUNDLE.gtb --verify), or convert a
    FLAME model pickle to npz."""


@app.command("lam")
def lam(
    avatar: Path = typer.Argument(..., help="LAM avatar zip (skin.glb, offset.ply, animation.glb, ...; at the top "
                                            "or in one folder), as LAM_WebRender and OpenAvatarChat ship them"),
    output: Path = typer.Option(None, "-o", "--output", help="checkpoint to write [default: AVATAR with .ckpt]"),
    clip: str = typer.Option(None, "--clip", help="animation.glb clip whose head motion becomes the pose track "
                                                  "[default: the idle clip]"),
    raw_weights: bool = typer.Option(False, "--raw-weights", help="keep the morph targets as stored; by default the "
                                     "web renderer's weight scales are folded in, so ARKit weights look as there"),
    covariance: str = typer.Option("static", "--covariance", help="how Gaussians' shapes follow the head: static "
                                   "(as LAM's renderer draws) or head (turned with the head bone)"),
    audio_model: Path = typer.Option(None, "--audio-model", help="an audio-to-ARKit ONNX model to attach instead "
                                     "of the built-in voice driver (input audio [1, S] at 16 kHz, output [1, T, 52] "
                                     "at 30 fps; docs/import.md)"),
    no_voice: bool = typer.Option(False, "--no-voice", help="attach no audio model: motion files drive the avatar, "
                                  "audio does not [default: the built-in voice driver, docs/voice.md]"),
    camera: str = typer.Option("portrait", "--camera", help="the bundle's camera: portrait (the head's box "
                               "47.5% of the frame's height, centred, docs/import.md) or source (LAM's renderer's "
                               "fixed camera)"),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="no progress bar"),
) -> None:
    """Import a LAM avatar (an ARKit speaker: 52 blendshape weights drive it; docs/import.md)."""
    from gaussiantalker.exporter.export.checkpoint import save_checkpoint
    from gaussiantalker.exporter.imports.audio_model import load_audio_model
    from gaussiantalker.exporter.imports.sources.lam import LamOptions, import_lam
    from gaussiantalker.exporter.voice.attach import builtin_audio_model

    if covariance not in COVARIANCE_MODES:
        raise typer.BadParameter(f"--covariance must be one of {', '.join(COVARIANCE_MODES)}, got {covariance!r}")
    _check_voice_options(audio_model, no_voice)
    _check_camera(camera)
    output = output or avatar.with_suffix(".ckpt")
    start = time.perf_counter()
    try:
        model = None if audio_model is None else load_audio_model(audio_model)  # a bad model fails first
        speaker = import_lam(avatar, LamOptions(clip=clip, renderer_weight_scale=not raw_weights,
                                                covariance=covariance, camera=camera), progress=not quiet)
        if model is None and not no_voice:
            model = builtin_audio_model(speaker)
        speaker.audio_model = model
        save_checkpoint(speaker, output)
    except GaussianTalkerError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None
    pose = "no pose track" if speaker.pose_track is None else \
        f"pose track {speaker.pose_track.shape[0]} frames from clip {speaker.source.get('pose_clip')!r}"
    motion = "no motion track" if speaker.motion_track is None else \
        f"motion track {speaker.motion_track.shape[0]} frames"
    attached = _attached(audio_model, model)
    typer.echo(f"imported {speaker.gaussians.count} Gaussians, {len(speaker.source['morph_targets'])} morph targets, "
               f"{pose}, {motion}{attached} in {time.perf_counter() - start:.1f} s")
    typer.echo(f"checkpoint: {output} (next: gt-export {output} --verify)")


@app.command("gaussian-avatars")
def gaussian_avatars(
    avatar: Path = typer.Argument(..., help="GaussianAvatars output directory (with point_cloud/iteration_N/"
                                            "point_cloud.ply and flame_param.npz), or that iteration folder"),
    flame_model: Path = typer.Option(..., "--flame", help="your FLAME 2023 model: flame2023.pkl (read without "
                                     "running anything from it) or the npz `gt-import flame` writes"),
    output: Path = typer.Option(None, "-o", "--output", help="checkpoint to write [default: AVATAR's folder name "
                                "with .ckpt, in the current directory]"),
    iteration: int = typer.Option(None, "--iteration", help="training iteration to import [default: the last]"),
    fps: float = typer.Option(25.0, "--fps", help="frame rate of the tracked motion in flame_param.npz (the file "
                              "records none); resampled to the speaker's 25 fps"),
    resolution: int = typer.Option(512, "--resolution", help="side of the default camera's square frame, pixels"),
    background: str = typer.Option("1,1,1", "--background", help="background colour r,g,b in 0..1"),
    audio_model: Path = typer.Option(None, "--audio-model", help="an audio-to-FLAME ONNX model to attach instead "
                                     "of the built-in voice driver (input audio [1, S] at 16 kHz; outputs expression "
                                     "[1, T, 100] and jaw pose [1, T, 3] at 25 fps; docs/import.md)"),
    no_voice: bool = typer.Option(False, "--no-voice", help="attach no audio model: FLAME parameters and motion "
                                  "files drive the avatar, audio does not [default: the built-in voice driver with "
                                  "its expressions fitted on your FLAME, docs/voice.md]"),
    camera: str = typer.Option("portrait", "--camera", help="the bundle's camera: portrait (the head's box 47.5% of "
                               "the frame's height, centred, docs/import.md) or source (GaussianAvatars' viewer: the "
                               "mesh at 80% of the height)"),
) -> None:
    """Import a GaussianAvatars avatar (a FLAME speaker: FLAME parameters or its tracked motion drive it)."""
    from gaussiantalker.exporter.export.checkpoint import save_checkpoint
    from gaussiantalker.exporter.imports.audio_model import flame_outputs, load_audio_model
    from gaussiantalker.exporter.imports.sources.gaussian_avatars import GaussianAvatarsOptions, import_gaussian_avatars
    from gaussiantalker.exporter.imports.sources.gaussian_avatars_flame import GA_N_EXPR
    from gaussiantalker.exporter.voice.attach import builtin_audio_model

    _check_voice_options(audio_model, no_voice)
    _check_camera(camera)
    try:
        colour = tuple(float(c) for c in background.split(","))
    except ValueError:
        colour = ()
    if len(colour) != 3 or not all(0.0 <= c <= 1.0 for c in colour):
        raise typer.BadParameter(f"--background must be three numbers r,g,b in 0..1, got {background!r}")
    if not (fps > 0 and 16 <= resolution <= 8192):
        raise typer.BadParameter("--fps must be positive and --resolution within 16..8192")
    output = output or Path(f"{avatar.resolve().name}.ckpt")
    start = time.perf_counter()
    try:
        model = None if audio_model is None else load_audio_model(audio_model, flame_outputs(GA_N_EXPR))
        speaker = import_gaussian_avatars(avatar, flame_model, GaussianAvatarsOptions(
            iteration=iteration, fps=fps, resolution=resolution, background=colour, camera=camera))
        if model is None and not no_voice:
            model = builtin_audio_model(speaker)
        speaker.audio_model = model
        save_checkpoint(speaker, output)
    except GaussianTalkerError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None
    attached = _attached(audio_model, model)
    typer.echo(f"imported {speaker.gaussians.count} Gaussians (SH degree {speaker.config.sh_degree}) on "
               f"{speaker.flame_arrays.n_faces} triangles from {speaker.source['iteration']}, motion track "
               f"{speaker.motion_track.shape[0]} frames{attached} in {time.perf_counter() - start:.1f} s")
    typer.echo(f"checkpoint: {output} (next: gt-export {output} --verify)")


@app.command("voice")
def voice(
    checkpoint: Path = typer.Argument(..., help="an imported speaker's checkpoint (gt-import lam or "
                                                "gaussian-avatars), from any version of the SDK"),
    output: Path = typer.Option(None, "-o", "--output", help="checkpoint to write [default: CHECKPOINT, in place]"),
    replace: bool = typer.Option(False, "--replace", help="replace an audio model attached already"),
    bundle: Path = typer.Option(None, "--bundle", help="also export the checkpoint to this bundle (gt-export's "
                                "defaults; run gt-export for other settings)"),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="no progress bar"),
) -> None:
    """Attach the built-in voice driver to an imported speaker, so audio drives it (docs/voice.md)."""
    from gaussiantalker.exporter.voice.attach import attach_builtin_voice

    try:
        written = attach_builtin_voice(checkpoint, output, replace=replace)
    except GaussianTalkerError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None
    typer.echo(f"built-in voice driver attached: {written}")
    if bundle is None:
        typer.echo(f"next: gt-export {written} --verify")
        return
    from gaussiantalker.exporter.export.bundle_export import export_bundle
    from gaussiantalker.exporter.export.checkpoint import load_checkpoint

    try:
        result = export_bundle(load_checkpoint(written), bundle, progress=not quiet)
    except GaussianTalkerError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None
    typer.echo(f"bundle: {bundle} ({result.bytes_written / 1e6:.1f} MB); audio drives it: "
               f"TalkingHead({str(bundle)!r}).frames(audio)")


def _check_voice_options(audio_model: Path | None, no_voice: bool) -> None:
    """--audio-model and --no-voice contradict each other."""
    if audio_model is not None and no_voice:
        raise typer.BadParameter("give --audio-model (attach that model) or --no-voice (attach none), not both")


def _check_camera(camera: str) -> None:
    """--camera names a framing."""
    from gaussiantalker.exporter.imports.portrait import CAMERA_CHOICES

    if camera not in CAMERA_CHOICES:
        raise typer.BadParameter(f"--camera must be one of {', '.join(CAMERA_CHOICES)}, got {camera!r}")


def _attached(audio_model: Path | None, model: bytes | None) -> str:
    """What the import line says of the attached audio model."""
    if model is None:
        return ", no audio model (--no-voice)"
    return f", audio model {audio_model.name} attached" if audio_model is not None else \
        ", built-in voice driver attached"


@app.command("flame")
def flame(
    model: Path = typer.Argument(..., help="FLAME's model pickle: generic_model.pkl (FLAME 2020), flame2023.pkl "
                                           "(FLAME 2023); read without running anything from it"),
    output: Path = typer.Option(None, "-o", "--output", help="npz to write [default: MODEL with .npz]"),
    flame_version: str = typer.Option(None, "--flame-version", help="the FLAME release to record "
                                      "[default: from the file name, as the FLAME site ships it]"),
) -> None:
    """Convert FLAME's pickle to the SDK's FLAME npz (standard keys, no pickles; docs/import.md)."""
    from gaussiantalker.exporter.imports.formats.flame_pkl import convert_flame_pkl

    output = output or model.with_suffix(".npz")
    try:
        result = convert_flame_pkl(model, output, version=flame_version)
    except GaussianTalkerError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None
    typer.echo(f"FLAME {result.version}: {result.n_vertices} vertices, {result.n_faces} faces, {result.n_shape} shape "
               f"+ {result.n_expr} expression columns in {result.seconds:.1f} s")
    typer.echo(f"npz: {result.output} (read by exporter.model.flame_npz.load_flame_npz)")


def main() -> None:
    """Console-script entry point."""
    app(prog_name="gt-import")


if __name__ == "__main__":
    sys.exit(main())
