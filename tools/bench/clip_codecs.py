"""How to store a reference clip: size and per-frame decode time of candidate codecs on the demo clip.

    gt-bench clip-codecs out/speaker.ckpt

Prints a Markdown table (docs/compositing.md keeps the measured one). Candidates: JPEG per frame at two
quantisers, PNG per frame (lossless), H.264 through libx264 as one stream with a 25-frame GOP, and what the SDK
stores: each frame its own intra-coded H.264 packet (`sdk.reference_clip.encode_frame`, decoded alone). Decode time
is the median per frame over the clip, decoding in order (the best case for the GOP stream, which cannot start at
an arbitrary frame without its keyframe).
"""

from __future__ import annotations

import statistics
import time
from fractions import Fraction
from pathlib import Path

import av
import numpy as np

from gaussiantalker.exporter.demo.clip import ClipComposer
from gaussiantalker.exporter.export.checkpoint import load_checkpoint
from gaussiantalker.sdk.image import psnr_db, to_uint8
from gaussiantalker.sdk.reference_clip import ClipLayout, decode_frame, encode_frame


def _encode_images(frames: list[np.ndarray], codec: str, pix_fmt: str, options: dict) -> list[bytes]:
    out = []
    for rgb in frames:
        ctx = av.CodecContext.create(codec, "w")
        ctx.width, ctx.height, ctx.pix_fmt, ctx.time_base = rgb.shape[1], rgb.shape[0], pix_fmt, Fraction(1, 25)
        ctx.options = options
        picture = av.VideoFrame.from_ndarray(rgb, format="rgb24").reformat(format=pix_fmt)
        out.append(b"".join(bytes(p) for p in ctx.encode(picture) + ctx.encode(None)))
    return out


def _decode_images(entries: list[bytes], codec: str) -> tuple[list[np.ndarray], list[float]]:
    frames, seconds = [], []
    for data in entries:
        start = time.perf_counter()
        picture = av.CodecContext.create(codec, "r").decode(av.Packet(data))[0]
        frames.append(picture.to_ndarray(format="rgb24"))
        seconds.append(time.perf_counter() - start)
    return frames, seconds


def _h264(frames: list[np.ndarray], gop: int) -> tuple[int, list[np.ndarray], list[float]]:
    ctx = av.CodecContext.create("libx264", "w")
    ctx.width, ctx.height, ctx.pix_fmt, ctx.time_base = frames[0].shape[1], frames[0].shape[0], "yuv420p", \
        Fraction(1, 25)
    ctx.gop_size = gop
    ctx.options = {"crf": "18", "preset": "medium", "bf": "0"}
    packets = []
    for index, rgb in enumerate(frames):
        picture = av.VideoFrame.from_ndarray(rgb, format="rgb24").reformat(format="yuv420p")
        picture.pts = index
        packets += [bytes(p) for p in ctx.encode(picture)]
    packets += [bytes(p) for p in ctx.encode(None)]
    decoder = av.CodecContext.create("h264", "r")
    decoded, seconds = [], []
    for data in packets:
        start = time.perf_counter()
        pictures = decoder.decode(av.Packet(data))
        decoded += [p.to_ndarray(format="rgb24") for p in pictures]
        seconds.append(time.perf_counter() - start)
    decoded += [p.to_ndarray(format="rgb24") for p in decoder.decode(None)]
    return sum(map(len, packets)), decoded, seconds


def run_clip_codecs_bench(checkpoint: str | Path) -> None:
    """Print the codec table for the checkpoint's reference clip."""
    composer = ClipComposer(load_checkpoint(checkpoint))
    frames = [to_uint8(frame.image) for frame in composer.frames()]
    rows = []
    for label, codec, pix_fmt, options in (("JPEG q2 (4:2:0)", "mjpeg", "yuvj420p", {"qmin": "2", "qmax": "2"}),
                                           ("JPEG q4 (4:2:0)", "mjpeg", "yuvj420p", {"qmin": "4", "qmax": "4"}),
                                           ("PNG", "png", "rgb24", {})):
        entries = _encode_images(frames, codec, pix_fmt, options)
        decoded, seconds = _decode_images(entries, codec)
        rows.append((label, sum(map(len, entries)), decoded, seconds, "any frame alone"))
    nbytes, decoded, seconds = _h264(frames, 25)
    rows.append(("H.264 crf 18, GOP 25", nbytes, decoded, seconds, "from its keyframe"))
    layout = ClipLayout(len(frames), composer.camera)
    entries = [encode_frame(rgb) for rgb in frames]
    decoded, seconds = [], []
    for data in entries:
        start = time.perf_counter()
        decoded.append(decode_frame(data, layout, "frame"))
        seconds.append(time.perf_counter() - start)
    rows.append(("H.264 crf 18, one intra frame per entry (stored)", sum(map(len, entries)), decoded, seconds,
                 "any frame alone"))
    print(f"{len(frames)} frames, {frames[0].shape[1]}x{frames[0].shape[0]}\n")
    print("| codec | MB | decode ms / frame (median) | min PSNR vs the frames | random access |")
    print("|---|---|---|---|---|")
    for label, nbytes, decoded, seconds, access in rows:
        quality = min(psnr_db(a, b) for a, b in zip(frames, decoded, strict=True))
        print(f"| {label} | {nbytes / 1e6:.2f} | {1e3 * statistics.median(seconds):.2f} | "
              f"{'lossless' if quality == float('inf') else f'{quality:.1f} dB'} | {access} |")
