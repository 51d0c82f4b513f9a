"""`gt-bench blend-limit`: the CPU splatter's tile blending against what the same kernel does at full occupancy.

The blend's counting twin (`splat_frame(..., counts)` in runtime/splat/cpu.py: the same pixels) counts its work:
(Gaussian, tile) pairs, pixel-row pairs, blocks of 4 x 2 pixels tried and blended, and fragments blended (pixels
whose colour a Gaussian changed). For the demo speaker's neutral frame (the closed, opaque head) this bench reports
those counts and the drawing kernel's time per fragment, in core-nanoseconds (wall time x threads).

"What the machine's SIMD can do" is measured with the same kernel on a scene that fills every lane: `layers`
faint Gaussians, each covering the whole image, none of which stops a pixel (T stays above T_MIN). There every
block tried is blended and every lane of it is a fragment, and each row pair holds whole tiles' blocks, so the time per
fragment is the kernel's arithmetic at full occupancy. The gap between the two is what sparsity costs: rows and
blocks set up for few fragments, lanes that miss the ellipse, blocks skipped as stopped.

Cases alternate within each round and the order rotates, so a shared machine's noise falls on all of them.
"""

from __future__ import annotations

import numpy as np

from gaussiantalker.sdk.camera import Camera

# Pixels per block of the blend, and the columns of the report.
BLOCK_LANES = 8
COUNT_COLUMNS = ("pairs_visited", "row_pairs", "blocks_tried", "blocks_blended", "fragments")


def full_occupancy_scene(size: int, layers: int) -> tuple[tuple[np.ndarray, ...], Camera]:
    """(means, cov3d, rgb, opacity) of `layers` faint, image-filling Gaussians and the camera that sees them:
    alpha is 0.02 x exp(-r^2 / 2 sigma^2) with sigma the image size, so every pixel blends every layer and
    T >= 0.98^layers stays above T_MIN for layers <= 400."""
    if not 1 <= layers <= 400:
        raise ValueError(f"layers must be 1..400 (more would stop pixels), got {layers}")
    camera = Camera(size, size, float(size), float(size), size / 2.0, size / 2.0)
    depth = 2.0 + 1e-3 * np.arange(layers, dtype=np.float32)
    means = np.stack([np.zeros(layers), np.zeros(layers), depth], axis=1).astype(np.float32)
    sigma_world = depth  # sigma in pixels = fx * sigma_world / z = size
    cov3d = np.zeros((layers, 6), dtype=np.float32)
    cov3d[:, 0] = cov3d[:, 3] = cov3d[:, 5] = sigma_world ** 2
    rng = np.random.default_rng(0)
    rgb = rng.uniform(0.2, 0.8, (layers, 3)).astype(np.float32)
    opacity = np.full(layers, 0.02, dtype=np.float32)
    return (means, cov3d, rgb, opacity), camera


def _blend_seconds(rows: np.ndarray, camera: Camera) -> float:
    """The drawing kernel's blend time for one splat of prepared rows."""
    from gaussiantalker.runtime.splat.cpu import splat_frame

    return splat_frame(rows, camera)[2]


def _blend_counts(rows: np.ndarray, camera: Camera) -> dict[str, int]:
    """The counting twin's work totals for one splat of prepared rows."""
    from gaussiantalker.runtime.splat.cpu import BLEND_COUNTS, splat_frame

    counts = np.zeros(len(BLEND_COUNTS), dtype=np.int64)
    splat_frame(rows, camera, counts)
    return dict(zip(BLEND_COUNTS, (int(v) for v in counts), strict=True))


def run_blend_limit(gaussians: list[int], size: int, layers: int, threads: list[int], frames: int,
                    rounds: int) -> dict:
    """Counts and blend times per case and thread count; the report's rows."""
    import numba

    from gaussiantalker.exporter.demo.demo_speaker import make_demo_speaker
    from gaussiantalker.runtime.splat.cpu import CPUSplatter

    from .renderers import neutral_gaussians

    splatter = CPUSplatter()
    cases: dict[str, tuple[np.ndarray, Camera]] = {}
    for count in gaussians:
        speaker, _ = make_demo_speaker(count, train_seconds=0, progress=False)
        camera = speaker.camera.resized(size, size)
        prepared = splatter.prepare(*neutral_gaussians(speaker, camera), camera)
        label = f"{count // 1000}k" if count % 1000 == 0 else f"{count:,}"
        cases[f"demo head, {label} Gaussians"] = (prepared.rows, prepared.camera)
    arrays, camera = full_occupancy_scene(size, layers)
    prepared = splatter.prepare(*arrays, camera)
    cases[f"full occupancy, {layers} layers"] = (prepared.rows, prepared.camera)

    threads = [min(t, numba.config.NUMBA_NUM_THREADS) for t in threads]
    times: dict[tuple[str, int], list[float]] = {(name, t): [] for name in cases for t in threads}
    counts = {name: _blend_counts(rows, cam) for name, (rows, cam) in cases.items()}  # the same for any threads
    previous = numba.get_num_threads()
    try:
        for rows, cam in cases.values():  # warm: first-touch pages
            _blend_seconds(rows, cam)
        keys = list(times)
        for round_index in range(rounds):
            shift = round_index % len(keys)
            for name, t in keys[shift:] + keys[:shift]:
                numba.set_num_threads(t)
                rows, cam = cases[name]
                times[name, t] += [_blend_seconds(rows, cam) for _ in range(frames)]
    finally:
        numba.set_num_threads(previous)

    full_name = list(cases)[-1]
    result: dict = {"size": size, "frames": frames, "rounds": rounds, "threads": threads, "cases": []}
    for name in cases:
        c = counts[name]
        row = {"case": name, **c, "lanes_per_fragment": BLOCK_LANES * c["blocks_blended"] / max(c["fragments"], 1),
               "blend_ms": {}, "core_ns_per_fragment": {}}
        for t in threads:
            ms = 1000.0 * float(np.median(times[name, t]))
            row["blend_ms"][t] = ms
            row["core_ns_per_fragment"][t] = 1e6 * ms * t / max(c["fragments"], 1)
        result["cases"].append(row)
    full = result["cases"][-1]
    for row in result["cases"]:
        row["vs_full_occupancy"] = {t: row["core_ns_per_fragment"][t] / full["core_ns_per_fragment"][t]
                                    for t in threads}
    result["full_occupancy_case"] = full_name
    return result


def blend_limit_table(result: dict) -> str:
    """The report's markdown table: counts, then time per fragment per thread count."""
    threads = result["threads"]
    head = ["case", "pairs visited", "row pairs", "blocks tried", "blocks blended", "fragments", "lanes / fragment"]
    for t in threads:
        head += [f"blend ms, {t} thr", f"core ns / fragment, {t} thr", f"x full occupancy, {t} thr"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for row in result["cases"]:
        cells = [row["case"], *(f"{row[k]:,}" for k in COUNT_COLUMNS), f"{row['lanes_per_fragment']:.2f}"]
        for t in threads:
            cells += [f"{row['blend_ms'][t]:.2f}", f"{row['core_ns_per_fragment'][t]:.2f}",
                      f"{row['vs_full_occupancy'][t]:.2f}"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)

