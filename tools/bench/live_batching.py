"""Fewer translator calls in live sessions (docs/live.md, "Fewer translator calls: --batch-frames"): a voice made as
it is spoken (20 ms chunks) through `LiveSession(open_driver(bundle), paced=False, min_batch_frames=K)` per K, in
alternating rounds on one thread: translator calls, CPU seconds per second of speech (median of the rounds), and
how the drives follow the offline ones (jaw correlation, RMS parameter error)."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

CHUNK_S = 0.02


def _session(driver, speech: np.ndarray, batch: int, context_ms: float) -> tuple[np.ndarray, int, float]:
    """The drives' parameters [T, D] of `speech` pushed in CHUNK_S chunks, the translator calls, CPU seconds."""
    from gaussiantalker.runtime import LiveSession

    live = LiveSession(driver, output=None, paced=False, context_ms=context_ms, min_batch_frames=batch)
    step, frames = int(driver.sample_rate * CHUNK_S), []
    started = time.process_time()
    for first in range(0, speech.shape[0], step):
        live.push(speech[first:first + step], driver.sample_rate)
        frames += live.poll()
    live.end()
    frames += list(live.frames())
    cpu = time.process_time() - started
    params = np.stack([np.concatenate([f.drive.expression, f.drive.flame_pose[6:9]]) for f in frames])
    return params, live.stats.translator_calls, cpu


def run_live_batching(bundle: Path, speech: Path, batches: list[int], seconds: float, rounds: int,
                      context_ms: float = 1000.0) -> dict:
    from gaussiantalker.runtime import open_driver
    from gaussiantalker.sdk.audio import load_audio

    driver = open_driver(bundle, threads=1)
    if driver.rig != "flame":
        raise ValueError(f"{bundle}: a FLAME speaker with a translator is needed (this one is {driver.rig})")
    audio = load_audio(speech, driver.sample_rate)[: int(seconds * driver.sample_rate)]
    expression, jaw = driver.translate(audio)
    offline = np.concatenate([expression, jaw], axis=1)
    cpu: dict[int, list[float]] = {batch: [] for batch in batches}
    rows: dict[int, dict] = {}
    for _ in range(rounds):
        for batch in batches:  # alternating: each round runs every K once
            params, calls, seconds_used = _session(driver, audio, batch, context_ms)
            cpu[batch].append(seconds_used)
            rows[batch] = {"batch_frames": batch, "translator_calls": calls, "frames": int(params.shape[0]),
                           "jaw_r": float(np.corrcoef(params[:, -3], offline[:, -3])[0, 1]),
                           "rms_error": float(np.sqrt(np.mean((params - offline) ** 2)))}
    speech_s = audio.shape[0] / driver.sample_rate
    for batch, row in rows.items():
        row["cpu_ms_per_speech_s"] = 1000 * float(np.median(cpu[batch])) / speech_s
        row["cpu_ms_rounds"] = [1000 * c / speech_s for c in cpu[batch]]
    return {"rows": [rows[b] for b in batches], "speech_s": speech_s, "rounds": rounds, "context_ms": context_ms}


def live_batching_table(result: dict) -> str:
    lines = ["| K (`--batch-frames`) | translator calls | CPU per second of speech (median) | jaw r vs offline | "
             "RMS parameter error vs offline |", "|---:|---:|---:|---:|---:|"]
    for row in result["rows"]:
        lines.append(f"| {row['batch_frames']} | {row['translator_calls']} | {row['cpu_ms_per_speech_s']:.0f} ms | "
                     f"{row['jaw_r']:.3f} | {row['rms_error']:.3f} |")
    return "\n".join(lines)


__all__ = ["run_live_batching", "live_batching_table"]
