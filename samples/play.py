"""Sample player: `python samples/play.py speaker.gtb --audio speech.wav -o talk.mp4 [--show]`.

Renders the bundle's speaker talking to the audio (25 fps, the speaker's camera at 512x512 unless told
otherwise) and writes an mp4 with the audio muxed in; --show also displays the frames in a window.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import typer

from gaussiantalker.runtime import TalkingHead
from gaussiantalker.sdk.errors import GaussianTalkerError

app = typer.Typer(add_completion=False)


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
    parts = [int(p) for p in text.lower().split("x")]
    return (parts[0], parts[0]) if len(parts) == 1 else (parts[0], parts[1])


@app.command()
def play(
    bundle: Path = typer.Argument(..., help="speaker bundle (.gtb) written by gt-export"),
    audio: Path = typer.Option(..., "--audio", "-a", help="speech: wav, mp3 or anything ffmpeg reads"),
    output: Path = typer.Option(Path("talk.mp4"), "-o", "--output", help="mp4 to write"),
    resolution: str = typer.Option("512", "--resolution", "-r", help="frame size, N or WxH"),
    background: str = typer.Option(None, "--background", help="background colour r,g,b in 0..1"),
    show: bool = typer.Option(False, "--show", help="also show the frames in a window (needs a display)"),
    threads: int = typer.Option(None, "--threads", help="onnxruntime threads [default: all cores]"),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="no progress bar"),
) -> None:
    """Render BUNDLE talking to AUDIO and write an mp4 with the audio muxed in."""
    start = time.perf_counter()
    try:
        bg = None if background is None else [float(c) for c in background.split(",")]
        head = TalkingHead(bundle, resolution=_parse_size(resolution), background=bg, threads=threads)
        window = None
        if show:
            headless = not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
            if sys.platform.startswith("linux") and headless:
                raise GaussianTalkerError("--show needs a display (DISPLAY is not set); the mp4 is still written "
                                          "without --show")
            window = FrameWindow(head.camera.width, head.camera.height, f"GaussianTalker - {bundle.name}")
        samples = head.load_audio(audio)
        total = head.frame_count(samples.shape[0])
        head.write_video(output, samples, head.config.sample_rate, progress=not quiet,
                         on_frame=window.show if window is not None else None)
        if window is not None:
            window.close()
        head.close()
    except GaussianTalkerError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None
    seconds = time.perf_counter() - start
    typer.echo(f"wrote {output} ({total} frames, {samples.shape[0] / head.config.sample_rate:.1f} s of audio) "
               f"in {seconds:.1f} s")


if __name__ == "__main__":
    app()
