"""`gt-bench framing`: how imported avatars sit in their bundle's frame, the source's camera against portrait framing
(docs/import.md, "Portrait framing"):

    gt-bench framing p2-1.zip concierge.zip /tmp/ga20k/avatar --flame /tmp/ga20k/flame.npz --out docs/bench/framing

Per avatar and camera: the head's box (the importer's own, recorded in the checkpoint's source) as a fraction of
the frame's height, its centre's offset from the frame's centre, and the share of the 512x512 frame the avatar covers
(runtime frame of the rest pose, alpha above 1/255); and a PNG of both frames side by side (256x256 each). With
`--rounds N`, what each framing costs to draw: the rest pose's frame drawn FRAMES times per round by the default
renderer (`TalkingHead`, renderer "auto"), the two cameras' bundles alternating, median ms a frame.
"""

from __future__ import annotations

import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from gaussiantalker.exporter.export.bundle_export import export_bundle
from gaussiantalker.exporter.imports.portrait import box_height_fill, projected
from gaussiantalker.sdk.camera import Camera

CAMERAS = ("source", "portrait")
ALPHA_FLOOR = 1.0 / 255.0
THUMBNAIL = 256  # each frame's side in the PNGs
FRAMES = 40  # frames drawn per timing round (the first WARMUP left out)
WARMUP = 5


def import_avatar(path: Path, camera: str, flame: Path | None):
    """The avatar at `path` (a LAM zip, or a GaussianAvatars folder with `flame`) imported with `camera`."""
    if path.suffix.lower() == ".zip":
        from gaussiantalker.exporter.imports.sources.lam import LamOptions, import_lam

        return import_lam(path, LamOptions(camera=camera), progress=False)
    from gaussiantalker.exporter.imports.sources.gaussian_avatars import GaussianAvatarsOptions, import_gaussian_avatars

    if flame is None:
        raise ValueError(f"{path}: a GaussianAvatars avatar needs --flame")
    return import_gaussian_avatars(path, flame, GaussianAvatarsOptions(camera=camera))


def box_centre_offset(camera: Camera, low: np.ndarray, high: np.ndarray) -> float:
    """How far the box's projected centre lies from the frame's centre, as a fraction of the frame's height."""
    x, y = projected(camera, (np.asarray(low) + np.asarray(high)) / 2.0)[0]
    return float(np.hypot(x - camera.width / 2.0, y - camera.height / 2.0) / camera.height)


def rest_frames(bundle: Path) -> tuple[np.ndarray, np.ndarray]:
    """The runtime's frame of the avatar at rest (neutral weights or parameters, no head motion): RGBA float and
    uint8 RGB over the bundle's background."""
    from gaussiantalker.runtime import TalkingHead

    head = TalkingHead(bundle)
    drive = head.driver.drive()
    return (np.asarray(head.frame_renderer.frame(drive, "rgba_float")),
            np.asarray(head.frame_renderer.frame(drive, "uint8")))


def frame_ms(bundles: dict[str, Path], rounds: int) -> dict[str, float]:
    """Median ms a frame of each bundle's rest pose, drawn by the default renderer in alternating rounds."""
    from gaussiantalker.runtime import TalkingHead

    heads = {name: TalkingHead(path) for name, path in bundles.items()}
    times: dict[str, list[float]] = {name: [] for name in heads}
    try:
        for _ in range(rounds):
            for name, head in heads.items():
                drive = head.driver.drive()
                for index in range(FRAMES):
                    start = time.perf_counter()
                    head.frame_renderer.frame(drive, "uint8")
                    if index >= WARMUP:
                        times[name].append(time.perf_counter() - start)
    finally:
        for head in heads.values():
            head.close()
    return {name: 1e3 * statistics.median(values) for name, values in times.items()}


def measure_avatar(path: Path, flame: Path | None, work: Path, rounds: int = 0) -> tuple[dict, list[np.ndarray]]:
    """One avatar's row per camera and its two rest frames (uint8 RGB); `rounds` > 0 also times both framings."""
    rows, images, bundles = {}, [], {}
    work.mkdir(parents=True, exist_ok=True)
    for camera_name in CAMERAS:
        speaker = import_avatar(path, camera_name, flame)
        low, high = (np.asarray(v) for v in speaker.source["head_box"])
        bundles[camera_name] = export_bundle(speaker, work / f"{camera_name}.gtb", progress=False).path
        frame, image = rest_frames(bundles[camera_name])
        alpha = frame[..., 3]
        camera = speaker.camera
        rows[camera_name] = {"head_box_height": box_height_fill(camera, low, high),
                             "head_box_centre_offset": box_centre_offset(camera, low, high),
                             "covered": float((alpha > ALPHA_FLOOR).mean()),
                             "fov_y_deg": float(np.degrees(2 * np.arctan(camera.height / 2 / camera.fy)))}
        images.append(image)
    if rounds:
        for camera_name, ms in frame_ms(bundles, rounds).items():
            rows[camera_name]["frame_ms"] = ms
    return rows, images


def avatar_label(path: Path) -> str:
    """A zip's file name, or a folder's parent/name (GaussianAvatars folders are often all called the same)."""
    return path.name if path.is_file() else f"{path.resolve().parent.name}/{path.name}"


def run_framing(avatars: list[Path], flame: Path | None, out: Path | None, rounds: int = 0) -> dict:
    """Every avatar measured with both cameras (`rounds` > 0: timed too); the side-by-side PNGs written to `out`
    when given."""
    from PIL import Image

    result = {}
    with tempfile.TemporaryDirectory() as work:
        for index, path in enumerate(avatars):
            label = avatar_label(path)
            rows, images = measure_avatar(path, flame, Path(work) / str(index), rounds)
            result[label] = rows
            if out is not None:
                out.mkdir(parents=True, exist_ok=True)
                strip = Image.fromarray(np.concatenate(images, axis=1))
                strip.thumbnail((2 * THUMBNAIL, THUMBNAIL))
                strip.save(out / f"{label.replace('/', '-')}.png")
    return result


def framing_table(result: dict) -> str:
    """The markdown table: per avatar, each camera's head box height, centre offset and covered share."""
    lines = ["| avatar | head box height, source | portrait | centre offset, source | portrait | frame covered, "
             "source | portrait |", "|---|---:|---:|---:|---:|---:|---:|"]
    for name, rows in result.items():
        if name in ("machine", "command"):
            continue
        source, portrait = rows["source"], rows["portrait"]
        lines.append(f"| {name} | {source['head_box_height']:.1%} | **{portrait['head_box_height']:.1%}** | "
                     f"{source['head_box_centre_offset']:.1%} | {portrait['head_box_centre_offset']:.1%} | "
                     f"{source['covered']:.1%} | {portrait['covered']:.1%} |")
    timed = [name for name, rows in result.items() if isinstance(rows, dict) and "frame_ms" in rows.get("portrait", {})]
    if timed:
        lines += ["", "| avatar | ms a frame, source camera | portrait | portrait / source |", "|---|---:|---:|---:|"]
        for name in timed:
            source, portrait = result[name]["source"]["frame_ms"], result[name]["portrait"]["frame_ms"]
            lines.append(f"| {name} | {source:.2f} | {portrait:.2f} | {portrait / source:.2f}× |")
    return "\n".join(lines)


__all__ = ["box_centre_offset", "framing_table", "measure_avatar", "run_framing"]
