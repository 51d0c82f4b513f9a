"""Live sessions' translator cost and accuracy (docs/live.md, "Fewer translator calls: --batch-frames" and "Streaming
translators"): a voice made as it is spoken (20 ms chunks) through `LiveSession(open_driver(bundle), paced=False)`
per mode (windowed with K frames per call at least, or each of the bundle's streams) and lookahead, in alternating
rounds on one thread: translator calls, CPU seconds per second of speech (median of the rounds), and how the drives
follow the offline ones (the ten busiest mouth channels' mean r, the jaw's r, RMS parameter error)."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

CHUNK_S = 0.02
BUSIEST = 10  # channels compared: the ten that move most offline (ARKit: of the mouth and jaw channels)


def _params(driver, frame) -> np.ndarray:
    drive = frame.drive
    if driver.rig == "flame":
        return np.concatenate([drive.expression, drive.flame_pose[6:9]])
    return np.asarray(drive.blendshapes, np.float32)


def _session(driver, speech: np.ndarray, mode: str, lookahead_ms: float, context_ms: float
             ) -> tuple[np.ndarray, int, float]:
    """The drives' parameters [T, D] of `speech` pushed in CHUNK_S chunks, the translator calls, CPU seconds. `mode`:
    "K=<frames>" (windowed), "stream" (the main stream) or "stream:<ms>" (the stream whose rows lag so)."""
    from gaussiantalker.runtime import LiveSession

    streaming = mode.startswith("stream")
    batch = 1 if streaming else int(mode.removeprefix("K="))
    delay_ms = float(mode.split(":")[1]) if ":" in mode else None
    live = LiveSession(driver, output=None, paced=False, context_ms=context_ms, min_batch_frames=batch,
                       lookahead_ms=lookahead_ms, streaming=streaming, stream_delay_ms=delay_ms)
    step, frames = int(driver.sample_rate * CHUNK_S), []
    started = time.process_time()
    for first in range(0, speech.shape[0], step):
        live.push(speech[first:first + step], driver.sample_rate)
        frames += live.poll()
    live.end()
    frames += list(live.frames())
    cpu = time.process_time() - started
    return np.stack([_params(driver, f) for f in frames]), live.stats.translator_calls, cpu


def _mouth_columns(driver, offline: np.ndarray) -> np.ndarray:
    """The BUSIEST columns that move most offline (an ARKit rig's among its mouth and jaw channels)."""
    candidates = np.arange(offline.shape[1])
    if driver.rig != "flame":
        from gaussiantalker.sdk.rig import ARKIT_BLENDSHAPES

        candidates = np.array([k for k, name in enumerate(ARKIT_BLENDSHAPES) if name.startswith(("mouth", "jaw"))])
    return candidates[np.argsort(-offline[:, candidates].std(axis=0))[:BUSIEST]]


def run_live_batching(bundle: Path, speech: Path, batches: list[int], seconds: float, rounds: int,
                      context_ms: float = 1000.0, streaming: bool = False,
                      lookaheads: tuple[float, ...] = (160.0,)) -> dict:
    """Every mode (K per `batches`, and each stream where asked) at every lookahead, `rounds` alternating rounds."""
    from gaussiantalker.runtime import open_driver
    from gaussiantalker.sdk.audio import load_audio

    driver = open_driver(bundle, threads=1)
    if streaming and not driver.has_stream:
        raise ValueError(f"{bundle}: its translator has no streaming graph (docs/live.md, \"Streaming translators\")")
    audio = load_audio(speech, driver.sample_rate)[: int(seconds * driver.sample_rate)]
    offline = driver.translate(audio)
    offline = np.concatenate(offline, axis=1) if isinstance(offline, tuple) else offline
    jaw = offline.shape[1] - 3 if driver.rig == "flame" else _arkit_index("jawOpen")
    mouth = _mouth_columns(driver, offline)
    modes = [f"K={b}" for b in batches] + (["stream"] if streaming else [])
    if streaming:  # the other streams (a trained speaker's short one), by how far their rows lag
        modes += [f"stream:{spec.delay_ms(driver.sample_rate):g}" for spec in driver.stream_specs[1:]]
    cases = [(mode, lookahead) for lookahead in lookaheads for mode in modes]
    cpu: dict[tuple, list[float]] = {case: [] for case in cases}
    rows: dict[tuple, dict] = {}
    for _ in range(rounds):
        for mode, lookahead in cases:  # alternating: each round runs every case once
            params, calls, seconds_used = _session(driver, audio, mode, lookahead, context_ms)
            cpu[(mode, lookahead)].append(seconds_used)
            count = min(params.shape[0], offline.shape[0])
            got, want = params[:count], offline[:count]
            rows[(mode, lookahead)] = {
                "mode": mode, "batch_frames": 1 if mode.startswith("stream") else int(mode.removeprefix("K=")),
                "lookahead_ms": lookahead, "translator_calls": calls, "frames": int(params.shape[0]),
                "mouth_r": float(np.mean([np.corrcoef(got[:, k], want[:, k])[0, 1] for k in mouth])),
                "jaw_r": float(np.corrcoef(got[:, jaw], want[:, jaw])[0, 1]),
                "rms_error": float(np.sqrt(np.mean((got - want) ** 2)))}
    speech_s = audio.shape[0] / driver.sample_rate
    for case, row in rows.items():
        row["cpu_ms_per_speech_s"] = 1000 * float(np.median(cpu[case])) / speech_s
        row["cpu_ms_rounds"] = [1000 * c / speech_s for c in cpu[case]]
    return {"rows": [rows[c] for c in cases], "speech_s": speech_s, "rounds": rounds, "context_ms": context_ms,
            "rig": driver.rig, "mouth_channels": [int(k) for k in mouth]}


def _arkit_index(name: str) -> int:
    from gaussiantalker.sdk.rig import ARKIT_BLENDSHAPES

    return ARKIT_BLENDSHAPES.index(name)


def live_batching_table(result: dict) -> str:
    lines = ["| translator | lookahead | translator calls | CPU per second of speech (median) | mouth channels r vs "
             "offline | jaw r vs offline | RMS parameter error vs offline |", "|---|---:|---:|---:|---:|---:|---:|"]
    for row in result["rows"]:
        mode = row.get("mode", f"K={row.get('batch_frames')}")
        name = f"windowed, `--batch-frames {mode.removeprefix('K=')}`"
        if mode.startswith("stream"):
            name = f"streaming, the {mode.split(':')[1]} ms stream" if ":" in mode else "streaming"
        lines.append(f"| {name} | {row.get('lookahead_ms', 160):g} ms | {row['translator_calls']} | "
                     f"{row['cpu_ms_per_speech_s']:.1f} ms | {row.get('mouth_r', float('nan')):.3f} | "
                     f"{row['jaw_r']:.3f} | {row['rms_error']:.3f} |")
    return "\n".join(lines)


__all__ = ["run_live_batching", "live_batching_table"]
