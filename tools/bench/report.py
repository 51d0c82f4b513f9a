"""`gt-bench sweep` output: the markdown table, the goals check, and the plot (matplotlib, the `bench` extra)."""

from __future__ import annotations

import math
from pathlib import Path

from .sweep import REFERENCE, SpeakerSweep
from .worker import STAGES

# The preset goals (docs/precision.md): bundle at least this many times smaller than fp32, head-region PSNR against
# the fp32 frames at least this, frame rate at 512x512 at least this many times the fp32 bundle's.
GOALS = {
    "balanced": {"smaller": 5.0, "head_psnr_db": 47.0},
    "compact": {"smaller": 14.0, "head_psnr_db": 36.0},
    "fast": {"fps_ratio": 2.0, "head_psnr_db": 35.0},
    "mobile": {"fps_ratio": 1.3, "head_psnr_db": 40.0},
}
PLOT_PSNR_CAP_DB = 80.0  # identical frames (infinite PSNR) are drawn here


def _db(value: float) -> str:
    return "∞" if math.isinf(value) else f"{value:.1f}"


def _largest(sweep: SpeakerSweep) -> str:
    return max(next(iter(sweep.cases.values()))["sizes"], key=int)


def pareto_front(points: dict[str, tuple[float, float]]) -> set[str]:
    """Names of the points (cost, quality) that no other point beats: lower-or-equal cost and higher-or-equal
    quality, one of them strictly."""
    front = set()
    for name, (cost, quality) in points.items():
        if not any((c <= cost and q >= quality) and (c < cost or q > quality)
                   for other, (c, q) in points.items() if other != name):
            front.add(name)
    return front


def format_sweep(sweep: SpeakerSweep) -> str:
    """One speaker's table: a row per case, quality and stages at the largest size, FPS at every size."""
    sizes = sorted(next(iter(sweep.cases.values()))["sizes"], key=int)
    big = sizes[-1]
    reference_bytes = sweep.cases[REFERENCE]["bundle_bytes"]
    whole_reference = sweep.cases[REFERENCE].get("whole_bytes")
    head = ["case", "bundle MB", "× smaller", *(["whole file MB (× smaller)"] if whole_reference else []),
            "Gaussians", "load s", "peak MB",
            f"ms/stage {big}² (" + " / ".join(STAGES) + ")",
            *[f"FPS {s}²" for s in sizes], f"× FPS {big}²", f"head PSNR / SSIM {big}²",
            f"mouth PSNR / SSIM {big}²", "FLAME max err"]
    lines = [f"### {sweep.speaker} ({sweep.gaussians:,} Gaussians)", "",
             "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, case in sweep.cases.items():
        at = case["sizes"][big]
        quality = at["quality"]
        label = f"**{name}**" if case["preset"] else name
        whole = case.get("whole_bytes")
        whole_cell = [f"{whole / 1e6:.2f} ({whole_reference / whole:.1f})" if whole else ""] if whole_reference else []
        cells = [label, f"{case['bundle_bytes'] / 1e6:.2f}", f"{reference_bytes / case['bundle_bytes']:.1f}",
                 *whole_cell, f"{case['gaussians']:,}", f"{at['load_s']:.2f}", f"{case['peak_rss_mb']:.0f}",
                 " / ".join(f"{at['stages_ms'][s]:.1f}" for s in STAGES),
                 *[f"{case['sizes'][s]['fps']:.1f}" for s in sizes], f"{at['fps_vs_reference']:.2f}",
                 f"{_db(quality['head_psnr_db'])} / {quality['head_ssim']:.4f}",
                 f"{_db(quality['mouth_psnr_db'])} / {quality['mouth_ssim']:.4f}", f"{quality['flame_max_abs']:.1e}"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def goal_rows(sweep: SpeakerSweep) -> list[dict]:
    """Each preset goal: measured value, target, and whether it is met (by how much it is missed). The size goal
    is on the whole file where the sweep weighed it (`whole_bytes`), else on the bare head's bundle."""
    big = _largest(sweep)
    size_key = "whole_bytes" if sweep.cases[REFERENCE].get("whole_bytes") else "bundle_bytes"
    reference_bytes = sweep.cases[REFERENCE][size_key]
    rows = []
    for preset, targets in GOALS.items():
        case = sweep.cases.get(preset)
        if case is None:
            continue
        measured = {"smaller": reference_bytes / case[size_key],
                    "head_psnr_db": case["sizes"][big]["quality"]["head_psnr_db"],
                    "fps_ratio": case["sizes"][big]["fps_vs_reference"]}
        for key, target in targets.items():
            rows.append({"preset": preset, "goal": key, "target": target, "measured": measured[key],
                         "met": measured[key] >= target, "whole_file": size_key == "whole_bytes"})
    return rows


def format_goals(sweep: SpeakerSweep) -> str:
    names = {"smaller": "bundle × smaller", "head_psnr_db": "head PSNR dB", "fps_ratio": "× FPS at 512²"}
    lines = ["| preset | goal | target | measured | |", "|---|---|---|---|---|"]
    for row in goal_rows(sweep):
        verdict = "met" if row["met"] else f"missed by {row['target'] - row['measured']:.2f}"
        name = "whole file × smaller" if row["goal"] == "smaller" and row["whole_file"] else names[row["goal"]]
        lines.append(f"| {row['preset']} | {name} | ≥ {row['target']:g} | {row['measured']:.2f} | "
                     f"{verdict} |")
    return "\n".join(lines)


def format_report(sweeps: list[SpeakerSweep], machine: dict, command: str) -> str:
    """The whole markdown report: machine, command, then per speaker its goals and its table."""
    lines = ["# gt-bench sweep", "", f"Command: `{command}`", "",
             "Machine: " + ", ".join(f"{k} {v}" for k, v in machine.items()), ""]
    for sweep in sweeps:
        lines += [format_sweep(sweep), "", "Goals (largest size):", "", format_goals(sweep), ""]
    return "\n".join(lines)


def plot_sweep(sweeps: list[SpeakerSweep], path: Path) -> Path:
    """PNG: per speaker, frame time vs head PSNR and bundle size vs head PSNR at the largest size, the Pareto
    front joined, presets labelled. Needs matplotlib (`pip install gaussiantalker-sdk[bench]`)."""
    import matplotlib
    import matplotlib.ticker

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(len(sweeps), 2, figsize=(12, 4.5 * len(sweeps)), squeeze=False)
    for row, sweep in zip(axes, sweeps, strict=True):
        big = _largest(sweep)
        psnr = {n: min(c["sizes"][big]["quality"]["head_psnr_db"], PLOT_PSNR_CAP_DB) for n, c in sweep.cases.items()}
        cases = sweep.cases.items()
        exported = {n: c for n, c in cases if c["preset"] or not c["runtime"]}  # runtime knobs: the fp32 bundle
        panels = [(f"frame ms at {big}² (pipelined)", {n: c["sizes"][big]["frame_ms"] for n, c in cases}, False),
                  ("bundle MB (log scale; runtime knobs left out)",
                   {n: c["bundle_bytes"] / 1e6 for n, c in exported.items()}, True)]
        for axis, (xlabel, cost, log_scale) in zip(row, panels, strict=True):
            points = {n: (cost[n], psnr[n]) for n in cost}
            front = sorted(pareto_front(points), key=lambda n: points[n][0])
            axis.scatter([p[0] for p in points.values()], [p[1] for p in points.values()], s=14, color="0.55",
                         label="knob alone")
            axis.plot([points[n][0] for n in front], [points[n][1] for n in front], "-o", color="tab:blue", ms=4,
                      label="Pareto front")
            for name in points:
                if sweep.cases[name]["preset"]:
                    axis.scatter(*points[name], s=50, color="tab:red", zorder=3)
                    axis.annotate(name, points[name], textcoords="offset points", xytext=(5, 4), fontsize=9,
                                  color="tab:red")
                elif name in front:
                    axis.annotate(name, points[name], textcoords="offset points", xytext=(4, -9), fontsize=7,
                                  color="tab:blue")
            if log_scale:
                axis.set_xscale("log")
                plain = matplotlib.ticker.FuncFormatter(lambda value, _: f"{value:g}")
                axis.xaxis.set_major_formatter(plain)
                axis.xaxis.set_minor_formatter(plain)
            axis.set_xlabel(xlabel)
            axis.set_ylabel(f"head PSNR vs fp32, dB (min over clip; ∞ drawn at {PLOT_PSNR_CAP_DB:g})")
            axis.set_title(f"{sweep.speaker}, {sweep.gaussians:,} Gaussians")
            axis.grid(alpha=0.3)
            axis.legend(fontsize=8, loc="lower right")
    figure.tight_layout()
    from gaussiantalker.sdk.files import atomic_path

    with atomic_path(path) as staged:
        figure.savefig(staged.path, dpi=110, format="png")
    plt.close(figure)
    return path
