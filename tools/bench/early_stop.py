"""The GL splatter's experimental early stop of saturated pixels (RenderSettings.early_stop), measured on a speaker
(docs/numerics.md, "Early stop of saturated pixels").

Three measures, all through the runtime's own GLSplatter on the speaker's deformed Gaussians (front view, and
frames of its pose track):
* saturation: how many covered pixels have transmittance below TRANSMITTANCE_MIN (what the early stop skips) and
  below 1/255 after each fraction of the depth-sorted Gaussians;
* agreement: the early-stopped frame against the plain draw (max difference of the float frame and of the 8-bit
  frame, PSNR);
* speed: the draw stage (`GLSplatter.last_timings["draw"]`) of the plain draw and of each early-stop setting,
  alternating settings frame by frame within a round and the order of settings round by round, so that the
  shared machine's load falls on all of them alike; medians, and each setting's ratio to the plain draw.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import torch

from gaussiantalker.runtime.splat.common import PreparedSplats
from gaussiantalker.runtime.splat.gl import GLSplatter
from gaussiantalker.sdk.drive import FrameDrive, HeadPose
from gaussiantalker.sdk.numerics import TRANSMITTANCE_MIN
from gaussiantalker.sdk.render_settings import RenderSettings

SATURATION_FRACTIONS = (0.2, 0.4, 0.6, 0.8, 1.0)
SATURATED_8BIT = 1.0 / 255.0  # what lies behind can change the pixel by less than one 8-bit level
POSE_FRAMES = (0, 25, 50, 75, 100, 125)  # frames of the speaker's pose track measured beside the front view
BACKGROUND = (1.0, 1.0, 1.0)


@torch.no_grad()
def splat_inputs(speaker, size: int, pose_frame: int | None = None) -> tuple:
    """(means, cov3d, rgb, opacity, camera) of the speaker at rest (neutral expression), at size² with its camera,
    head posed as frame `pose_frame` of its pose track (None: the front view, no head pose)."""
    camera = speaker.camera.resized(size, size)
    head_pose = None
    if pose_frame is not None:
        row = speaker.pose_track[pose_frame % speaker.pose_track.shape[0]].numpy()
        head_pose = HeadPose.make(row[:3], row[3:6])
    drive = FrameDrive.make(speaker.config.n_expr, head_pose=head_pose)
    eye = torch.from_numpy(camera.center.astype(np.float32))[None]
    means, cov3d, rgb, opacity = speaker.deform_drive(drive, eye)
    return (means[0].numpy(), cov3d[0].numpy(), rgb[0].numpy(), opacity.numpy().reshape(-1), camera)


def prefix(splatter: GLSplatter, prepared: PreparedSplats, count: int) -> PreparedSplats:
    """The prepared frame cut to its first `count` depth-sorted Gaussians."""
    rows = prepared.rows[:count]
    return dataclasses.replace(prepared, rows=rows, runs=splatter.plan_runs(rows, prepared.camera))


def saturation(splatter: GLSplatter, inputs: tuple, fractions=SATURATION_FRACTIONS) -> dict:
    """Covered pixels (any Gaussian reaches them) and, after each fraction of the sorted Gaussians, how many of them
    have T < TRANSMITTANCE_MIN and T < 1/255."""
    prepared = splatter.prepare(*inputs)
    n = len(prepared.rows)
    final = splatter.draw(prepared, BACKGROUND, output="rgba_float")
    covered = final[..., 3] > 0.0
    result = {"gaussians_drawn": n, "covered": int(covered.sum()), "after": {}}
    for fraction in fractions:
        accumulated = splatter.draw(prefix(splatter, prepared, round(fraction * n)), BACKGROUND, output="rgba_float")
        transmittance = 1.0 - accumulated[..., 3].astype(np.float64)
        result["after"][f"{fraction:g}"] = {"t_min": int((transmittance < TRANSMITTANCE_MIN).sum()),
                                           "t_8bit": int((transmittance < SATURATED_8BIT).sum())}
    return result


def agreement(plain: GLSplatter, early: GLSplatter, inputs: tuple) -> dict:
    """The early-stopped frame against the plain one: max |difference| (float and 8-bit) and PSNR (dB, float)."""
    a = plain.render(*inputs, BACKGROUND, output="float")
    b = early.render(*inputs, BACKGROUND, output="float")
    diff = np.abs(a.astype(np.float64) - b)
    mse = float(np.mean(diff**2))
    a8 = plain.render(*inputs, BACKGROUND).astype(np.int32)
    b8 = early.render(*inputs, BACKGROUND).astype(np.int32)
    return {"max_abs": float(diff.max()), "changed_values": int((diff > 0).sum()),
            "psnr_db": float("inf") if mse == 0 else float(10 * np.log10(1.0 / mse)),
            "max_levels_8bit": int(np.abs(a8 - b8).max())}


def speed(splatters: dict[str, GLSplatter], frames: list[tuple], per_setting: int = 30, rounds: int = 3) -> dict:
    """Draw-stage milliseconds per setting: in each round every setting draws `per_setting` frames, interleaved
    frame by frame (settings in an order rotated each round), cycling through `frames` (each prepared once per
    setting); medians per round and overall, and the ratio plain / setting (above 1: faster than plain)."""
    names = list(splatters)
    prepared = {name: [s.prepare(*inputs) for inputs in frames] for name, s in splatters.items()}
    for name, s in splatters.items():  # warm-up: compile, allocate targets
        for p in prepared[name][:2]:
            s.draw(p, BACKGROUND)
    times: dict[str, list[list[float]]] = {name: [] for name in names}
    for r in range(rounds):
        order = names[r % len(names):] + names[:r % len(names)]
        for name in names:
            times[name].append([])
        for i in range(per_setting):
            for name in order:
                splatters[name].draw(prepared[name][i % len(frames)], BACKGROUND)
                times[name][-1].append(1000.0 * splatters[name].last_timings["draw"])
    medians = {name: float(np.median(np.concatenate(times[name]))) for name in names}
    base = medians[names[0]]
    return {name: {"draw_ms_median": medians[name],
                   "round_medians_ms": [float(np.median(t)) for t in times[name]],
                   "speedup_vs_plain": base / medians[name]} for name in names}


def run_early_stop_bench(speaker, sizes=(256, 512), settings=((0.5,), (0.3, 0.6), (0.4, 0.6, 0.8)),
                         per_setting: int = 30, rounds: int = 3, saturation_size: int = 512) -> dict:
    """Saturation (at saturation_size², front view and POSE_FRAMES), agreement and speed of each early-stop
    setting against the plain draw at each size."""
    started = time.perf_counter()
    plain = GLSplatter()
    early = {s: GLSplatter(plain.ctx, settings=RenderSettings(early_stop=tuple(s))) for s in settings}
    try:
        views = {"front": None, **{f"pose {f}": f for f in POSE_FRAMES}}
        sat = {label: saturation(plain, splat_inputs(speaker, saturation_size, frame))
               for label, frame in views.items()}
        result = {"gaussians": speaker.gaussians.count, "saturation_size": saturation_size, "saturation": sat,
                  "sizes": {}}
        for size in sizes:
            frames = [splat_inputs(speaker, size, f) for f in (None, *POSE_FRAMES)]
            agree = {str(list(s)): agreement(plain, e, frames[0]) for s, e in early.items()}
            speeds = speed({"plain": plain, **{str(list(s)): e for s, e in early.items()}}, frames, per_setting,
                           rounds)
            result["sizes"][str(size)] = {"agreement": agree, "speed": speeds}
    finally:
        for e in early.values():
            e.release()
        plain.release()
    result["seconds"] = time.perf_counter() - started
    return result


def early_stop_tables(result: dict) -> str:
    """Markdown tables of `run_early_stop_bench`'s result."""
    n = result["gaussians"]
    fractions = list(next(iter(result["saturation"].values()))["after"])
    lines = [f"Saturated covered pixels, {n} Gaussians at {result['saturation_size']}² "
             "(T < 1e-4 / T < 1/255 after each fraction of the depth-sorted Gaussians):", "",
             "| view | covered | " + " | ".join(f"after {float(f):.0%}" for f in fractions) + " |",
             "|---|---|" + "---|" * len(fractions)]
    for view, s in result["saturation"].items():
        cells = [f"{a['t_min']} / {a['t_8bit']}" for a in s["after"].values()]
        lines.append(f"| {view} | {s['covered']} | " + " | ".join(cells) + " |")
    lines += ["", "| size | setting | draw ms (median) | per-round medians | speed-up vs plain | max |diff| | "
              "max 8-bit levels | PSNR dB |", "|---|---|---|---|---|---|---|---|"]
    for size, r in result["sizes"].items():
        for name, s in r["speed"].items():
            a = r["agreement"].get(name)
            agree = "| — | — | — |" if a is None else (f"| {a['max_abs']:.2e} | {a['max_levels_8bit']} | "
                                                         f"{a['psnr_db']:.1f} |")
            rounds = ", ".join(f"{t:.1f}" for t in s["round_medians_ms"])
            lines.append(f"| {size}² | {name} | {s['draw_ms_median']:.2f} | {rounds} | "
                         f"{s['speedup_vs_plain']:.3f}× {agree}")
    return "\n".join(lines)
