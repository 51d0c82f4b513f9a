"""`gt-bench lam-web`: PNGs of a LAM avatar drawn by the original web renderer, with their camera and weights.

The frames are the ground truth our renderer's frames are compared against by PSNR (docs/lam-web.md).
"""

from __future__ import annotations

import json
import struct
import time
import zlib
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from gaussiantalker.sdk.camera import Camera
from gaussiantalker.sdk.errors import DriveError
from gaussiantalker.sdk.image import psnr_db
from gaussiantalker.sdk.motion import load_motion
from gaussiantalker.sdk.rig import ARKIT_BLENDSHAPES

from .lam_web import LamWebRenderer, page_camera, weights_dict
from .lam_web_camera import lam_default_camera


def write_png(path: Path, rgb: np.ndarray) -> None:
    """Write an HxWx3 uint8 image as an 8-bit RGB PNG (stdlib zlib: no imaging package needed)."""
    rgb = np.ascontiguousarray(rgb, dtype=np.uint8)
    height, width = rgb.shape[:2]
    rows = np.concatenate([np.zeros((height, 1), np.uint8), rgb.reshape(height, width * 3)], axis=1)

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(rows.tobytes(), 6))
                     + chunk(b"IEND", b""))


def parse_frames(spec: str, count: int) -> list[int]:
    """Motion frame indexes from "0,15,30" (negative ones count from the end), each checked against `count`."""
    indexes = []
    for part in spec.split(","):
        index = int(part)
        index = index + count if index < 0 else index
        if not 0 <= index < count:
            raise ValueError(f"motion frame {part} is out of range: the motion has {count} frames")
        indexes.append(index)
    return indexes


def check_web_layout(avatar: Path) -> None:
    """ValueError unless the web renderer can open the zip: it takes the folder of the zip's last directory entry
    and loads FOLDER/offset.ply and FOLDER/skin.glb from it (gt-import takes any layout; docs/lam-web.md)."""
    import zipfile

    try:
        with zipfile.ZipFile(avatar) as archive:
            entries = archive.infolist()
    except (zipfile.BadZipFile, OSError) as exc:
        raise ValueError(f"{avatar}: not a readable zip ({exc})") from None
    folders = [entry.filename[:-1] for entry in entries if entry.is_dir()]
    names = {entry.filename for entry in entries}
    if not folders:
        raise ValueError(f"{avatar}: the web renderer needs a directory entry for the avatar's folder (zip it as a "
                         "folder: `zip -r avatar.zip avatar/`)")
    missing = [f"{folders[-1]}/{name}" for name in ("offset.ply", "skin.glb") if f"{folders[-1]}/{name}" not in names]
    if missing:
        raise ValueError(f"{avatar}: the web renderer opens the last folder of the zip, {folders[-1]}/, which lacks "
                         f"{', '.join(missing)}")


def run_lam_web(avatar: Path, out: Path, motion: Path | None = None, frames: str = "0", size: int = 512,
                background: Sequence[float] = (1.0, 1.0, 1.0), camera: Camera | None = None,
                cache_dir: Path | None = None, echo: Callable[[str], None] = print,
                compare: Path | None = None) -> list[Path]:
    """Render the chosen motion frames (or the neutral face) to out/web_{frame}.png, cameras.json (the camera,
    Camera.to_dict()) and weights.json; `camera` defaults to the renderer's own at size x size. With `compare` (a
    bundle of the same avatar), the runtime draws the same frames too (ours_{frame}.png) and compare.json holds
    the PSNR of each pair (`compare_frames`)."""
    camera = camera if camera is not None else lam_default_camera(size, size)
    if (camera.width, camera.height) != (size, size):
        camera = camera.resized(size, size)
    page_camera(camera, (size, size))  # refuse a camera three.js cannot draw before starting a browser
    check_web_layout(avatar)
    if motion is None:
        jobs = [("neutral", {})]
    else:
        try:
            track = load_motion(motion).weights  # the file's own frames, in ARKit order
        except DriveError as exc:
            raise ValueError(str(exc)) from None
        jobs = [(str(i), {n: float(w) for n, w in zip(ARKIT_BLENDSHAPES, track[i], strict=True)})
                for i in parse_frames(frames, len(track))]
    out.mkdir(parents=True, exist_ok=True)
    written, web_frames = [], []
    start = time.perf_counter()
    with LamWebRenderer(avatar, (size, size), background, cache_dir) as renderer:
        echo(f"loaded {avatar.name}: {renderer.info['splatCount']} splats, {len(renderer.info['morphTargets'])} "
             f"morph targets in {renderer.load_seconds:.1f} s")
        seconds = []
        for label, weights in jobs:
            tick = time.perf_counter()
            image = renderer.render(camera, weights_dict(weights))
            seconds.append(time.perf_counter() - tick)
            path = out / f"web_{label}.png"
            write_png(path, image)
            written.append(path)
            web_frames.append(image)
            echo(f"frame {label}: {seconds[-1]:.2f} s -> {path}")
    (out / "cameras.json").write_text(json.dumps(camera.to_dict(), indent=1))
    (out / "weights.json").write_text(json.dumps({
        "note": "raw ARKit weights handed to getExpressionData(); the renderer applies its motionConfig scale",
        "background": list(background), "size": [size, size],
        "frames": {label: weights for label, weights in jobs}}, indent=1))
    written += [out / "cameras.json", out / "weights.json"]
    echo(f"{len(jobs)} frame(s) in {time.perf_counter() - start:.1f} s (per frame {np.mean(seconds):.2f} s, "
         f"load {renderer.load_seconds:.1f} s)")
    if compare is not None:
        written += compare_frames(compare, out, jobs, web_frames, camera, background, echo)
    return written


# A pixel is compared as part of the head when either frame differs from the background by more than this many
# 8-bit levels: both renderers agree on the empty background exactly, which would otherwise inflate the PSNR.
HEAD_LEVELS = 2


def compare_frames(bundle: Path, out: Path, jobs: list[tuple[str, dict]], web_frames: list[np.ndarray],
                   camera: Camera, background: Sequence[float], echo: Callable[[str], None] = print) -> list[Path]:
    """The runtime's frames of the same weights (head at rest, as the harness holds the skeleton), camera and
    background against the web renderer's: PSNR over the frame and over the head, max error, per frame."""
    from gaussiantalker.runtime import HeadPose, TalkingHead

    rows, written = [], []
    bg = np.round(np.asarray(background) * 255).astype(np.int16)
    with TalkingHead(bundle, camera=camera, background=background) as head:
        for (label, weights), web in zip(jobs, web_frames, strict=True):
            ours = head.render_blendshapes(weights, head_pose=HeadPose.make())
            path = out / f"ours_{label}.png"
            write_png(path, ours)
            written.append(path)
            region = (np.abs(web.astype(np.int16) - bg).max(-1) > HEAD_LEVELS) | \
                (np.abs(ours.astype(np.int16) - bg).max(-1) > HEAD_LEVELS)
            error = np.abs(web.astype(np.int16) - ours.astype(np.int16))
            rows.append({"frame": label, "psnr_db": psnr_db(web, ours), "head_psnr_db": psnr_db(web[region],
                                                                                                 ours[region]),
                         "head_pixels": int(region.sum()), "max_error": int(error.max()),
                         "mean_head_error": float(error[region].mean()) if region.any() else 0.0})
            echo(f"frame {label}: PSNR {rows[-1]['psnr_db']:.2f} dB, head {rows[-1]['head_psnr_db']:.2f} dB "
                 f"({rows[-1]['head_pixels']} px), max error {rows[-1]['max_error']} levels")
    (out / "compare.json").write_text(json.dumps({"bundle": str(bundle), "head_levels": HEAD_LEVELS,
                                                  "frames": rows}, indent=1))
    written.append(out / "compare.json")
    return written
