"""`gt-bench voice`: every audio driver on every family of voice, real human speech included, against the same
gates (exporter/voice/gates.py; what each measure is: docs/voice.md, "Measurements").

The drivers: the built-in ARKit and FLAME voice models (the committed ones, or `--arkit-model`/`--flame-model`) and
each `--bundle`'s own translator (the demo speaker's, measured on its Gaussians). The families: held-out espeak-ng
voices, festival and flite voices saying held-out sentences, the held-out festival diphone family, and the real
recordings fetched at install (`python -m gaussiantalker.exporter.voice.real_speech fetch`), aligned by
pocketsphinx. Also what that alignment alone costs the ARKit voice's score (families.aligned_twins) and each
driver's cost per second of audio on one core.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from gaussiantalker.exporter.voice import families, gates
from gaussiantalker.exporter.voice.mouths import ArkitVoice, BundleSpeaker, FlameVoice
from gaussiantalker.exporter.voice.paths import ARKIT_MODEL, FLAME_MODEL

COST_SECONDS, COST_ROUNDS = 10.0, 5


def drivers_of(arkit_model: Path, flame_model: Path, bundles: list[Path]) -> list:
    """The drivers under test, in table order."""
    return [ArkitVoice(arkit_model), FlameVoice(flame_model)] + [BundleSpeaker(b) for b in bundles]


def driver_cost(driver, seconds: float = COST_SECONDS, rounds: int = COST_ROUNDS) -> float:
    """Median wall seconds (one thread) per second of audio of the driver's own work (`run`: not the measuring) on
    a noise clip, after a warm-up."""
    audio = (0.1 * np.random.default_rng(0).standard_normal(int(seconds * 16000))).astype(np.float32)
    driver.run(audio)
    times = []
    for _ in range(rounds):
        start = time.perf_counter()
        driver.run(audio)
        times.append(time.perf_counter() - start)
    return float(np.median(times)) / seconds


def run_voice_bench(arkit_model: Path = ARKIT_MODEL, flame_model: Path = FLAME_MODEL, bundles: Sequence[Path] = (),
                    clips: int = 40, seed: int = 0, progress: bool = True, log=print) -> dict:
    """Clips of every family, every driver measured on them; the result `voice_table` prints."""
    start = time.perf_counter()
    clip_sets = families.synthetic_clips(clips, seed, progress=progress)
    real = families.real_clips()
    clip_sets["real"], clip_sets["real-unseen"] = real.clips, families.unseen_speakers(real)
    log(f"clips made in {time.perf_counter() - start:.0f} s: " +
        ", ".join(f"{name} {len(c)}" for name, c in clip_sets.items()))
    drivers = drivers_of(arkit_model, flame_model, list(bundles))
    table = gates.gate_table(drivers, clip_sets)
    table["alignment"] = real.alignment
    twins = families.aligned_twins(clips, seed, progress=progress)
    arkit = drivers[0]
    table["alignment_cost"] = {name: {**gates.alignment_cost(arkit, t.clips, t.aligned, table["channels"]),
                                      "unaligned": t.unaligned} for name, t in twins.items()}
    table["drivers"] = {d.name: {"ms_per_audio_second": 1000 * driver_cost(d)} for d in drivers}
    for name, model in (("ARKit voice", arkit_model), ("FLAME voice", flame_model)):
        table["drivers"][name]["model_mb"] = Path(model).stat().st_size / 1e6
    table["settings"] = {"clips_per_family": clips, "seed": seed, "goal_families": list(families.GOAL_FAMILIES),
                         "goals": {k: v[1] for k, v in gates.GOALS.items()}}
    return table


def _cell(value, digits: int = 3) -> str:
    if value is None or (isinstance(value, float) and np.isnan(value)):
        return "–"
    return f"{value:.{digits}f}"


def _mark(ok: bool | None) -> str:
    return "" if ok is None else (" ✓" if ok else " ✗")


def voice_table(result: dict) -> str:
    """The report's tables: per family and driver, the alignment of the real clips, the drivers' cost."""
    goals = result["settings"]["goal_families"]
    lines = ["| family | clips (s) | driver | mouth channels r (mean of 10) | /p b m/ closed | vowels open | "
             "jaw vs loudness r | lag (ms) |", "|---|---|---|---:|---:|---:|---:|---:|"]
    for family, entry in result["families"].items():
        label = f"**{family}** (goals)" if family in goals else family
        for k, (name, row) in enumerate(entry["rows"].items()):
            ok = row.get("passes", {}) if family in goals else {}
            first = (f"{label} | {entry['clips']} ({entry['seconds']:.0f})" if k == 0 else " | ")
            lines.append(
                f"| {first} | {name} | {_cell(row.get('mouth_r_mean'))}{_mark(ok.get('mouth_r'))} | "
                f"{_cell(row['closure_share'])} of {row['bilabial_onsets']}{_mark(ok.get('closure'))} | "
                f"{_cell(row['vowel_open_share'])} | {_cell(row['jaw_loudness_r_median'])}"
                f"{_mark(ok.get('jaw_loudness_r'))} | {_cell(row['lag_ms_median'], 1)}{_mark(ok.get('lag_ms'))} |")
    lines += ["", "Real recordings, aligned by pocketsphinx (mean score in nats per frame; squeezed = share of "
              "phones at the aligner's 3-frame minimum; poor = score below -3 or over 25% squeezed):", "",
              "| clip | s | speaker | mean score | squeezed | poor |", "|---|---:|---|---:|---:|---|"]
    for clip_id, quality in result["alignment"].items():
        lines.append(f"| {clip_id} | {quality['seconds']:.1f} | {quality['speaker']} | {quality['mean_score']:.2f} | "
                     f"{quality['squeezed']:.2f} | {'**poor**' if quality['poor'] else 'no'} |")
    lines += ["", "What the aligner alone costs (word-list sentences, targets from the engine's phone times and from "
              "pocketsphinx's alignment of the same audio; mean r of the ten channels over all frames):", "",
              "| family | clips (unaligned) | targets vs aligned targets r | ARKit voice vs engine targets | "
              "ARKit voice vs aligned targets |", "|---|---:|---:|---:|---:|"]
    for family, cost in result.get("alignment_cost", {}).items():
        if cost["clips"]:
            lines.append(f"| {family} | {cost['clips']} ({len(cost['unaligned'])}) | {cost['targets_r_mean']:.3f} | "
                         f"{cost['driver_r_engine']:.3f} | {cost['driver_r_aligned']:.3f} |")
    lines += ["", "| driver | one core, ms per s of audio | model file |", "|---|---:|---:|"]
    for name, cost in result["drivers"].items():
        size = f"{cost['model_mb']:.2f} MB" if "model_mb" in cost else "(in its bundle)"
        lines.append(f"| {name} | {cost['ms_per_audio_second']:.2f} | {size} |")
    lines += ["", "Channels: " + ", ".join(result["channels"]) + " (the ten mouth channels the espeak-ng held-out "
              "targets move most)."]
    return "\n".join(lines)


__all__ = ["drivers_of", "driver_cost", "run_voice_bench", "voice_table"]
