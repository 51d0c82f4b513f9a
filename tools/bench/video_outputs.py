"""Encoding cost of every video output (docs/video.md): `gt-bench video BUNDLE`.

Renders the frames once (the speaker talking to the demo speech), then encodes them to each output in alternating
rounds and prints a markdown table: start-up (writer opened, encoder checked), median ms per frame, bytes per
second of video. The first row pipes the same frames to an ffmpeg process through imageio-ffmpeg (the previous
writer), for the library comparison.

The frames are the bare head's (RGBA, so the alpha outputs have their alpha), also for a bundle with a reference
clip; `composite=True` measures such a bundle's composited frames instead: opaque RGB at the clip's aspect, so the
alpha outputs are left out. The table's first line says which.
"""

from __future__ import annotations

import shutil
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from gaussiantalker.runtime import TalkingHead
from gaussiantalker.sdk.video import VideoWriter

ROOT = Path(__file__).resolve().parents[2]  # the checkout (samples/ holds the demo speech)
# (label, file name, writer options)
OUTPUTS = [
    ("mp4 h264", "a.mp4", {}),
    ("mov prores 422 HQ", "a.mov", {"codec": "prores"}),
    ("mov prores 4444 + alpha", "a.mov", {"codec": "prores", "alpha": True}),
    ("webm vp9", "a.webm", {}),
    ("webm vp9 + alpha", "a.webm", {"alpha": True}),
    ("mkv ffv1 (lossless)", "a.mkv", {"codec": "ffv1"}),
    ("gif (palette per frame)", "a.gif", {}),
    ("png sequence + alpha", "seq/%05d.png", {"alpha": True}),
]


def _encode_pyav(path: Path, frames: list[np.ndarray], audio: np.ndarray, options: dict) -> tuple[float, float]:
    start = time.perf_counter()
    height, width = frames[0].shape[:2]
    with VideoWriter(path, 25, (width, height), audio=audio, **options) as out:
        opened = time.perf_counter()
        for frame in frames:
            out.write(frame if options.get("alpha") else frame[..., :3])
    return opened - start, time.perf_counter() - opened


def _encode_imageio(path: Path, frames: list[np.ndarray]) -> tuple[float, float]:
    import imageio_ffmpeg

    start = time.perf_counter()
    height, width = frames[0].shape[:2]
    writer = imageio_ffmpeg.write_frames(str(path), (width, height), fps=25, quality=8, macro_block_size=1,
                                         output_params=["-preset", "veryfast"], ffmpeg_log_level="error")
    writer.send(None)
    opened = time.perf_counter()
    for frame in frames:
        writer.send(np.ascontiguousarray(frame[..., :3]))
    writer.close()
    return opened - start, time.perf_counter() - opened


def _size(path: Path) -> int:
    return sum(p.stat().st_size for p in path.parent.iterdir()) if "%" in path.name else path.stat().st_size


def _frame_source(bundle: Path, size: int, composite: bool) -> tuple[tuple[int, int], str, str]:
    """(resolution, output, what the frames are) for the bench's frames of `bundle`."""
    view = TalkingHead.output_view(bundle)
    if not composite:
        note = " (its reference clip unused: composite=True measures the composited frames)" if view.composite else ""
        return (size, size), "rgba", f"the bare head, RGBA{note}"
    if not view.composite:
        raise ValueError(f"{bundle}: composite=True needs a bundle with a reference clip")
    width, height = view.size
    resolution = (max(2, 2 * round(size * width / height / 2)), size)  # the clip's aspect, an even width
    return resolution, "uint8", "composited into the reference clip, RGB (a composited frame is opaque: no alpha rows)"


def run_video_bench(bundle: Path, size: int = 512, frames: int = 50, rounds: int = 3, composite: bool = False) -> None:
    """Print the encoding table for BUNDLE's frames, SIZE high: the bare head's at SIZE x SIZE (every output), or with
    `composite` the frames composited into the bundle's reference clip at its aspect (the outputs without alpha)."""
    resolution, output, what = _frame_source(bundle, size, composite)
    with TalkingHead(bundle, resolution=resolution, composite=composite) as head:
        speech = head.driver.load_audio(ROOT / "samples" / "demo_speech.wav")
        audio = speech[: frames * head.driver.config.samples_per_frame]
        rendered = list(head.frames(audio, head.driver.config.sample_rate, output=output))
    outputs = OUTPUTS if output == "rgba" else [row for row in OUTPUTS if not row[2].get("alpha")]
    rows = [("mp4 h264 via imageio-ffmpeg (ffmpeg process)", "b.mp4", None), *outputs]
    results: dict[str, list[tuple[float, float, int]]] = {label: [] for label, _, _ in rows}
    work = Path(tempfile.mkdtemp(prefix="gt-bench-video-"))
    try:
        for _ in range(rounds):
            for label, name, options in rows:
                folder = work / label.replace(" ", "_")
                shutil.rmtree(folder, ignore_errors=True)
                path = folder / name
                path.parent.mkdir(parents=True, exist_ok=True)
                opened, encoded = (_encode_imageio(path, rendered) if options is None
                                   else _encode_pyav(path, rendered, audio, options))
                results[label].append((opened, encoded, _size(path)))
    finally:
        shutil.rmtree(work, ignore_errors=True)
    seconds = frames / 25
    print(f"{frames} frames of {what} at {resolution[0]}x{resolution[1]}, {rounds} alternating rounds, medians")
    print("| output | start-up ms | ms per frame | kB per second |")
    print("|---|---|---|---|")
    for label, runs in results.items():
        opened = statistics.median(r[0] for r in runs) * 1e3
        per_frame = statistics.median(r[1] for r in runs) * 1e3 / frames
        print(f"| {label} | {opened:.0f} | {per_frame:.1f} | {runs[0][2] / seconds / 1e3:.0f} |")
