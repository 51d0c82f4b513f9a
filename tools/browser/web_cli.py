"""`gt-web`: the browser player (web/, docs/web.md) from the command line, in headless Debian Chromium.

    gt-web render speaker.gtb --audio speech.wav --frames 0,10,20 --size 512x512 -o out/web [--timings] [--compare]
    gt-web render avatar.gtb --motion bsData.json --frames 0,5 -o out/web      # flame_param.npz for a FLAME avatar
    gt-web install          # npm ci in web/ (onnxruntime-web and fflate, pinned by web/package-lock.json)

`render` writes frame_NNNNN.png (8-bit RGB) per frame and, with --timings, timings.json: the player's per-step
seconds (graphs, sort, upload, draw, readback) per frame and their medians. --compare renders the same frames with
the Python runtime (TalkingHead, renderer "gl") and reports the PSNR between the two and the runtime's own step
times.
Run as `python -m tools.browser.web_cli` from the checkout's root where the console script is not installed.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import typer

from gaussiantalker.sdk.image import write_png

from .chromium import ChromiumMissing
from .web_assets import web_root
from .web_harness import WEBGPU_FLAGS, WebPlayerMissing, WebPlayerPage

app = typer.Typer(add_completion=False, no_args_is_help=True,
                  help="The browser player (web/) in headless Chromium: frames as PNGs (docs/web.md).")
STEPS = ("graphs", "sort", "upload", "draw", "readback")
# The Python runtime's name of each step (TalkingHead.timings).
PYTHON_STEPS = (("graphs", "deformation"), ("sort", "sort"), ("upload", "upload"), ("draw", "draw"),
                ("readback", "readback"))


def parse_size(text: str) -> tuple[int, int]:
    """"512x512" (or "512") -> (width, height)."""
    parts = text.lower().split("x")
    try:
        width, height = (int(parts[0]), int(parts[-1])) if len(parts) in (1, 2) else (0, 0)
    except ValueError:
        width = height = 0
    if not (1 <= width <= 16384 and 1 <= height <= 16384):
        raise typer.BadParameter(f"size must be WIDTHxHEIGHT in 1..16384, got {text!r}")
    return width, height


def parse_frames(text: str) -> list[int]:
    """"0,10,20" -> [0, 10, 20] (each >= 0; checked against the drive's length once it is known)."""
    try:
        frames = [int(part) for part in text.split(",") if part.strip()]
    except ValueError:
        frames = []
    if not frames or min(frames) < 0:
        raise typer.BadParameter(f"frames must be a comma-separated list of indexes >= 0, got {text!r}")
    return frames


def _python_frames(bundle: Path, audio: Path | None, motion: Path | None, frames: list[int],
                   size: tuple[int, int] | None, camera: dict | None, settings: dict, composite: bool = False
                   ) -> tuple[list[np.ndarray], dict]:
    """The same frames from the Python runtime (GL renderer, the same render settings, composited or not as the
    page's), and its median per-step seconds."""
    from itertools import islice

    from gaussiantalker.runtime.head import TalkingHead
    from gaussiantalker.sdk.camera import Camera

    kwargs = {"camera": Camera.from_dict(camera)} if camera else {}
    with TalkingHead(bundle, resolution=size, renderer="gl", composite=composite, **kwargs, **settings) as head:
        if composite:  # composited frames come from frames(): each drive composited into its clip picture
            made = list(islice(head.frames(audio) if audio else head.frames(motion=motion), max(frames) + 1))
            out = [made[index] for index in frames]
        else:
            drives = list(islice(head.drives(audio) if audio else head.drives(motion=motion), max(frames) + 1))
            out = [head.render(drives[index]) for index in frames]
        median = {stage: float(np.median(values[-len(frames):])) for stage, values in head.timings.items()}
    return out, median


@app.command()
def render(
    bundle: Path = typer.Argument(..., exists=True, dir_okay=False, help="the .gtb bundle"),
    audio: Path | None = typer.Option(None, "--audio", exists=True, dir_okay=False,
                                      help="audio file (what Chromium decodes: WAV, MP3, ...) through the translator"),
    motion: Path | None = typer.Option(None, "--motion", exists=True, dir_okay=False,
                                       help="motion file: LAM's JSON for an ARKit speaker, a FLAME motion npz "
                                            "(GaussianAvatars' flame_param.npz) for a FLAME one"),
    frames: str = typer.Option("0", "--frames", help="comma-separated frame indexes, e.g. 0,10,20"),
    size: str = typer.Option(None, "--size", help="output WIDTHxHEIGHT (the camera resized) [default: the "
                             "bundle camera's size, the reference clip's when composited]"),
    composite: bool = typer.Option(None, "--composite/--bare", help="audio's frames composited into the bundle's "
                                   "reference clip, or the bare head [default: composited where the bundle has a "
                                   "clip and an inpainting graph]"),
    camera: Path | None = typer.Option(None, "--camera", exists=True, dir_okay=False,
                                       help="a camera JSON (Camera.to_dict keys) instead of the bundle's"),
    out: Path = typer.Option(..., "-o", "--out", help="folder for frame_NNNNN.png (and timings.json)"),
    timings: bool = typer.Option(False, "--timings", help="print per-step times and write timings.json"),
    compare: bool = typer.Option(False, "--compare", help="also render with the Python runtime: PSNR and its times"),
    render_target: str | None = typer.Option(None, "--render-target", help="float32, float16 or uint8"),
    render_scale: float | None = typer.Option(None, "--render-scale", help="draw at this fraction, upscale"),
    sort_key_bits: int | None = typer.Option(None, "--sort-key-bits", help="32 (exact depth) or 16"),
    sort_interval: int | None = typer.Option(None, "--sort-interval", help="depth-sort every k-th frame"),
    quads: bool = typer.Option(False, "--quads", help="the web player draws every Gaussian as a quad (same pixels)"),
    graphs: str = typer.Option("auto", "--graphs", help="onnxruntime-web backend: auto (WebGPU on a hardware adapter, "
                               "else wasm), wasm, or webgpu (here: SwiftShader's software adapter, seconds a graph)"),
) -> None:
    """Render frames of BUNDLE through the browser player in headless Chromium, as 8-bit RGB PNGs."""
    if (audio is None) == (motion is None):
        raise typer.BadParameter("give exactly one of --audio and --motion")
    if graphs not in ("auto", "wasm", "webgpu"):
        raise typer.BadParameter(f"--graphs must be auto, wasm or webgpu, got {graphs!r}")
    wanted = parse_frames(frames)
    wanted_size = parse_size(size) if size else None
    camera_dict = json.loads(camera.read_text()) if camera else None
    if camera_dict and "width" not in camera_dict:
        width, height = wanted_size or (512, 512)
        camera_dict = {**camera_dict, "width": width, "height": height}
    out.mkdir(parents=True, exist_ok=True)
    # The bundle's runtime defaults, overridden where given: the player's names, and the Python runtime's.
    settings = {name: value for name, value in (("render_target", render_target), ("render_scale", render_scale),
                                                ("sort_key_bits", sort_key_bits), ("sort_interval", sort_interval))
                if value is not None}
    web_settings = {"".join(w.capitalize() if i else w for i, w in enumerate(k.split("_"))): v
                    for k, v in settings.items()}
    if quads:
        web_settings["pointSprites"] = False
    web_settings["graphs"] = graphs
    report: dict = {"bundle": str(bundle), "settings": settings, "quads": quads, "frames": {}}
    try:
        with WebPlayerPage(extra_flags=WEBGPU_FLAGS if graphs == "webgpu" else ()) as page:
            info = page.load(bundle, size=wanted_size, camera=camera_dict, settings=web_settings, composite=composite)
            width, height = info["size"]
            report.update(size=[width, height], composited=info["composited"])
            drive = page.drive(audio=audio, motion=motion)
            over = [i for i in wanted if i >= drive["frames"]]
            if over:
                raise typer.BadParameter(f"frame {over[0]} is out of range: the drive has {drive['frames']} frames")
            report.update(load=info, translate_seconds=drive["translate"], renderer=info["renderer"],
                          precision=info["precision"], graphs=info["graphs"])
            web_frames = []
            for index in wanted:
                frame, steps = page.render(index)
                write_png(out / f"frame_{index:05d}.png", frame)
                web_frames.append(frame)
                report["frames"][str(index)] = steps
                if timings:
                    typer.echo(f"frame {index}: " + "  ".join(f"{s} {steps[s] * 1000:.1f} ms" for s in STEPS))
    except (ChromiumMissing, WebPlayerMissing) as exc:
        typer.echo(f"gt-web: {exc}", err=True)
        raise typer.Exit(2) from None
    except RuntimeError as exc:  # the page's error: a damaged bundle, a bad drive
        typer.echo(f"gt-web: {str(exc).splitlines()[0]}", err=True)
        raise typer.Exit(1) from None
    adapter = info["graphs"]["adapter"]
    backend = info["graphs"]["name"] + (f" on {adapter['vendor']} {adapter['architecture']}" if adapter else "")
    kind = "composited" if info["composited"] else "bare head"
    typer.echo(f"wrote {len(wanted)} {kind} frames ({width}x{height}) to {out} [{info['precision']} framebuffer, "
               f"{info['renderer']}; graphs {backend}]")
    if compare:
        from gaussiantalker.sdk.image import psnr_db

        start = time.perf_counter()
        python_frames, python_steps = _python_frames(bundle, audio, motion, wanted, wanted_size, camera_dict,
                                                     settings, composite=info["composited"])
        report["python_steps"] = python_steps
        report["python_seconds"] = time.perf_counter() - start
        typer.echo("Python runtime (GL), median: " + "  ".join(
            f"{name} {python_steps[stage] * 1000:.1f} ms" for name, stage in PYTHON_STEPS if stage in python_steps))
        for index, web, ref in zip(wanted, web_frames, python_frames, strict=True):
            psnr = psnr_db(ref, web)
            levels = int(np.abs(ref.astype(np.int16) - web).max())
            report["frames"][str(index)].update(psnr_db=psnr, max_levels=levels)
            typer.echo(f"frame {index}: PSNR {psnr:.2f} dB against the Python runtime, at most {levels} levels off")
    if timings or compare:
        steps = {s: float(np.median([f[s] for f in report["frames"].values()])) for s in STEPS}
        report["median_steps"] = steps
        typer.echo("web player, median: " + "  ".join(f"{s} {steps[s] * 1000:.1f} ms" for s in STEPS))
        (out / "timings.json").write_text(json.dumps(report, indent=2))


@app.command()
def install() -> None:
    """Install the player's npm dependencies (npm ci in web/, the versions web/package-lock.json pins; no package
    install scripts run: the player needs none)."""
    npm = shutil.which("npm")
    if npm is None:
        typer.echo("gt-web: npm is not installed: `apt-get install -y npm`", err=True)
        raise typer.Exit(2)
    root = web_root()
    result = subprocess.run([npm, "ci", "--ignore-scripts", "--no-audit", "--no-fund"], cwd=root, check=False)
    if result.returncode != 0:
        typer.echo(f"gt-web: `npm ci` in {root} failed", err=True)
        raise typer.Exit(1)
    typer.echo(f"installed the web player's npm dependencies in {root / 'node_modules'}")


def main() -> None:
    """`gt-web`."""
    app(prog_name="gt-web")


if __name__ == "__main__":
    sys.exit(main())


__all__ = ["app", "main", "parse_frames", "parse_size"]
