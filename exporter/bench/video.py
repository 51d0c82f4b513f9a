"""Encoding cost of every video output (docs/video.md): `gt-bench video BUNDLE`.

Renders the frames once (the speaker talking to the demo speech), then encodes them to each output in alternating
rounds and prints a markdown table: start-up (writer opened, encoder checked), median ms per frame, bytes per
second of video. The first row pipes the same frames to an ffmpeg process through imageio-ffmpeg (the previous
writer), for the library comparison.
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


def run_video_bench(bundle: Path, size: int = 512, frames: int = 50, rounds: int = 3) -> None:
    """Print the encoding table for BUNDLE's frames at SIZE x SIZE."""
    with TalkingHead(bundle, resolution=(size, size)) as head:
        audio = head.load_audio(ROOT / "samples" / "demo_speech.wav")[: frames * head.config.samples_per_frame]
        rendered = list(head.frames(audio, head.config.sample_rate, output="rgba"))
    rows = [("mp4 h264 via imageio-ffmpeg (ffmpeg process)", "b.mp4", None), *OUTPUTS]
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
    print(f"{frames} frames at {size}x{size}, {rounds} alternating rounds, medians")
    print("| output | start-up ms | ms per frame | kB per second |")
    print("|---|---|---|---|")
    for label, runs in results.items():
        opened = statistics.median(r[0] for r in runs) * 1e3
        per_frame = statistics.median(r[1] for r in runs) * 1e3 / frames
        print(f"| {label} | {opened:.0f} | {per_frame:.1f} | {runs[0][2] / seconds / 1e3:.0f} |")
