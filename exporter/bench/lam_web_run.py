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


def load_motion(path: Path) -> tuple[list[str], list[list[float]]]:
    """(names, per-frame weights) of a LAM motion file: {"names": [...], "frames": [{"weights": [...]}, ...]}."""
    data = json.loads(Path(path).read_text())
    try:
        names = [str(n) for n in data["names"]]
        frames = [[float(w) for w in frame["weights"]] for frame in data["frames"]]
    except (KeyError, TypeError) as exc:
        raise ValueError(f"{path}: not a motion file with 'names' and 'frames[].weights' ({exc})") from exc
    for index, weights in enumerate(frames):
        if len(weights) != len(names):
            raise ValueError(f"{path}: frame {index} has {len(weights)} weights for {len(names)} names")
    return names, frames


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


def run_lam_web(avatar: Path, out: Path, motion: Path | None = None, frames: str = "0", size: int = 512,
                background: Sequence[float] = (1.0, 1.0, 1.0), camera: Camera | None = None,
                cache_dir: Path | None = None, echo: Callable[[str], None] = print) -> list[Path]:
    """Render the chosen motion frames (or the neutral face) to out/web_{frame}.png, cameras.json (the camera,
    Camera.to_dict()) and weights.json; `camera` defaults to the renderer's own at size x size."""
    camera = camera if camera is not None else lam_default_camera(size, size)
    if (camera.width, camera.height) != (size, size):
        camera = camera.resized(size, size)
    page_camera(camera, (size, size))  # refuse a camera three.js cannot draw before starting a browser
    if motion is None:
        jobs = [("neutral", {})]
    else:
        names, motion_frames = load_motion(motion)
        jobs = [(str(i), dict(zip(names, motion_frames[i], strict=True)))
                for i in parse_frames(frames, len(motion_frames))]
    out.mkdir(parents=True, exist_ok=True)
    written = []
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
            echo(f"frame {label}: {seconds[-1]:.2f} s -> {path}")
    (out / "cameras.json").write_text(json.dumps(camera.to_dict(), indent=1))
    (out / "weights.json").write_text(json.dumps({
        "note": "raw ARKit weights handed to getExpressionData(); the renderer applies its motionConfig scale",
        "background": list(background), "size": [size, size],
        "frames": {label: weights for label, weights in jobs}}, indent=1))
    written += [out / "cameras.json", out / "weights.json"]
    echo(f"{len(jobs)} frame(s) in {time.perf_counter() - start:.1f} s (per frame {np.mean(seconds):.2f} s, "
         f"load {renderer.load_seconds:.1f} s)")
    return written
