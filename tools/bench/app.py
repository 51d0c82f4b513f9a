"""`gt-bench`: the benchmarks, one subcommand each, every subcommand with only its own options.

    gt-bench frames        per-stage timings and FPS of the runtime vs the torch reference (bench/frames.py)
    gt-bench sweep         every speed/accuracy knob alone and every preset side by side (bench/sweep.py)
    gt-bench compare       this SDK against another checkout of it, alternating rounds (bench/compare.py)
    gt-bench composite     compositing's cost and seam quality (bench/composite_cost.py)
    gt-bench backends      onnxruntime vs MNN (bench/backends.py)
    gt-bench renderers     the CPU tile splatter vs the GL splatter, alternating (bench/renderers.py)
    gt-bench video         the encoding cost of every video output (bench/video_outputs.py)
    gt-bench clip-codecs   how to store a reference clip (bench/clip_codecs.py)
    gt-bench clip-crf      the reference clip's codec knob: bytes against PSNR, presets' whole files (bench/clip_crf.py)
    gt-bench surface       how opaque a head's surface is from around it (bench/surface.py)
    gt-bench early-stop    the GL splatter's early stop of saturated pixels against the plain draw
                           (bench/early_stop.py)
    gt-bench lam-web       ground-truth frames of a LAM avatar from the original web renderer (bench/lam_web.py)
    gt-bench avatar        an imported LAM or GaussianAvatars avatar: import, export, verify, presets' quality,
                           FPS (bench/avatar.py)
    gt-bench live          live sessions: first-frame latency, agreement with offline frames, barge-in, drift,
                           sessions per process (bench/live_sessions.py)
    gt-bench live-clients  client-render live sessions under load (gt-serve, tokens on; beside an older server
                           with --baseline-server): late frames, server CPU, first-frame and barge-in latency per
                           number of clients (bench/live_clients.py)
    gt-bench serve-attacks the threat model's attacks on gt-serve (beside an older server with --baseline-server):
                           held or broke, with what each observed (bench/serve_attacks.py)
    gt-bench batch         gt-render's engines: seconds of video per second for 1, 2 local workers and Ray
                           actors, a long clip split and whole (bench/batch_rate.py)
    gt-bench voice         every audio driver (the built-in ARKit and FLAME voices, a bundle's translator) on every
                           family of voice and on real human speech: lip closure, channels, jaw, lag
                           (bench/voice_gates.py)
    gt-bench pipeline      the pipelined frame loop against the serial one on the CPU splatter, alternating
                           (bench/pipeline_vs_serial.py)
    gt-bench blend-limit   the CPU splatter's blend: its work counts and time per fragment against the same
                           kernel at full occupancy (bench/blend_limit.py)
    gt-bench framing       imported avatars' head box in the frame, source camera against portrait framing
                           (bench/framing.py)
    gt-bench codings       what each coding of a speaker's per-Gaussian buffers would cost in bytes and head
                           PSNR, before the bundle format has it (bench/codings.py)
    gt-bench translator-stream  a speaker's Motion Translator streamed against its windowed live calls and offline
                           drive on unseen speech, and a session-frame's cost each way (bench/translator_stream.py)
    gt-bench stream-calls  a streaming translator call's cost per sessions and frames a call, bundles side by side
                           (bench/stream_calls.py)
    gt-bench live-pool     the CPU a live server's pool spends a session-second, on a fake clock without sockets,
                           beside an older checkout (bench/live_pool.py)
    gt-bench voice-pushes  the CPU a live server's event loop spends pushing its own voices at real time, beside an
                           older checkout (bench/voice_pushes.py)

The flags of the single command before these subcommands (`--sweep`, `--baseline`, `--composite`, `--backends`)
still work: `gaussiantalker.cli.bench` rewrites them to their subcommand.
"""

from __future__ import annotations

import json
import shlex
import sys
from collections.abc import Callable
from pathlib import Path

import typer

from .frames import machine_info

app = typer.Typer(add_completion=False, no_args_is_help=True, help="Benchmarks of the runtime against the torch "
                  "reference, the speed/accuracy knobs, another checkout, compositing, graph backends and video "
                  "outputs.")

SIZES_HELP = "square resolutions to bench"


def _command() -> str:
    """The command line this bench runs under, as a user types it (what every report names)."""
    return shlex.join(["gt-bench", *sys.argv[1:]])


def _stamp(result: dict) -> dict:
    """`result` with the machine it ran on and its command line."""
    result["machine"], result["command"] = machine_info(), _command()
    return result


def _numbers(text: str, convert: Callable[[str], float], option: str) -> list:
    """Option `option`'s comma-separated numbers (`convert`: int or float); BadParameter naming it otherwise."""
    try:
        return [convert(v) for v in text.split(",") if v.strip()]
    except ValueError:
        kind = "whole numbers" if convert is int else "numbers"
        raise typer.BadParameter(f"comma-separated {kind} expected, got {text!r}", param_hint=option) from None


@app.command()
def frames(
    checkpoint: Path = typer.Option(None, "--checkpoint", help="speaker checkpoint [default: untrained demo]"),
    gaussians: int = typer.Option(20_000, "--gaussians", help="demo speaker size when no checkpoint is given"),
    sizes: str = typer.Option("256,512", "--sizes", help=SIZES_HELP),
    seconds: float = typer.Option(6.0, "--seconds", help="audio length driven through the runtime"),
    torch_frames: int = typer.Option(3, "--torch-frames", help="frames rendered by the torch reference"),
    paper_translator: bool = typer.Option(False, "--paper-translator", help="also export/run the ~300M translator"),
    json_path: Path = typer.Option(None, "--json", help="write results as JSON"),
) -> None:
    """Per-stage timings and FPS of the runtime vs the torch reference (what a bare `gt-bench` runs)."""
    from .frames import run_frames_bench

    run_frames_bench(checkpoint, gaussians, sizes, seconds, torch_frames, paper_translator, json_path)


@app.command()
def renderers(
    gaussians: str = typer.Option("20000,100000", "--gaussians", help="demo speaker sizes (comma-separated; empty: "
                                  "only --play)"),
    sizes: str = typer.Option("256,512,1024", "--sizes", help=SIZES_HELP),
    frames: int = typer.Option(10, "--frames", min=1, help="draws per splatter per round"),
    rounds: int = typer.Option(3, "--rounds", min=1, help="alternating rounds"),
    threads: str = typer.Option("1,2", "--threads", help="CPU splatter thread counts (comma-separated)"),
    json_path: Path = typer.Option(None, "--json", help="write results as JSON"),
    play: Path = typer.Option(None, "--play", help="a bundle: also time audio -> pixels and samples/play.py on the "
                              "sample speech with each renderer"),
    play_size: int = typer.Option(512, "--play-size", min=16, help="--play's bare frame size"),
    play_rounds: int = typer.Option(3, "--play-rounds", min=1, help="--play's alternating rounds"),
) -> None:
    """The CPU tile splatter vs the GL splatter: splat-time medians and ratios, alternating (the cpu extra)."""
    from .renderers import run_play_bench, run_renderers_bench

    if play is not None and not play.is_file():
        raise typer.BadParameter(f"{play}: no such bundle", param_hint="--play")
    results = run_renderers_bench(gaussians, sizes, frames, rounds, threads) if gaussians else {}
    if play is not None:
        results["play"] = run_play_bench(play, ["gl", "cpu"], play_size, play_rounds)
        typer.echo(json.dumps(results["play"], indent=2))
    if json_path is not None:
        json_path.write_text(json.dumps(results, indent=2))
        typer.echo(f"wrote {json_path}")


@app.command()
def sweep(
    checkpoint: Path = typer.Option(None, "--checkpoint", help="speaker checkpoint [default: the demo speaker, "
                                    "its translator trained for a few minutes]"),
    gaussians: int = typer.Option(20_000, "--gaussians", help="demo speaker size when no checkpoint is given"),
    sweep_gaussians: int = typer.Option(100_000, "--sweep-gaussians", min=0, help="size of the synthetic speaker "
                                        "(0: demo speaker only)"),
    skip_demo: bool = typer.Option(False, "--skip-demo", help="the synthetic speaker only (each speaker can then "
                                   "get its own --seconds and --rounds)"),
    cases: str = typer.Option(None, "--cases", help="only the cases whose name or knob contains one of these "
                              "comma-separated words, e.g. 'preset,sort' [default: all]"),
    scene: Path = typer.Option(None, "--scene", help="each preset plain and specialised for this scene file "
                               "(docs/scene.md), side by side (use --sizes at the scene's resolution)"),
    sizes: str = typer.Option("256,512", "--sizes", help=SIZES_HELP),
    seconds: float = typer.Option(6.0, "--seconds", help="audio length of each case"),
    rounds: int = typer.Option(3, "--rounds", min=1, help="alternating rounds per case"),
    out: Path = typer.Option(Path("bench-sweep"), "--out", help="folder for sweep.md, sweep.json and sweep.png"),
    renderers: str = typer.Option("gl", "--renderers", help="the splatters each case is drawn with, side by side in "
                                  "the same rounds (comma-separated: gl, cpu); each gets its own tables"),
) -> None:
    """Every speed/accuracy knob alone and every preset side by side (alternating rounds) on the demo speaker and
    a larger synthetic one."""
    if skip_demo and sweep_gaussians == 0:
        raise typer.BadParameter("--skip-demo needs a synthetic speaker (--sweep-gaussians > 0)",
                                 param_hint="--skip-demo")
    chosen_renderers = tuple(dict.fromkeys(name.strip() for name in renderers.split(",") if name.strip()))
    if not chosen_renderers or not set(chosen_renderers) <= {"gl", "cpu"}:
        raise typer.BadParameter(f"renderers must be gl, cpu or both (comma-separated), got {renderers!r}",
                                 param_hint="--renderers")
    _sweep(checkpoint, gaussians, sweep_gaussians, sizes, seconds, rounds, cases, out, skip_demo, scene,
           chosen_renderers)


@app.command()
def compare(
    baseline: Path = typer.Option(..., "--baseline", help="another checkout of the SDK, measured side by side"),
    gaussians: int = typer.Option(20_000, "--gaussians", help="demo speaker size"),
    sizes: str = typer.Option("256,512", "--sizes", help=SIZES_HELP),
    seconds: float = typer.Option(6.0, "--seconds", help="audio length driven through each version"),
    rounds: int = typer.Option(3, "--rounds", min=1, help="rounds per version and case"),
    scaling: str = typer.Option(None, "--scaling", help="Gaussian counts to compare at the largest size, e.g. "
                                "20000,50000,100000,200000 [default: --gaussians only]"),
    play_seconds: float = typer.Option(10.0, "--play-seconds", help="audio length for timing each version's "
                                       "samples/play.py at 512x512 (0: skip)"),
    json_path: Path = typer.Option(None, "--json", help="write results as JSON"),
) -> None:
    """This SDK and another checkout of it (--baseline), alternating rounds: the per-stage table with speed-ups."""
    _compare_with_baseline(baseline, gaussians, sizes, seconds, rounds, scaling, play_seconds, json_path)


@app.command()
def composite(
    checkpoint: Path = typer.Option(..., "--checkpoint", help="a speaker with a reference clip"),
    bundle: Path = typer.Option(None, "--bundle", help="its exported bundle (default: exported afresh)"),
    seconds: float = typer.Option(6.0, "--seconds", help="audio per FPS case"),
    rounds: int = typer.Option(3, "--rounds", min=1, help="alternating rounds"),
    pairs: int = typer.Option(12, "--pairs", min=1, help="re-rendered frames for the seam measure"),
    codecs: str = typer.Option(None, "--codecs", help="F codecs to measure, comma-separated (the first is the "
                               "reference; empty: none; default: bench/composite_cost.py's F_CODECS)"),
    out: Path = typer.Option(Path("bench-sweep"), "--out", help="folder for composite.md"),
) -> None:
    """Compositing into the reference clip: FPS composited and bare at the clip's size and 512x512, F's cost and
    codecs, seam steps (docs/compositing.md)."""
    from .composite_cost import F_CODECS, run_composite_bench

    chosen = F_CODECS if codecs is None else tuple(c.strip() for c in codecs.split(",") if c.strip())
    typer.echo(run_composite_bench(checkpoint, bundle, seconds, rounds, pairs, out / "composite.md", chosen))


@app.command()
def backends(
    checkpoint: Path = typer.Option(..., "--checkpoint", help="speaker checkpoint (exported here with --mnn)"),
    sizes: str = typer.Option("256,512", "--sizes", help="square resolutions; the largest is benched"),
    seconds: float = typer.Option(6.0, "--seconds", help="audio length of each case"),
    rounds: int = typer.Option(3, "--rounds", min=1, help="alternating rounds"),
    out: Path = typer.Option(Path("bench-sweep"), "--out", help="folder for backends.md"),
) -> None:
    """onnxruntime vs MNN: each graph's ms, stages and FPS, alternating (docs/mnn.md)."""
    from .backends import run_backends_bench

    run_backends_bench(checkpoint, max(int(s) for s in sizes.split(",")), seconds, rounds, out / "backends.md")


@app.command()
def video(
    bundle: Path = typer.Argument(..., help="speaker bundle"),
    size: int = typer.Option(512, "--size", help="frame side"),
    frames: int = typer.Option(50, "--frames", help="frames per encode"),
    rounds: int = typer.Option(3, "--rounds", min=1, help="alternating rounds"),
) -> None:
    """The encoding cost of every video output (docs/video.md) for BUNDLE's frames at SIZE x SIZE."""
    from .video_outputs import run_video_bench

    run_video_bench(bundle, size, frames, rounds)


@app.command("clip-codecs")
def clip_codecs(checkpoint: Path = typer.Argument(Path("out/speaker.ckpt"), help="a speaker with a reference clip")
                ) -> None:
    """Size and decode time of candidate reference-clip codecs on the speaker's clip (docs/compositing.md)."""
    from .clip_codecs import run_clip_codecs_bench

    run_clip_codecs_bench(checkpoint)


@app.command("early-stop")
def early_stop(
    gaussians: str = typer.Option("20000,100000", "--gaussians", help="demo speaker sizes (untrained)"),
    sizes: str = typer.Option("256,512", "--sizes", help=SIZES_HELP),
    settings: str = typer.Option("0.5;0.3,0.6;0.4,0.6,0.8", "--settings",
                                 help="early-stop settings to compare with the plain draw: ';' between settings, "
                                      "',' between a setting's fractions"),
    frames: int = typer.Option(30, "--frames", min=1, help="frames per setting and round"),
    rounds: int = typer.Option(3, "--rounds", min=1, help="alternating rounds"),
    json_path: Path = typer.Option(None, "--json", help="write the results here"),
) -> None:
    """Saturated pixels after each fraction of the sorted Gaussians, and the early stop's agreement with and speed
    against the plain draw (docs/numerics.md, "Early stop of saturated pixels")."""
    from gaussiantalker.exporter.demo.demo_speaker import make_demo_speaker

    from .early_stop import early_stop_tables, run_early_stop_bench

    try:
        choices = [tuple(float(f) for f in part.split(",")) for part in settings.split(";") if part.strip()]
    except ValueError:
        raise typer.BadParameter(f"not fractions: {settings!r}", param_hint="--settings") from None
    results = {"machine": machine_info(), "speakers": []}
    for n in (int(g) for g in gaussians.split(",")):
        speaker, _ = make_demo_speaker(n, train_seconds=0, progress=False)
        result = run_early_stop_bench(speaker, tuple(int(s) for s in sizes.split(",")), choices, frames, rounds)
        results["speakers"].append(result)
        typer.echo(early_stop_tables(result) + "\n")
    if json_path is not None:
        json_path.write_text(json.dumps(results, indent=2))
        typer.echo(f"wrote {json_path}")


@app.command()
def surface(
    checkpoint: Path = typer.Option(None, "--checkpoint", help="a FLAME speaker checkpoint [default: the demo head, "
                                    "untrained]"),
    gaussians: int = typer.Option(20_000, "--gaussians", help="demo speaker size when no checkpoint is given"),
    resolution: int = typer.Option(160, "--resolution", min=32, help="square size of the torch reference frames"),
    out: Path = typer.Option(None, "--out", help="folder for surface.md and surface.json"),
) -> None:
    """How opaque the head's surface is from yaw -90 to 90 degrees: how much of its hidden half shows through, how
    many pixels saturate, how many Gaussians a pixel blends (docs/demo-speaker.md, "Surface")."""
    from gaussiantalker.exporter.demo.demo_speaker import make_demo_speaker
    from gaussiantalker.exporter.export.checkpoint import load_checkpoint
    from gaussiantalker.exporter.model.speaker import Speaker

    from .surface import measure_surface, surface_table

    if checkpoint is None:
        speaker, _ = make_demo_speaker(gaussians, train_seconds=0, progress=False)
    else:
        speaker = load_checkpoint(checkpoint)
        if not isinstance(speaker, Speaker):
            raise typer.BadParameter("the surface measure needs a FLAME speaker (triangle-bound Gaussians)",
                                     param_hint="--checkpoint")
    views = measure_surface(speaker, resolution=resolution)
    table = surface_table(views)
    typer.echo(table)
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        source = str(checkpoint) if checkpoint else f"demo head, {gaussians} Gaussians"
        (out / "surface.md").write_text(f"# Surface of {source} at {resolution}x{resolution}\n\n{table}\n")
        (out / "surface.json").write_text(json.dumps({"machine": machine_info(), "source": source,
                                                      "resolution": resolution,
                                                      "views": [v.to_dict() for v in views]}, indent=2))
        typer.echo(f"wrote {out / 'surface.md'}")


@app.command("clip-crf")
def clip_crf(
    checkpoint: Path = typer.Option(..., "--checkpoint", help="a speaker with a reference clip"),
    crfs: str = typer.Option(None, "--crfs", help="x264 CRFs of the clip to measure against the clip as stored, "
                             "comma-separated [default: bench/clip_crf.py's CLIP_CRFS, 18,23,28,33]"),
    codings: str = typer.Option("", "--codings", help="more clip settings to measure, as gt-export "
                                "--reference-codec takes them, separated by ';' (e.g. 'crf:20,gop:25;crf:33,gop:25,"
                                "mask-crf:24')"),
    presets: str = typer.Option(None, "--presets", help="presets whose whole files to compare, comma-separated "
                                "(the first is the reference; empty: none) [default: all, quality first]"),
    seconds: float = typer.Option(6.0, "--seconds", help="audio played through each bundle"),
    out: Path = typer.Option(Path("bench-sweep"), "--out", help="folder for clip-crf.md"),
) -> None:
    """The reference clip's codec knob (`gt-export --reference-codec`): clip and bundle bytes against the PSNR of
    the clip and of the composited frames; the presets' whole-file sizes (docs/compositing.md)."""
    from gaussiantalker.exporter.export.presets import PRESETS, parse_reference
    from gaussiantalker.sdk.errors import BundleError

    from .clip_crf import CLIP_CRFS, run_clip_crf_bench

    try:
        crf_values = CLIP_CRFS if crfs is None else tuple(int(c) for c in crfs.split(",") if c.strip())
    except ValueError:
        raise typer.BadParameter(f"--crfs must be integers, got {crfs!r}", param_hint="--crfs") from None
    chosen = tuple(PRESETS) if presets is None else tuple(p.strip() for p in presets.split(",") if p.strip())
    unknown = [p for p in chosen if p not in PRESETS]
    if unknown:
        raise typer.BadParameter(f"unknown preset(s) {unknown} (known: {', '.join(PRESETS)})", param_hint="--presets")
    coding_values = tuple(c.strip() for c in codings.split(";") if c.strip())
    for coding in coding_values:
        try:
            parse_reference(coding)
        except BundleError as exc:
            raise typer.BadParameter(str(exc), param_hint="--codings") from None
    typer.echo(run_clip_crf_bench(checkpoint, crf_values, chosen, seconds, out / "clip-crf.md",
                                  codings=coding_values))


@app.command("lam-web")
def lam_web(
    avatar: Path = typer.Argument(None, help="a LAM avatar zip (one folder: skin.glb, animation.glb, offset.ply, "
                                  "vertex_order.json)"),
    motion: Path = typer.Option(None, "--motion", help="motion JSON {names, frames: [{weights}]} [default: the "
                                "neutral face, all weights 0]"),
    frames: str = typer.Option("0", "--frames", help="comma-separated motion frame indexes"),
    size: int = typer.Option(512, "--size", min=1, help="frame side"),
    camera: Path = typer.Option(None, "--camera", help="camera JSON (Camera.to_dict()) [default: the renderer's "
                                "own camera]"),
    background: str = typer.Option("1,1,1", "--background", help="background r,g,b in 0..1"),
    out: Path = typer.Option(Path("out/lam-web"), "-o", "--out", help="folder for web_{frame}.png, cameras.json, "
                             "weights.json"),
    cache: Path = typer.Option(None, "--cache", help="npm cache folder [default: $GT_LAM_WEB_CACHE or "
                               "~/.cache/gaussiantalker/lam-web]"),
    install: bool = typer.Option(False, "--install", help="first install the npm renderer and Debian's chromium"),
    compare: Path = typer.Option(None, "--compare", help="a bundle of the same avatar (gt-import lam + gt-export): "
                                 "draw the same frames with the runtime and write their PSNR (compare.json)"),
) -> None:
    """Frames of AVATAR drawn by the original LAM web renderer in headless Chromium (docs/lam-web.md)."""
    from gaussiantalker.sdk.camera import Camera

    from .lam_web import LamWebMissing
    from .lam_web import install as install_lam_web
    from .lam_web_run import run_lam_web

    if install:
        typer.echo(f"installed the renderer in {install_lam_web(cache)}")
    if avatar is None:
        if not install:
            raise typer.BadParameter("give an avatar zip (or --install)", param_hint="AVATAR")
        return
    rgb = tuple(float(c) for c in background.split(","))
    if len(rgb) != 3:
        raise typer.BadParameter("three numbers: r,g,b", param_hint="--background")
    view = Camera.from_dict(json.loads(camera.read_text())) if camera is not None else None
    try:
        run_lam_web(avatar, out, motion, frames, size, rgb, view, cache, echo=typer.echo, compare=compare)
    except (LamWebMissing, ValueError) as exc:
        typer.echo(f"gt-bench lam-web: {exc}", err=True)
        raise typer.Exit(2) from exc


@app.command()
def avatar(
    avatar_path: Path = typer.Argument(..., metavar="AVATAR", help="a LAM avatar zip, or a GaussianAvatars output "
                                       "directory with --flame (docs/import.md)"),
    flame: Path = typer.Option(None, "--flame", help="the FLAME model (.pkl or .npz) a GaussianAvatars avatar is "
                               "imported with (gt-import gaussian-avatars --flame)"),
    motion: Path = typer.Option(None, "--motion", help="motion played for quality and FPS: an ARKit motion file for "
                                "a LAM avatar, a FLAME motion npz for a GaussianAvatars one [default: the avatar's "
                                "own motion track, else random ARKit drives]"),
    frames: int = typer.Option(30, "--frames", min=1, help="frames sampled evenly from the motion for quality"),
    fps_seconds: float = typer.Option(4.0, "--fps-seconds", min=0.1, help="seconds of frames per FPS run"),
    rounds: int = typer.Option(3, "--rounds", min=1, help="alternating FPS rounds"),
    demo_checkpoint: Path = typer.Option(None, "--demo-checkpoint", help="the demo speaker played beside the avatar "
                                         "(samples/make_demo_speaker.py) [default: an untrained one built here]"),
    demo_bundle: Path = typer.Option(None, "--demo-bundle", help="the demo speaker's exported fp32 bundle played "
                                     "beside the avatar instead of one exported here (gt-export out/speaker.ckpt)"),
    gaussians: int = typer.Option(20_000, "--gaussians", min=1, help="demo speaker size when no checkpoint is given"),
    note: str = typer.Option(None, "--note", help="a line about the machine or the run, written into avatar.md"),
    out: Path = typer.Option(Path("bench-avatar"), "--out", help="folder for avatar.md and avatar.json"),
    presets: str = typer.Option(None, "--presets", help="comma-separated presets to export and compare, quality "
                                "among them [default: all]"),
    verify_frames: int = typer.Option(25, "--verify-frames", min=0, help="frames verify_bundle compares against the "
                                      "torch speaker (its 6 novel views come on top); 0: no verify"),
    variant: list[str] = typer.Option(None, "--variant", help="LABEL=PRESET:key=value,...: the preset's bundle "
                                      "played with these TalkingHead settings (render_scale, render_target, "
                                      "sort_interval, sort_key_bits, alpha_min, transmittance_min, max_draw_pixels, "
                                      "threads) beside the presets, in quality and FPS; repeatable"),
) -> None:
    """An imported LAM or GaussianAvatars avatar: import, preset export and verify times, bundle sizes, each preset's
    head PSNR against fp32, and FPS at 512x512 beside the demo speaker (alternating rounds)."""

    from gaussiantalker.sdk.errors import GaussianTalkerError

    from .avatar import Variant, check_variants, format_report, run_avatar_bench

    if avatar_path.is_dir() and flame is None:
        raise typer.BadParameter(f"{avatar_path} is a directory: a GaussianAvatars avatar, which needs its FLAME "
                                 "model (--flame FLAME.pkl|npz)", param_hint="--flame")
    if flame is not None and not avatar_path.is_dir():
        raise typer.BadParameter(f"{avatar_path}: --flame is for a GaussianAvatars output directory, and this is no "
                                 "directory", param_hint="AVATAR")
    from gaussiantalker.exporter.export.presets import PRESETS

    chosen = None if presets is None else [name.strip() for name in presets.split(",") if name.strip()]
    if chosen is not None and ("quality" not in chosen or set(chosen) - set(PRESETS)):
        raise typer.BadParameter(f"{presets!r}: presets among {', '.join(PRESETS)}, quality (the reference) "
                                 "among them", param_hint="--presets")
    try:
        variants = [Variant.parse(text) for text in variant or []]
        check_variants(variants, chosen or list(PRESETS))
    except ValueError as exc:
        raise typer.BadParameter(str(exc), param_hint="--variant") from None
    if demo_checkpoint is not None and demo_bundle is not None:
        raise typer.BadParameter("give the demo speaker once: --demo-checkpoint (exported here) or --demo-bundle",
                                 param_hint="--demo-bundle")
    files = [(motion, "--motion"), (demo_checkpoint, "--demo-checkpoint"), (demo_bundle, "--demo-bundle"),
             (flame, "--flame")]
    if flame is None:
        files.insert(0, (avatar_path, "AVATAR"))  # a LAM zip; a GaussianAvatars directory was checked above
    for path, hint in files:
        if path is not None and not path.is_file():
            raise typer.BadParameter(f"{path}: no such file", param_hint=hint)
    command = _command()
    try:
        result = run_avatar_bench(avatar_path, motion, frames, fps_seconds, rounds, demo_checkpoint, gaussians, out,
                                  command, note, flame, chosen, verify_frames, variants, demo_bundle)
    except GaussianTalkerError as exc:  # a damaged avatar, FLAME model or motion file: its message, not a traceback
        typer.echo(f"gt-bench avatar: {exc}", err=True)
        raise typer.Exit(2) from None
    typer.echo(format_report(result))
    typer.echo(f"wrote {out / 'avatar.md'}, {out / 'avatar.json'}")


@app.command()
def live(
    bundle: Path = typer.Argument(..., help="a speaker bundle with a translator (.gtb)"),
    size: int = typer.Option(512, "--size", min=16, help="square frame size of the latency and barge-in runs"),
    lookaheads: str = typer.Option("0,80,160,320", "--lookaheads", help="lookaheads to measure (ms)"),
    utterances: int = typer.Option(10, "--utterances", min=1, help="utterances per lookahead for the latency"),
    barge_trials: int = typer.Option(5, "--barge-trials", min=1, help="interrupt() trials"),
    drift_minutes: float = typer.Option(60.0, "--drift-minutes", min=0.0, help="minutes of the drift run (0: none)"),
    session_sizes: str = typer.Option("512,256", "--session-sizes", help="frame sizes of the sessions run"),
    most_sessions: int = typer.Option(8, "--most-sessions", min=1, help="largest session count tried"),
    renderer: str = typer.Option("gl", "--renderer", help="what splats: gl, cpu or auto (docs/embedding.md)"),
    out: Path = typer.Option(None, "--out", help="folder for live.md and live.json"),
) -> None:
    """Live sessions (docs/live.md): first-frame latency p50/p95 per lookahead (paced, real-time pushes), jaw
    agreement with offline frames, barge-in time, drift over a long free-running session, sessions sustained."""

    from .live_sessions import live_tables, run_live_bench

    if not bundle.is_file():
        raise typer.BadParameter(f"{bundle}: no such file", param_hint="BUNDLE")
    chosen, sizes = _numbers(lookaheads, float, "--lookaheads"), _numbers(session_sizes, int, "--session-sizes")
    result = run_live_bench(bundle, size, chosen, utterances, barge_trials, drift_minutes, sizes, most_sessions,
                            renderer)
    _stamp(result)
    tables = live_tables(result)
    typer.echo(tables)
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        (out / "live.json").write_text(json.dumps(result, indent=2))
        (out / "live.md").write_text(f"# Live sessions\n\n`{result['command']}` on {result['machine']['cpu']}, "
                                     f"{result['machine']['cores']} cores, {result['machine']['gl']}; splatted by the "
                                     f"{result['renderer']} renderer.\n\n{tables}\n")
        typer.echo(f"wrote {out / 'live.md'}, {out / 'live.json'}")


@app.command()
def pipeline(
    bundle: Path = typer.Argument(..., help="a speaker bundle with a translator and a reference clip (.gtb)"),
    audio: Path = typer.Option(Path("samples/demo_speech.wav"), "--audio", help="speech to render"),
    seconds: float = typer.Option(0.0, "--seconds", min=0.0, help="the first seconds of the audio (0: all)"),
    size: int = typer.Option(512, "--size", min=16, help="square frame size of the bare-head cases"),
    rounds: int = typer.Option(3, "--rounds", min=1, help="rounds per case and variant"),
    cases: str = typer.Option("frames,frames-composite,play,play-composite", "--cases",
                              help="what to time: frames, frames-composite, play, play-composite"),
    before: Path = typer.Option(None, "--before", help="another checkout of the SDK, timed as it is (\"before\")"),
    out: Path = typer.Option(None, "--out", help="folder for pipeline.md and pipeline.json"),
) -> None:
    """The pipelined frame loop against the serial one and, with --before, another checkout, on the CPU tile
    splatter, alternating rounds (bench/pipeline_vs_serial.py)."""

    from .pipeline_vs_serial import bench_pipeline, format_report

    if not bundle.is_file():
        raise typer.BadParameter(f"{bundle}: no such file", param_hint="BUNDLE")
    result = bench_pipeline(bundle.resolve(), audio=audio.resolve(), seconds=seconds, size=size, rounds=rounds,
                            cases=[c.strip() for c in cases.split(",") if c.strip()],
                            baseline=before)
    _stamp(result)
    report = format_report(result, result["machine"], result["command"])
    typer.echo(report)
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        (out / "pipeline.json").write_text(json.dumps(result, indent=2))
        (out / "pipeline.md").write_text(report)
        typer.echo(f"wrote {out / 'pipeline.md'}, {out / 'pipeline.json'}")


def _write_report(out: Path | None, name: str, title: str, result: dict, table: str, details: str) -> None:
    """`name`.json (the result) and `name`.md (the title, the command and machine, `details`, the table) in `out`
    (nothing when it is None)."""
    if out is None:
        return
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{name}.json").write_text(json.dumps(result, indent=2))
    (out / f"{name}.md").write_text(f"# {title}\n\n`{result['command']}` on {result['machine']['cpu']}, "
                                    f"{result['machine']['cores']} cores{details}\n\n{table}\n")
    typer.echo(f"wrote {out / f'{name}.md'}, {out / f'{name}.json'}")


def _publish(result: dict, table_of: Callable[[dict], str], out: Path | None, name: str, title: str,
             details: str) -> None:
    """Stamp `result` with its machine and command, print its table and write the report (`_write_report`)."""
    _stamp(result)
    table = table_of(result)
    typer.echo(table)
    _write_report(out, name, title, result, table, details)


@app.command("live-batching")
def live_batching(
    bundle: Path = typer.Argument(..., help="a speaker bundle with a translator (.gtb)"),
    audio: Path = typer.Option(Path("samples/demo_speech.wav"), "--audio", help="the voice"),
    batch_frames: str = typer.Option("1,4,8", "--batch-frames", help="comma-separated K (min_batch_frames)"),
    seconds: float = typer.Option(8.0, "--seconds", min=1.0, help="seconds of the voice"),
    rounds: int = typer.Option(3, "--rounds", min=1, help="alternating rounds (CPU: their median)"),
    context_ms: float = typer.Option(1000.0, "--context-ms", min=0.0, help="the translator's past context"),
    stream: bool = typer.Option(False, "--stream", help="also the bundle's streaming translator (docs/live.md)"),
    lookahead_ms: str = typer.Option("160", "--lookahead-ms", help="comma-separated lookaheads (ms)"),
    out: Path = typer.Option(None, "--out", help="folder for live-batching.md and live-batching.json"),
) -> None:
    """Live sessions' translator calls, CPU per second of speech and drive accuracy per min_batch_frames (and the
    streaming translator with --stream) and lookahead, with a voice pushed in 20 ms chunks (docs/live.md)."""

    from .live_batching import live_batching_table, run_live_batching

    batches = _numbers(batch_frames, int, "--batch-frames")
    lookaheads = _numbers(lookahead_ms, float, "--lookahead-ms")
    if not batches or not all(1 <= b <= 8 for b in batches):
        raise typer.BadParameter("whole numbers in 1..8", param_hint="--batch-frames")
    if not lookaheads or min(lookaheads) < 0:
        raise typer.BadParameter("lookaheads >= 0 ms", param_hint="--lookahead-ms")
    try:
        result = run_live_batching(bundle, audio, batches, seconds, rounds, context_ms, stream, tuple(lookaheads))
    except ValueError as error:
        raise typer.BadParameter(str(error), param_hint="BUNDLE") from None
    _publish(result, live_batching_table, out, "live-batching", "Live sessions: the translator's calls, CPU and "
             "accuracy", f"; {result['speech_s']:g} s of speech in 20 ms chunks, free-running, one thread; {rounds} "
             "alternating rounds.")


@app.command("translator-stream")
def translator_stream(
    checkpoint: Path = typer.Argument(..., help="a speaker checkpoint with a Motion Translator (.ckpt)"),
    refresh: str = typer.Option("0,2,4", "--refresh", help="comma-separated refreshed frames to compare"),
    tail: str = typer.Option("window,5", "--tail", help="comma-separated frames the transformers run again "
                             "before a call's new ones (\"window\": the whole window, no K/V cache)"),
    batch_frames: str = typer.Option("1,8", "--batch-frames", help="comma-separated frames a call"),
    rounds: int = typer.Option(20, "--rounds", min=1, help="alternating timing rounds (medians)"),
    gated: bool = typer.Option(True, "--gated/--no-gated", help="also each refreshing stream gated as live sessions "
                               "call it: its steady graph while the window's loudness holds"),
    base_size: bool = typer.Option(False, "--base-size", help="also the cost of an untrained translator of wav2vec "
                                   "2.0 BASE's size (one session, a frame a call)"),
    out: Path = typer.Option(None, "--out", help="folder for translator-stream.md and translator-stream.json"),
) -> None:
    """A speaker's Motion Translator streamed against its windowed live calls and its offline drive on unseen
    speech, per number of refreshed frames, and what a session-frame costs each way (docs/live.md)."""
    from gaussiantalker.exporter.export.checkpoint import load_checkpoint

    from .translator_stream import run_cost, run_quality, stream_variants, translator_stream_table

    refreshes, batches = _numbers(refresh, int, "--refresh"), _numbers(batch_frames, int, "--batch-frames")
    if not refreshes or min(refreshes) < 0 or not batches or not all(1 <= b <= 8 for b in batches):
        raise typer.BadParameter("refresh >= 0 and frames a call in 1..8", param_hint="--refresh/--batch-frames")
    tails = [None if t.strip() == "window" else t for t in tail.split(",") if t.strip()]
    if not all(t is None or t.strip().isdigit() for t in tails) or not tails:
        raise typer.BadParameter(f"{tail!r}: comma-separated whole numbers or \"window\"", param_hint="--tail")
    variants = stream_variants(refreshes, [None if t is None else int(t) for t in tails], gated)
    if not variants:
        raise typer.BadParameter("no tail is long enough for these refreshes (at least refresh + 1 and the "
                                 "delay)", param_hint="--tail")
    speaker = load_checkpoint(checkpoint)
    if getattr(speaker, "translator", None) is None:
        raise typer.BadParameter(f"{checkpoint}: the speaker has no Motion Translator", param_hint="CHECKPOINT")
    cases = [(sessions, n) for sessions in (1, 100) for n in batches]
    result = {"quality": run_quality(speaker.translator, variants, batches),
              "cost": run_cost(speaker.translator, variants, cases, rounds)}
    if base_size:
        from .translator_stream import base_size_translator

        result["cost_base_size"] = run_cost(base_size_translator(), variants, [(1, 1)], max(3, rounds // 5))
    _publish(result, translator_stream_table, out, "translator-stream", "The Motion Translator streamed: quality and "
             "cost", f"; torch modules for quality, onnxruntime on one thread for cost ({rounds} alternating rounds).")


@app.command("stream-calls")
def stream_calls(
    bundles: list[Path] = typer.Argument(..., help="bundles with a streaming translator (.gtb); the first is the "
                                         "reference of the ratios"),
    sessions: str = typer.Option("1,4,12,50", "--sessions", help="comma-separated sessions stacked a call"),
    frames: str = typer.Option("1,2", "--frames", help="comma-separated frames a call (one committed, the rest "
                               "provisional)"),
    rounds: int = typer.Option(15, "--rounds", min=1, help="alternating timing rounds (medians)"),
    graph: str = typer.Option("refreshing", "--graph", help="refreshing (translator_stream) or steady (its steady "
                              "form, the speaker's own translator's calls while the loudness holds)"),
    out: Path = typer.Option(None, "--out", help="folder for stream-calls.md and stream-calls.json"),
) -> None:
    """What one call of each bundle's streaming translator graph costs, per sessions a call and frames a call, side
    by side in alternating rounds (docs/live.md, "Sessions batched together")."""
    from .stream_calls import run_stream_calls, stream_calls_table

    counts, lengths = _numbers(sessions, int, "--sessions"), _numbers(frames, int, "--frames")
    if not counts or min(counts) < 1 or max(counts) > 256 or not lengths or not all(1 <= n <= 8 for n in lengths):
        raise typer.BadParameter("sessions a call in 1..256 and frames a call in 1..8", param_hint="--sessions")
    for path in bundles:
        if not path.is_file():
            raise typer.BadParameter(f"{path}: no such bundle", param_hint="BUNDLES")
    try:
        result = run_stream_calls(bundles, [(s, n) for s in counts for n in lengths], rounds, graph=graph)
    except ValueError as exc:
        raise typer.BadParameter(str(exc), param_hint="BUNDLES") from None
    _publish(result, stream_calls_table, out, "stream-calls", "A streaming translator call's cost",
             f"; the {graph} graph, onnxruntime on one thread, {rounds} alternating rounds of 20 calls, medians.")


def _sessions_beside_checkout(sessions: str, baseline_checkout: Path | None, bundle: Path,
                              baseline_bundle: Path | None = None) -> list[int]:
    """--sessions (1..500 each) of a bench run beside an older checkout, its bundles and the checkout checked."""
    counts = _numbers(sessions, int, "--sessions")
    if not counts or min(counts) < 1 or max(counts) > 500:
        raise typer.BadParameter("sessions in 1..500", param_hint="--sessions")
    for path, hint in ((bundle, "BUNDLE"), (baseline_bundle, "--baseline-bundle")):
        if path is not None and not path.is_file():
            raise typer.BadParameter(f"{path}: no such bundle", param_hint=hint)
    if baseline_checkout is not None and not (baseline_checkout / "src" / "gaussiantalker").is_dir():
        raise typer.BadParameter(f"{baseline_checkout}: not a checkout of this project (no src/gaussiantalker)",
                                 param_hint="--baseline-checkout")
    return counts


@app.command("live-pool")
def live_pool(
    bundle: Path = typer.Argument(..., help="a bundle with a streaming translator (.gtb)"),
    sessions: str = typer.Option("50", "--sessions", help="comma-separated numbers of sessions"),
    seconds: float = typer.Option(6.0, "--seconds", min=1.0, max=120.0, help="seconds of the fake clock a run"),
    rounds: int = typer.Option(5, "--rounds", min=1, help="alternating rounds (medians)"),
    lookahead_ms: float = typer.Option(160.0, "--lookahead-ms", min=0.0, help="the sessions' lookahead"),
    baseline_checkout: Path = typer.Option(None, "--baseline-checkout", help="a checkout of an older commit "
                                           "(`git worktree add DIR COMMIT`) whose pool code runs beside this one"),
    baseline_bundle: Path = typer.Option(None, "--baseline-bundle", help="the bundle the baseline runs (e.g. the "
                                         "same speaker as its commit exports it) [default: BUNDLE]"),
    out: Path = typer.Option(None, "--out", help="folder for live-pool.md and live-pool.json"),
) -> None:
    """The CPU a live server's pool spends a session-second (the translator calls, each frame, its packet), on a
    fake clock without sockets: versions side by side within a few percent (bench/live_pool.py)."""
    from .live_pool import live_pool_table, run_live_pool

    counts = _sessions_beside_checkout(sessions, baseline_checkout, bundle, baseline_bundle)
    try:
        result = run_live_pool(bundle.resolve(), counts, seconds, rounds, lookahead_ms,
                               None if baseline_checkout is None else baseline_checkout.resolve(),
                               None if baseline_bundle is None else baseline_bundle.resolve())
    except RuntimeError as exc:
        raise typer.BadParameter(str(exc), param_hint="BUNDLE") from None
    _publish(result, live_pool_table, out, "live-pool", "A live server's pool work, without sockets",
             f"; {seconds:g} s of fake clock a run, {rounds} alternating rounds, each a fresh process, medians.")


@app.command("voice-pushes")
def voice_pushes(
    bundle: Path = typer.Argument(..., help="a bundle whose driver the sessions use (.gtb)"),
    sessions: str = typer.Option("100", "--sessions", help="comma-separated numbers of sessions"),
    seconds: float = typer.Option(5.0, "--seconds", min=1.0, max=120.0, help="seconds each voice speaks"),
    rounds: int = typer.Option(5, "--rounds", min=1, help="alternating rounds (medians)"),
    chunk_ms: float = typer.Option(20.0, "--chunk-ms", min=5.0, max=1000.0, help="the voices' chunk size"),
    baseline_checkout: Path = typer.Option(None, "--baseline-checkout", help="a checkout of an older commit "
                                           "(`git worktree add DIR COMMIT`) whose pusher runs beside this one"),
    out: Path = typer.Option(None, "--out", help="folder for voice-pushes.md and voice-pushes.json"),
) -> None:
    """The CPU a live server's event loop spends pushing its own voices at real time, versions side by side
    (bench/voice_pushes.py)."""
    from .voice_pushes import run_voice_pushes, voice_pushes_table

    counts = _sessions_beside_checkout(sessions, baseline_checkout, bundle)
    try:
        result = run_voice_pushes(bundle.resolve(), counts, seconds, rounds, chunk_ms,
                                  None if baseline_checkout is None else baseline_checkout.resolve())
    except RuntimeError as exc:
        raise typer.BadParameter(str(exc), param_hint="BUNDLE") from None
    _publish(result, voice_pushes_table, out, "voice-pushes", "A live server's own voices pushed at real time",
             f"; {seconds:g} s voices in {chunk_ms:g} ms chunks, {rounds} alternating rounds, each a fresh process, "
             "medians.")


@app.command("codings")
def codings(
    speaker: Path = typer.Argument(..., help="a LAM avatar zip (imported without its voice) or a speaker checkpoint "
                                   "(.ckpt)"),
    budgets: str = typer.Option("", "--budgets", help="comma-separated Gaussian budgets in percent to export compact "
                                "at as well (e.g. 55,75)"),
    combined_loss: float = typer.Option(None, "--combined-loss-db", min=0.0, help="the combined row takes each "
                                        "buffer's smallest coding that lost at most this much head PSNR alone "
                                        "[default: 1.5]"),
    out: Path = typer.Option(None, "--out", help="folder for codings.md and codings.json"),
) -> None:
    """What each coding of a speaker's per-Gaussian buffers (and morph basis) would cost in bytes and head PSNR
    against `quality`, before the bundle format has it (docs/precision.md)."""
    from .codings import COMBINED_LOSS_DB, codings_table, run_codings

    percents = _numbers(budgets, float, "--budgets")
    if not all(0 < p <= 100 for p in percents):
        raise typer.BadParameter("budgets are percentages in (0, 100]", param_hint="--budgets")
    if not speaker.is_file():
        raise typer.BadParameter(f"{speaker}: no such file", param_hint="SPEAKER")
    if speaker.suffix == ".ckpt":
        from gaussiantalker.exporter.export.checkpoint import load_checkpoint

        loaded = load_checkpoint(speaker)
    else:
        from gaussiantalker.exporter.imports.sources.lam import import_lam

        loaded = import_lam(speaker, progress=False)
    result = run_codings(loaded, [p / 100 for p in percents],
                         COMBINED_LOSS_DB if combined_loss is None else combined_loss)
    _publish(result, codings_table, out, "codings", "Codings of the per-Gaussian buffers: bytes against head PSNR",
             "; one buffer of `compact` coded at a time, its frames against `quality`'s (tools/bench/codings.py).")


@app.command("framing")
def framing(
    avatars: list[Path] = typer.Argument(..., help="LAM avatar zips and GaussianAvatars output folders"),
    flame: Path = typer.Option(None, "--flame", help="the FLAME model (.pkl or npz) of the GaussianAvatars folders"),
    out: Path = typer.Option(None, "--out", help="folder for framing.md, framing.json and a PNG per avatar"),
    rounds: int = typer.Option(0, "--rounds", min=0, help="alternating timing rounds of both framings' frames "
                               "(0: none)"),
) -> None:
    """Imported avatars in their bundle's frame: the source's camera against portrait framing (docs/import.md)."""
    from .framing import framing_table, run_framing

    for path in avatars:
        if not path.exists() or (path.is_dir() and flame is None):
            raise typer.BadParameter(f"{path}: no such avatar, or a GaussianAvatars folder without --flame",
                                     param_hint="AVATARS")
    result = run_framing(avatars, flame, out, rounds)
    _publish(result, framing_table, out, "framing", "Imported avatars' framing: source camera and portrait",
             "; rest pose, 512x512, the runtime's frames (PNGs: source left, portrait right); times: the "
             f"default renderer, {rounds} alternating rounds, median ms a frame.")


@app.command("web-presets")
def web_presets(
    speakers: list[str] = typer.Argument(..., help="LABEL=CHECKPOINT[:audio=WAV|:motion=FILE], one per speaker"),
    presets: str = typer.Option("quality,balanced,compact,fast,mobile", "--presets", help="export presets"),
    rounds: int = typer.Option(3, "--rounds", min=1, help="fresh pages per bundle (medians)"),
    out: Path = typer.Option(None, "--out", help="folder for web-presets.md and web-presets.json"),
) -> None:
    """Each preset's bundle bytes (the page's download) and time to the first frame in headless Chromium (load,
    drive, first frame), per speaker (docs/web.md)."""

    from .web_presets import run_web_presets, web_presets_table

    parsed = []
    for spec in speakers:
        label, _, rest = spec.partition("=")
        checkpoint, *options = rest.split(":")
        given = dict(option.split("=", 1) for option in options if "=" in option)
        if not label or not Path(checkpoint).is_file() or set(given) - {"audio", "motion"}:
            raise typer.BadParameter(f"{spec!r}: LABEL=CHECKPOINT[:audio=WAV|:motion=FILE] of an existing "
                                     "checkpoint", param_hint="SPEAKERS")
        parsed.append((label, Path(checkpoint), Path(given["audio"]) if "audio" in given else None,
                       Path(given["motion"]) if "motion" in given else None))
    result = run_web_presets(parsed, [p.strip() for p in presets.split(",") if p.strip()], rounds, log=typer.echo)
    _publish(result, web_presets_table, out, "web-presets", "Bundles for the web: download size and time to the "
             "first frame", f" (headless Chromium, SwiftShader; {result['size'][0]}x{result['size'][1]}; medians of "
             f"{rounds} fresh pages).")


@app.command("live-clients")
def live_clients(
    bundle: Path = typer.Argument(..., help="a speaker bundle with a translator (.gtb)"),
    clients: str = typer.Option("1,10,25,50,75", "--clients", help="numbers of concurrent sessions to run"),
    lookahead_ms: float = typer.Option(160.0, "--lookahead-ms", min=0.0, help="the sessions' lookahead"),
    speak_s: float = typer.Option(4.0, "--speak-s", min=0.5, help="seconds each client lets the head speak "
                                  "before it interrupts"),
    chunk_ms: str = typer.Option("20", "--chunk-ms", help="the voice's chunk sizes (ms, pushed at real time; "
                                 "comma-separated: one run each): 20 is a voice made as it is spoken"),
    transport: str = typer.Option("ws", "--transport", help="how drives and voice reach the clients "
                                  "(comma-separated: one run each): ws, one WebSocket a session; ws-deflate, one "
                                  "whose handshake asks for permessage-deflate as a browser's does; webrtc, an "
                                  "audio track and a data channel"),
    batch_frames: str = typer.Option("1", "--batch-frames", help="the server's frames per translator call at least "
                                     "(comma-separated: one run each; gt-serve --batch-frames)"),
    context_ms: float = typer.Option(1000.0, "--context-ms", min=0.0, help="the translator's past context "
                                     "(gt-serve --context-ms)"),
    baseline_server: Path = typer.Option(None, "--baseline-server", help="an older server script to run beside "
                                         "gt-serve in alternating rounds (samples/live_server.py of an earlier "
                                         "commit, e.g. `git show 49c2f1e:samples/live_server.py > FILE`)"),
    baseline_checkout: Path = typer.Option(None, "--baseline-checkout", help="a checkout of the baseline's commit "
                                           "(`git worktree add DIR COMMIT`): its src/ is what the baseline imports "
                                           "[default: the checkout the script lies in]"),
    baseline_bundle: Path = typer.Option(None, "--baseline-bundle", help="the bundle the baseline serves [default: "
                                         "BUNDLE], e.g. the same speaker as the baseline's commit exports it"),
    rounds: int = typer.Option(1, "--rounds", min=1, help="rounds per N and server (with a baseline: old, new, "
                               "old, new ...)"),
    replicas: int = typer.Option(1, "--replicas", min=1, max=8, help="gt-serve processes behind nginx "
                                 "(deploy/nginx.conf; docs/serve.md, \"Replicas behind a load balancer\"); 1: "
                                 "one process, no nginx"),
    baseline_replicas: int = typer.Option(1, "--baseline-replicas", min=1, max=8, help="the baseline's gt-serve "
                                          "processes behind nginx (a baseline that runs gt-serve)"),
    stream_delay_ms: float = typer.Option(None, "--stream-delay-ms", min=0.0, help="gt-serve's --stream-delay-ms "
                                          "(80: the short stream; the baseline runs its default)"),
    out: Path = typer.Option(None, "--out", help="folder for live-clients.md and live-clients.json"),
) -> None:
    """Client-render live sessions (gt-serve --client-render, tokens on) under N concurrent load clients: late
    drives, server CPU per session-second, first-frame and barge-in latency; the largest N with <= 5% late. With
    --baseline-server, the same against an older server script, alternating, and the ratios new / old."""
    import itertools

    from .live_clients import TRANSPORT_NAMES, live_clients_table, run_live_clients_bench

    if not bundle.is_file():
        raise typer.BadParameter(f"{bundle}: no such file", param_hint="BUNDLE")
    counts, chunks = _numbers(clients, int, "--clients"), _numbers(chunk_ms, float, "--chunk-ms")
    batches = _numbers(batch_frames, int, "--batch-frames")
    if not counts or min(counts) < 1 or not chunks or not all(10 <= c <= 10000 for c in chunks):
        raise typer.BadParameter("counts >= 1 and chunks of 10..10000 ms", param_hint="--clients/--chunk-ms")
    transports = [v.strip() for v in transport.split(",") if v.strip()]
    if not transports or not set(transports) <= {"ws", "ws-deflate", "webrtc"}:
        raise typer.BadParameter("ws, ws-deflate, webrtc or a list of them", param_hint="--transport")
    if not batches or not all(1 <= b <= 8 for b in batches):
        raise typer.BadParameter("whole numbers in 1..8", param_hint="--batch-frames")
    baseline = _live_baseline(baseline_server, baseline_checkout, baseline_bundle)
    import os

    result = {"load_at_start": os.getloadavg(), "runs": []}
    for kind, chunk, batch in itertools.product(transports, chunks, batches):
        typer.echo(f"{kind}: voice in {chunk:g} ms chunks, {batch} frames per translator call at least")
        result["runs"].append(run_live_clients_bench(bundle, counts, lookahead_ms, speak_s, chunk_ms=chunk,
                                                     log=typer.echo, transport=kind, batch_frames=batch,
                                                     context_ms=context_ms, baseline=baseline, rounds=rounds,
                                                     replicas=replicas, baseline_replicas=baseline_replicas,
                                                     stream_delay_ms=stream_delay_ms))
    result["load_at_end"] = os.getloadavg()
    _stamp(result)
    table = "\n\n".join(f"{TRANSPORT_NAMES[run['transport']]}, voice in {run['chunk_ms']:g} ms chunks at "
                         f"real time, `--batch-frames {run['batch_frames']}`, `--context-ms {run['context_ms']:g}`:"
                         f"\n\n{live_clients_table(run)}"
                         for run in result["runs"])
    typer.echo(table)
    _write_report(out, "live-clients", "Live sessions rendered by the client, under load", result, table,
                  f"; load average (1, 5, 15 min) {', '.join(f'{v:.2f}' for v in result['load_at_start'])} at the "
                  f"start, {', '.join(f'{v:.2f}' for v in result['load_at_end'])} at the end.")


@app.command("serve-attacks")
def serve_attacks(
    bundle: Path = typer.Argument(..., help="a speaker bundle with a translator (.gtb)"),
    baseline_server: Path = typer.Option(None, "--baseline-server", help="an older server script to attack as well "
                                         "(samples/live_server.py of an earlier commit, e.g. `git show "
                                         "49c2f1e:samples/live_server.py > FILE`)"),
    baseline_checkout: Path = typer.Option(None, "--baseline-checkout", help="a checkout of the baseline's commit "
                                           "(`git worktree add DIR COMMIT`): its src/ is what the baseline imports "
                                           "[default: the checkout the script lies in]"),
    out: Path = typer.Option(None, "--out", help="folder for serve-attacks.md and serve-attacks.json"),
) -> None:
    """The threat model's attacks (docs/serve.md) against gt-serve --client-render with tokens and, with
    --baseline-server, against an older server script: each attack held or broke, with what was observed."""
    from .serve_attacks import run_serve_attacks, serve_attacks_table

    if not bundle.is_file():
        raise typer.BadParameter(f"{bundle}: no such file", param_hint="BUNDLE")
    baseline = _live_baseline(baseline_server, baseline_checkout)
    result = run_serve_attacks(bundle, baseline, log=typer.echo)
    _publish(result, serve_attacks_table, out, "serve-attacks", "Attacks on the live server",
             "; each server alone on loopback, `--client-render`, gt-serve with `--secret-file`.")


@app.command("batch")
def batch(
    bundle: Path = typer.Argument(..., help="a speaker bundle with a translator (.gtb)"),
    resolution: int = typer.Option(256, "--resolution", min=16, help="square frames of every job"),
    jobs: int = typer.Option(8, "--jobs", min=1, help="jobs in the throughput list"),
    job_s: float = typer.Option(6.0, "--job-s", min=0.5, help="seconds of each job"),
    long_s: float = typer.Option(600.0, "--long-s", min=1.0, help="seconds of the long clip"),
    segment_s: float = typer.Option(60.0, "--segment-s", min=0.1, help="segments of the long clip"),
    rounds: int = typer.Option(3, "--rounds", min=1, help="alternating rounds of the throughput cases"),
    long_rounds: int = typer.Option(1, "--long-rounds", min=1, help="alternating rounds of the long clip"),
    ray: bool = typer.Option(True, "--ray/--no-ray", help="bench the Ray engine too (a local Ray)"),
    out: Path = typer.Option(None, "--out", help="folder for batch.md and batch.json"),
) -> None:
    """gt-render's throughput: seconds of video made per second by 1 and 2 local workers and Ray actors, and a
    long clip split into segments against the same clip whole; extrapolated to many machines."""
    from .batch_rate import batch_table, run_batch_bench

    if not bundle.is_file():
        raise typer.BadParameter(f"{bundle}: no such file", param_hint="BUNDLE")
    result = run_batch_bench(bundle, resolution=resolution, jobs=jobs, job_s=job_s, long_s=long_s,
                             segment_s=segment_s, rounds=rounds, long_rounds=long_rounds, ray=ray, log=typer.echo)
    _publish(result, batch_table, out, "batch", "gt-render: seconds of video per second",
             f"; {jobs} jobs of {job_s:g} s at {resolution}x{resolution}, rounds alternating the engines.")


@app.command()
def voice(
    bundle: list[Path] = typer.Option([], "--bundle", help="also a FLAME bundle's own translator (repeatable)"),
    arkit_model: Path = typer.Option(None, "--arkit-model", help="the ARKit voice model [default: the committed"
                                     " one]"),
    flame_model: Path = typer.Option(None, "--flame-model", help="the FLAME voice model [default: the committed"
                                     " one]"),
    clips: int = typer.Option(40, "--clips", min=1, help="clips of each synthetic family"),
    seed: int = typer.Option(0, "--seed", help="the training run's seed the clips are held out from"),
    out: Path = typer.Option(None, "--out", help="folder for gates.md and gates.json"),
) -> None:
    """Lip-sync of every audio driver on every family of voice and on real human speech (docs/voice.md)."""
    from gaussiantalker.exporter.voice.paths import ARKIT_MODEL, FLAME_MODEL
    from gaussiantalker.exporter.voice.real_speech import RealSpeechMissing

    from .voice_gates import run_voice_bench, voice_table

    for path, hint in [(p, "--bundle") for p in bundle] + [(arkit_model, "--arkit-model"),
                                                           (flame_model, "--flame-model")]:
        if path is not None and not path.is_file():
            raise typer.BadParameter(f"{path}: no such file", param_hint=hint)
    try:
        result = run_voice_bench(arkit_model or ARKIT_MODEL, flame_model or FLAME_MODEL, bundle, clips, seed,
                                 log=typer.echo)
    except RealSpeechMissing as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None
    _publish(result, voice_table, out, "gates", "Voice drivers on every family of voice and on real speech",
             f"; {clips} clips per synthetic family; ✓/✗: the goals (docs/voice.md, \"Measurements\").")


def _live_baseline(script: Path | None, checkout: Path | None, bundle: Path | None = None):
    """`gt-bench live-clients`' baseline (a live_clients.Baseline, or None without --baseline-server)."""
    from .live_clients import Baseline, baseline_checkout

    if script is None:
        for value, hint in ((checkout, "--baseline-checkout"), (bundle, "--baseline-bundle")):
            if value is not None:
                raise typer.BadParameter("needs --baseline-server", param_hint=hint)
        return None
    if bundle is not None and not bundle.is_file():
        raise typer.BadParameter(f"{bundle}: no such file", param_hint="--baseline-bundle")
    if not script.is_file():
        raise typer.BadParameter(f"{script}: no such file", param_hint="--baseline-server")
    checkout = checkout or baseline_checkout(script)
    if checkout is None:
        raise typer.BadParameter(f"{script} lies in no git checkout: name the checkout of its commit",
                                 param_hint="--baseline-checkout")
    if not (checkout / "src" / "gaussiantalker").is_dir():
        raise typer.BadParameter(f"{checkout} has no src/gaussiantalker", param_hint="--baseline-checkout")
    baseline = Baseline(script.resolve(), checkout.resolve(), bundle.resolve() if bundle is not None else None)
    try:
        typer.echo(f"baseline: {baseline.script} on {baseline.package().parent.parent}")
    except ValueError as error:  # it would import another checkout's package (this one's editable install)
        raise typer.BadParameter(str(error), param_hint="--baseline-checkout") from None
    return baseline


def _compare_with_baseline(baseline: Path, gaussians: int, sizes: str, seconds: float, rounds: int,
                           scaling: str | None, play_seconds: float, json_path: Path | None) -> None:
    """`gt-bench compare`: the side-by-side table of bench/compare.py, printed (and written as JSON)."""
    from dataclasses import asdict

    from .compare import checkout_root, compare, format_table

    try:
        checkout_root(baseline)
    except ValueError as exc:
        raise typer.BadParameter(str(exc), param_hint="--baseline") from None
    size_list = [int(s) for s in sizes.split(",")]
    result = compare(baseline, gaussians=[gaussians], sizes=size_list, seconds=seconds, rounds=rounds,
                     play_seconds=play_seconds)
    if scaling:
        counts = [int(c) for c in scaling.split(",") if int(c) != gaussians]
        scaled = compare(baseline, gaussians=counts, sizes=[max(size_list)], seconds=seconds, rounds=rounds,
                         play_seconds=0)
        result.cases.update(scaled.cases)
    result_text = format_table(result)
    typer.echo(f"machine: {json.dumps(machine_info())}\n{result_text}")
    if json_path is not None:
        json_path.write_text(json.dumps({"machine": machine_info(), **asdict(result)}, indent=2))
        typer.echo(f"wrote {json_path}")


def _sweep(checkpoint: Path | None, gaussians: int, large: int, sizes: str, seconds: float, rounds: int,
           cases: str | None, out: Path, skip_demo: bool = False, scene: Path | None = None,
           renderers: tuple[str, ...] = ("gl",)) -> None:
    """`gt-bench sweep`: see bench/sweep.py; writes the markdown report, the JSON and (with matplotlib) the plot."""
    from dataclasses import asdict

    from gaussiantalker.exporter.demo.demo_speaker import make_demo_speaker
    from gaussiantalker.exporter.export.checkpoint import load_checkpoint
    from gaussiantalker.sdk.errors import GaussianTalkerError
    from gaussiantalker.sdk.files import atomic_write

    from .report import format_report, plot_sweep
    from .sweep import scene_cases, select_cases, sweep_cases, sweep_speaker_renderers

    try:
        if scene is not None:
            from gaussiantalker.sdk.scene import load_scene

            try:
                load_scene(scene)  # a bad scene file fails here, before any speaker is built
            except GaussianTalkerError as exc:
                raise typer.BadParameter(str(exc), param_hint="--scene") from None
        chosen = select_cases(sweep_cases() if scene is None else scene_cases(str(scene)), cases)
    except ValueError as exc:
        raise typer.BadParameter(str(exc), param_hint="--cases") from None
    size_list = [int(s) for s in sizes.split(",")]
    if checkpoint is not None:
        demo = load_checkpoint(checkpoint)
    else:
        typer.echo("building the demo speaker (its translator trains for a few minutes; --checkpoint skips this)")
        demo, _ = make_demo_speaker(gaussians)
    # The cases play the bare head (compositing: tools/bench/composite_cost.py); with a preset among them and a clip
    # in the speaker, the sweep also weighs the presets' whole files (the head, the clip, F).
    whole_files = demo.reference is not None and any(case.preset for case in chosen)
    speakers = [] if skip_demo else [("demo speaker", demo)]
    if large > 0:
        synthetic, _ = make_demo_speaker(large, seed=1, train_seconds=0, progress=False, config=demo.config)
        synthetic.translator.load_state_dict(demo.translator.state_dict())  # the same speech, more Gaussians
        speakers.append(("synthetic speaker", synthetic))
    out.mkdir(parents=True, exist_ok=True)
    sweeps = [sweep for name, speaker in speakers
              for sweep in sweep_speaker_renderers(name, speaker, chosen, sizes=size_list, seconds=seconds,
                                                   rounds=rounds, renderers=renderers,
                                                   whole_files=whole_files and speaker is demo)]
    machine = machine_info()
    command = "gt-bench " + " ".join(sys.argv[1:])
    report = format_report(sweeps, machine, command)
    with atomic_write(out / "sweep.md", "w") as handle:
        handle.write(report + "\n")
    with atomic_write(out / "sweep.json", "w") as handle:
        json.dump({"machine": machine, "command": command, "seconds": seconds, "rounds": rounds,
                   "speakers": [asdict(s) for s in sweeps]}, handle, indent=2)
    written = ["sweep.md", "sweep.json"]
    try:
        plot_sweep(sweeps, out / "sweep.png")
        written.append("sweep.png")
    except ImportError:
        typer.echo("matplotlib is not installed (pip install 'gaussiantalker-sdk[bench]'): no plot", err=True)
    typer.echo(report)
    typer.echo(f"wrote {', '.join(str(out / name) for name in written)}")


def main_entry(args: list[str] | None = None) -> None:
    """Run the app as `gt-bench` (`args`: the command line after the program name; None: sys.argv's)."""
    app(args=args, prog_name="gt-bench")


@app.command("blend-limit")
def blend_limit(
    gaussians: str = typer.Option("20000,100000", "--gaussians", help="demo speaker sizes (comma-separated)"),
    size: int = typer.Option(512, "--size", min=16, help="square frame size"),
    layers: int = typer.Option(100, "--layers", min=1, max=400, help="image-filling layers of the full-occupancy "
                               "scene"),
    threads: str = typer.Option("1,2", "--threads", help="CPU splatter thread counts (comma-separated)"),
    frames: int = typer.Option(5, "--frames", min=1, help="blends per case and thread count per round"),
    rounds: int = typer.Option(5, "--rounds", min=1, help="alternating rounds"),
    out: Path = typer.Option(None, "--out", help="folder for blend-limit.md and blend-limit.json"),
) -> None:
    """The CPU splatter's blend on the demo head: its work counts and core-ns per blended fragment, against the same
    kernel at full SIMD occupancy (docs/speed.md)."""

    from .blend_limit import blend_limit_table, run_blend_limit

    counts, thread_counts = _numbers(gaussians, int, "--gaussians"), _numbers(threads, int, "--threads")
    if not counts or not thread_counts or min(counts + thread_counts) < 1:
        raise typer.BadParameter("--gaussians and --threads need whole numbers >= 1")
    result = run_blend_limit(counts, size, layers, thread_counts, frames, rounds)
    _publish(result, blend_limit_table, out, "blend-limit", "CPU splatter: the blend's work and time per fragment",
             f"; {size}x{size}, medians of {rounds} alternating rounds x {frames} blends.")
