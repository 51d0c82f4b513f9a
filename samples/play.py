"""Sample player: `python samples/play.py speaker.gtb --audio speech.wav -o talk.mp4 [--show]`.

Renders the bundle's speaker talking to the audio (25 fps) and writes a video with the audio muxed in (the format
from the extension: mp4, mov, webm, mkv, gif, or a png sequence such as frames/%05d.png); --show also displays the
frames in a window. A bundle with a reference clip is composited into the speaker's own video at the clip's size
(docs/compositing.md); --no-composite gives the bare head, at the speaker's camera (512x512 unless told
otherwise), and --alpha an alpha channel for it. The output is checked before anything is rendered.

An imported avatar (docs/import.md) plays a motion: an ARKit speaker (LAM) `--motion bsData.json` (LAM's ARKit JSON
kinds), a FLAME speaker (GaussianAvatars) `--motion flame_param.npz` (per-frame FLAME parameters), or `--motion`
alone (or, without a translator, no --motion) the motion the avatar ships, with --audio muxed in if given; with an
attached audio model and no --motion, the audio drives it.
"""

from __future__ import annotations

import os
import sys
import time
from dataclasses import replace
from pathlib import Path

import typer

from gaussiantalker.runtime import BackendSettings, GaussianTalkerError, OutputSettings, TalkingHead

app = typer.Typer(add_completion=False)
# The value of a bare `--motion`: play the motion the bundle ships.
OWN_MOTION = "@bundle"


class FrameWindow:
    """A minimal Tk window showing uint8 frames (stdlib only: frames go in as binary PPM images)."""

    def __init__(self, width: int, height: int, title: str) -> None:
        import tkinter

        self.root = tkinter.Tk()
        self.root.title(title)
        self.label = tkinter.Label(self.root, width=width, height=height)
        self.label.pack()
        self._tk = tkinter
        self.open = True
        self.root.protocol("WM_DELETE_WINDOW", self.close)

    def show(self, frame) -> None:
        if not self.open:
            return
        frame = frame[..., :3]  # an alpha channel is not shown
        height, width = frame.shape[:2]
        ppm = f"P6 {width} {height} 255 ".encode() + frame.tobytes()
        self.image = self._tk.PhotoImage(data=ppm, format="PPM")
        self.label.configure(image=self.image)
        self.root.update()

    def close(self) -> None:
        if self.open:
            self.open = False
            self.root.destroy()


def _parse_size(text: str) -> tuple[int, int]:
    """'N' or 'WxH' -> (width, height); GaussianTalkerError naming the text otherwise."""
    try:
        parts = [int(p) for p in text.lower().split("x")]
    except ValueError:
        parts = []
    if len(parts) not in (1, 2) or min(parts) < 1:
        raise GaussianTalkerError(f"resolution must be N or WxH with positive whole numbers, got {text!r}")
    return (parts[0], parts[0]) if len(parts) == 1 else (parts[0], parts[1])


def _parse_background(text: str) -> list[float]:
    """'r,g,b' -> three floats; GaussianTalkerError naming the text otherwise (the range is TalkingHead's check)."""
    try:
        values = [float(c) for c in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 3:
        raise GaussianTalkerError(f"background must be r,g,b (three numbers in 0..1), got {text!r}")
    return values


@app.command()
def play(
    bundle: Path = typer.Argument(..., help="speaker bundle (.gtb) written by gt-export"),
    audio: Path = typer.Option(None, "--audio", "-a", help="speech: wav, mp3 or anything ffmpeg reads (an ARKit "
                               "speaker: muxed beside its motion)"),
    motion: str = typer.Option(None, "--motion", "-m", help="a motion to play: an ARKit speaker's JSON of ARKit "
                               "weights as LAM writes them, a FLAME speaker's npz of FLAME parameters "
                               "(GaussianAvatars' flame_param.npz keys); --motion alone: the avatar's own"),
    output: Path = typer.Option(Path("talk.mp4"), "-o", "--output",
                                help="video to write: .mp4 .mov .webm .mkv .gif, or frames/%05d.png"),
    resolution: str = typer.Option(None, "--resolution", "-r", help="frame size, N or WxH [default: the reference "
                                   "clip's when compositing, else 512]"),
    no_composite: bool = typer.Option(False, "--no-composite", help="the bare head, not composited into the "
                                      "bundle's reference clip"),
    background: str = typer.Option(None, "--background", help="background colour r,g,b in 0..1"),
    alpha: bool = typer.Option(False, "--alpha", help="write coverage as an alpha channel (webm, mov with "
                                                      "--codec prores, mkv, png sequence)"),
    codec: str = typer.Option(None, "--codec", help="h264, vp9, prores, ffv1 [default: the container's]"),
    crf: int = typer.Option(None, "--crf", help="constant-rate factor (h264 0-51, vp9 0-63; lower: better)"),
    preset: str = typer.Option(None, "--preset", help="encoder speed preset (x264 names; vp9: realtime, good, "
                                                      "best)"),
    video_format: str = typer.Option(None, "--format", help="container when the extension does not say: mp4, "
                                                            "mov, webm, mkv, gif, png"),
    show: bool = typer.Option(False, "--show", help="also show the frames in a window (needs a display)"),
    threads: int = typer.Option(None, "--threads", help="graph threads [default: the bundle's preset, else all "
                                "cores for onnxruntime, 1 for MNN]"),
    backend: str = typer.Option("onnxruntime", "--backend", help="graph backend: onnxruntime, or mnn (a bundle "
                                "exported with gt-export --mnn, the mnn extra; docs/mnn.md)"),
    renderer: str = typer.Option("auto", "--renderer", help="what splats: gl, cpu (the numba tile splatter, the "
                                 "cpu extra) or auto (cpu where the GL is a software rasterizer and numba is "
                                 "installed; docs/embedding.md)"),
    render_scale: float = typer.Option(None, "--render-scale", help="draw at this fraction of the size, then "
                                       "upscale (0.1-1) [default: the bundle's preset, else 1]"),
    render_target: str = typer.Option(None, "--render-target", help="framebuffer: float32, float16, uint8 "
                                      "[default: the bundle's preset, else float32]"),
    sort_interval: int = typer.Option(None, "--sort-interval", help="depth-sort every k-th frame and reuse that "
                                      "order in between (1-60) [default: the bundle's preset, else 1]"),
    sort_key_bits: int = typer.Option(None, "--sort-key-bits", help="32: exact depth; 16: depth quantised to "
                                      "65536 levels, faster [default: the bundle's preset, else 32]"),
    alpha_min: float = typer.Option(None, "--alpha-min", help="CPU splatter: skip contributions with a smaller "
                                    "alpha (1/255-0.1) [default: the bundle's preset, else 1/255]"),
    transmittance_min: float = typer.Option(None, "--transmittance-min", help="CPU splatter: also stop a pixel once "
                                            "its transmittance falls below this (1e-4-0.1) [default: the bundle's "
                                            "preset, else 1e-4]"),
    max_draw_pixels: int = typer.Option(None, "--max-draw-pixels", min=0, help="draw at most about this many "
                                        "pixels, then upscale; 0: no cap [default: the bundle's preset, else no "
                                        "cap]"),
    no_pipeline: bool = typer.Option(False, "--no-pipeline", help="one frame stage after another on one thread "
                                     "(the same frames; by default neighbouring frames' stages overlap)"),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="no progress bar"),
) -> None:
    """Render BUNDLE talking to AUDIO (or playing an ARKit MOTION) and write a video with the audio muxed in."""
    start = time.perf_counter()
    try:
        # Everything about the output is checked before the speaker is loaded (the manifest alone says the frames).
        size = None if resolution is None else _parse_size(resolution)
        output_settings = OutputSettings(resolution=size, composite=False if no_composite else None,
                                         background=None if background is None else _parse_background(background))
        view = TalkingHead.output_view(bundle, output_settings)
        if view.composite and alpha:
            raise GaussianTalkerError("a composited frame is opaque (the reference clip fills it): --alpha needs "
                                      "--no-composite")
        if size is None and not view.composite:  # the bare head defaults to 512x512
            output_settings = replace(output_settings, resolution=(512, 512))
            view = TalkingHead.output_view(bundle, output_settings)
        plan = view.plan_video(output, alpha=alpha, codec=codec, crf=crf, preset=preset, container=video_format)
        # The render knobs are shortcuts: each one not given keeps the bundle's preset value.
        head = TalkingHead(bundle, output_settings=output_settings,
                           backend_settings=BackendSettings(backend, threads=threads, renderer=renderer,
                                                            pipeline=not no_pipeline),
                           render_scale=render_scale, render_target=render_target, sort_interval=sort_interval,
                           sort_key_bits=sort_key_bits, alpha_min=alpha_min, max_draw_pixels=max_draw_pixels,
                           transmittance_min=transmittance_min)
        window = None
        if show:
            headless = not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
            if sys.platform.startswith("linux") and headless:
                raise GaussianTalkerError("--show needs a display (DISPLAY is not set); the video is still written "
                                          "without --show")
            window = FrameWindow(*head.frame_size, f"GaussianTalker - {bundle.name}")
        driver = head.driver
        samples = None if audio is None else driver.load_audio(audio)
        if motion is not None or samples is None or not driver.has_translator:
            if motion is None and driver.has_translator and driver.motion_track is None:
                raise GaussianTalkerError("--audio is required: this speaker turns speech into motion (or give "
                                          "--motion FILE)")
            track = driver.motion(None if motion == OWN_MOTION else motion)
            total = len(track)
        else:
            track, total = None, driver.frame_count(samples.shape[0])
        head.write_video(plan, samples, head.sample_rate, progress=not quiet, motion=track,
                         on_frame=window.show if window is not None else None)
        if window is not None:
            window.close()
        head.close()
    except GaussianTalkerError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None
    seconds = time.perf_counter() - start
    if samples is None:
        sound = f"{total / head.fps:.1f} s, no audio"
    else:
        sound = f"{samples.shape[0] / head.sample_rate:.1f} s of audio" + \
            ("" if plan.with_audio else f"; {plan.container.name} holds no audio")
    typer.echo(f"wrote {output} ({total} frames, {sound}) in {seconds:.1f} s with the {head.renderer} renderer: "
               f"{plan.describe()}")


def _own_motion_flag(argv: list[str]) -> list[str]:
    """`--motion` (or `-m`) given without a file means the avatar's own motion: OWN_MOTION is put in as its value
    (hand-written because typer options cannot take an optional value)."""
    out = []
    for index, arg in enumerate(argv):
        out.append(arg)
        following = argv[index + 1] if index + 1 < len(argv) else None
        if arg in ("--motion", "-m") and (following is None or following.startswith("-")):
            out.append(OWN_MOTION)
    return out


if __name__ == "__main__":
    app(_own_motion_flag(sys.argv[1:]))
