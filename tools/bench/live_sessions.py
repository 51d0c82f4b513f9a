"""Live sessions measured (docs/bench/live/live.md): first-frame latency, agreement with offline frames, barge-in,
drift over a long session, and how many sessions one process sustains in real time.

Speech is the sample speech (samples/demo_speech.wav). A "real-time producer" pushes 20 ms chunks on a wall-clock
schedule, as a text-to-speech engine streaming at real time would; engines that run faster than real time only
make the latency smaller.
"""

from __future__ import annotations

import resource
import threading
import time
from pathlib import Path

import numpy as np

from gaussiantalker.runtime import IdleMotion, TalkingHead
from gaussiantalker.runtime.live_audio import SampleFifo
from gaussiantalker.sdk.audio import load_audio, resample

CHUNK_MS = 20.0
SPEECH = Path(__file__).resolve().parents[2] / "samples" / "demo_speech.wav"


def sample_speech(rate: int) -> np.ndarray:
    if not SPEECH.exists():
        raise FileNotFoundError(f"{SPEECH} is missing: the live benchmark runs from a source checkout")
    return load_audio(SPEECH, rate)


def percentile(values: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(values, dtype=np.float64), q))


def _push_real_time(live, audio: np.ndarray, rate: int, started: list[float],
                    stop: threading.Event | None = None) -> None:
    """Push `audio` in CHUNK_MS chunks on a wall-clock schedule until `stop` is set (the voice stops when the user
    barges in); `started` gets the first push's time."""
    step = int(rate * CHUNK_MS / 1000)
    begin = time.monotonic()
    started.append(begin)
    for k, start in enumerate(range(0, audio.shape[0], step)):
        delay = begin + k * CHUNK_MS / 1000 - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        if stop is not None and stop.is_set():
            return
        live.push(audio[start:start + step], rate)
    live.flush()


def first_frame_latency(head: TalkingHead, speech: np.ndarray, lookahead_ms: float, utterances: int) -> dict:
    """Paced session: an utterance of 1 s pushed at real time after each idle second; latency = the first push to
    the utterance's first speaking frame ready (rendered), per utterance."""
    latencies: list[float] = []
    rate = head.sample_rate
    with head.live(lookahead_ms=lookahead_ms, idle=IdleMotion(blink_ms=0)) as live:
        for k in range(utterances):
            start = int((0.3 + 1.1 * k) % max(0.1, speech.shape[0] / rate - 1.2) * rate)
            started: list[float] = []
            producer = threading.Timer(0.5, _push_real_time, (live, speech[start:start + rate], rate, started))
            producer.start()
            for frame in live.frames():
                if frame.speaking:
                    latencies.append(time.monotonic() - started[0])
                    break
            for frame in live.frames():  # let the utterance play out
                if not frame.speaking and live.queued_s == 0 and not producer.is_alive():
                    break
            producer.join()
        stats = live.stats
    return {"lookahead_ms": lookahead_ms, "utterances": utterances, "latency_ms": [1000 * t for t in latencies],
            "p50_ms": 1000 * percentile(latencies, 50), "p95_ms": 1000 * percentile(latencies, 95),
            "late_frames": stats.late_frames, "underruns": stats.underruns}


def agreement(head: TalkingHead, speech: np.ndarray, lookahead_ms: float) -> dict:
    """Free-running, 20 ms chunks read as they become ready: the jaw's correlation with the offline frames'
    (`head.driver.translate`), and the expression's RMS error relative to its offline spread."""
    expression, jaw_pose = head.driver.translate(speech)
    frames = []
    rate, step = head.sample_rate, int(head.sample_rate * CHUNK_MS / 1000)
    with head.live(lookahead_ms=lookahead_ms, paced=False, output=None) as live:
        for start in range(0, speech.shape[0], step):
            live.push(speech[start:start + step], rate)
            frames += live.poll()
        live.end()
        frames += list(live.frames())
    jaw = np.array([f.drive.flame_pose[6] for f in frames])
    live_expression = np.stack([f.drive.expression for f in frames])
    error = np.sqrt(np.mean((live_expression - expression) ** 2)) / max(float(expression.std()), 1e-12)
    return {"lookahead_ms": lookahead_ms, "jaw_r": float(np.corrcoef(jaw, jaw_pose[:, 0])[0, 1]),
            "jaw_max_error_rad": float(np.abs(jaw - jaw_pose[:, 0]).max()),
            "expression_rms_relative": float(error), "frames": len(frames)}


def barge_in(head: TalkingHead, speech: np.ndarray, trials: int, lookahead_ms: float = 160.0) -> dict:
    """Paced: speech pushed at real time; after ~1 s of speaking frames the app calls interrupt(); time from the
    call to the first frame on the idle face (expression and jaw exactly neutral: blinks off) being ready."""
    results, timeline = [], []
    rate = head.sample_rate
    for trial in range(trials):
        with head.live(lookahead_ms=lookahead_ms, idle=IdleMotion(blink_ms=0)) as live:
            stop = threading.Event()
            producer = threading.Thread(target=_push_real_time, args=(live, speech[: 4 * rate], rate, [], stop))
            producer.start()
            spoken, called, called_at = 0, None, 0
            for frame in live.frames():
                spoken += frame.speaking
                if called is None and spoken >= 25 + 3 * trial:
                    called, called_at = time.monotonic(), frame.index
                    stop.set()  # the app stops its voice and the face together
                    live.interrupt()
                elif called is not None and not frame.speaking and not frame.drive.expression.any() \
                        and not frame.drive.flame_pose[3:].any():
                    results.append(time.monotonic() - called)
                    timeline.append((frame.index - called_at) / head.fps)
                    break
            live.close()
            producer.join()
    return {"trials": trials, "ms": [1000 * t for t in results], "p50_ms": 1000 * percentile(results, 50),
            "max_ms": 1000 * max(results), "timeline_ms": [1000 * t for t in timeline],
            "timeline_max_ms": 1000 * max(timeline)}


def drift(head: TalkingHead, speech: np.ndarray, minutes: float, rate: int = 44100, seed: int = 0) -> dict:
    """Free-running, no rendering: `minutes` of speech and silences (0.2-3 s) at `rate` in random 5-50 ms chunks.
    The frame clock against the audio clock at the end, the shown audio against the pushed audio, and the
    jaw-to-loudness lag in the first and last minute; peak memory before and after."""
    rng = np.random.default_rng(seed)
    source = resample(speech, head.sample_rate, rate)
    pushed, shown_samples, mismatched = 0, 0, 0
    jaws, levels = [], []
    rss_start = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    total = int(minutes * 60 * rate)
    started = time.perf_counter()
    with head.live(paced=False, output=None, audio_rate=rate) as live:
        pending = SampleFifo()  # pushed samples not yet shown, to compare with what frames carry

        def take(frames):
            nonlocal shown_samples, mismatched
            for frame in frames:
                count = min(len(pending), frame.audio.shape[0])
                mismatched += int(not np.array_equal(frame.audio[:count], pending.take(count)))
                shown_samples += frame.audio.shape[0]
                jaws.append(float(frame.drive.flame_pose[6]))
                levels.append(float(np.sqrt(np.mean(frame.audio ** 2))))

        while pushed < total:
            part = source if rng.random() < 0.6 else np.zeros(int(rng.uniform(0.2, 3.0) * rate), np.float32)
            start = 0
            while start < part.shape[0]:
                size = int(rng.integers(rate // 200, rate // 20))
                chunk = part[start:start + size]
                live.push(chunk, rate)
                pending.append(chunk)
                pushed += chunk.shape[0]
                start += size
                take(live.poll())
        live.end()
        take(live.frames())
        frames = live.stats.frames
    seconds = time.perf_counter() - started
    minute = int(60 * head.fps)

    def lag(part: slice) -> int:
        a, b = np.array(jaws[part]), np.array(levels[part])
        a, b = a - a.mean(), b - b.mean()
        return int(np.argmax([np.dot(np.roll(a, k), b) for k in range(-5, 6)])) - 5

    return {"minutes": minutes, "rate": rate, "frames": frames, "pushed_s": pushed / rate,
            "frame_clock_s": frames / head.fps, "clock_gap_frames": frames - pushed / rate * head.fps,
            "shown_s": shown_samples / rate, "frames_with_other_audio": mismatched,
            "lag_first_minute": lag(slice(0, minute)), "lag_last_minute": lag(slice(len(jaws) - minute, len(jaws))),
            "max_rss_mb_before": rss_start / 1024, "max_rss_mb_after": resource.getrusage(
                resource.RUSAGE_SELF).ru_maxrss / 1024, "wall_s": seconds}


def sessions(bundle: Path, size: int, speech: np.ndarray, seconds: float, most: int, renderer: str = "gl") -> dict:
    """Sessions of one head rendered round-robin on one thread, free-running with their audio pushed: the
    aggregate frame rate for 1..most sessions, each session's p95 interval between its frames (the worst
    session's), and the largest count whose rate keeps every session at the speaker's fps (real time)."""
    rows = []
    with TalkingHead(bundle, resolution=(size, size), composite=False, renderer=renderer) as head:
        rate = head.sample_rate
        audio = speech[: int(seconds * rate)]
        head.render_params()  # warm the GL context
        for count in range(1, most + 1):
            sessions_ = [head.live(paced=False) for _ in range(count)]
            for live in sessions_:
                live.push(audio, rate)
                live.end()
            readers = {k: live.frames() for k, live in enumerate(sessions_)}
            arrivals: dict[int, list[float]] = {k: [] for k in readers}
            frames, started = 0, time.perf_counter()
            while readers:
                for k, reader in list(readers.items()):
                    if next(reader, None) is None:
                        del readers[k]
                    else:
                        frames += 1
                        arrivals[k].append(time.perf_counter())
            wall = time.perf_counter() - started
            p95 = max((percentile(list(np.diff(times) * 1000), 95) for times in arrivals.values() if len(times) > 1),
                      default=float("nan"))
            rows.append({"sessions": count, "fps_total": frames / wall, "fps_each": frames / wall / count,
                         "p95_interval_ms": p95, "real_time": frames / wall / count >= head.fps})
            for live in sessions_:
                live.close()
            if not rows[-1]["real_time"]:
                break
        sustained = max([row["sessions"] for row in rows if row["real_time"]], default=0)
        return {"size": size, "fps": head.fps, "rows": rows, "sustained": sustained}


def run_live_bench(bundle: Path, size: int, lookaheads: list[float], utterances: int, barge_trials: int,
                   drift_minutes: float, session_sizes: list[int], most_sessions: int, renderer: str = "gl") -> dict:
    """Everything docs/bench/live/live.md reports, in one run, with the `renderer` that splats ("gl", "cpu", "auto")."""
    with TalkingHead(bundle, resolution=(size, size), composite=False, renderer=renderer) as head:
        speech = sample_speech(head.sample_rate)
        head.render_params()
        started = time.perf_counter()
        for _ in range(10):
            head.render_params()
        result = {"bundle": str(bundle), "size": size, "fps": head.fps, "renderer": head.renderer,
                  "frame_ms": 1000 * (time.perf_counter() - started) / 10,
                  "latency": [first_frame_latency(head, speech, ms, utterances) for ms in lookaheads],
                  "agreement": [agreement(head, speech, ms) for ms in lookaheads],
                  "barge_in": barge_in(head, speech, barge_trials)}
        if drift_minutes > 0:
            result["drift"] = drift(head, speech, drift_minutes)
    result["sessions"] = [sessions(bundle, s, speech, 4.0, most_sessions, renderer) for s in session_sizes]
    return result


def live_tables(result: dict) -> str:
    """Markdown tables of `run_live_bench`'s result."""
    lines = [f"Latency and agreement at {result['size']}², {result['fps']} fps (a frame rendered in "
             f"{result['frame_ms']:.0f} ms on this machine, mean of 10):", "",
             "| lookahead | first frame p50 | p95 | jaw r vs offline | expression RMS / spread | late frames |",
             "|---:|---:|---:|---:|---:|---:|"]
    for lat, agr in zip(result["latency"], result["agreement"], strict=True):
        lines.append(f"| {lat['lookahead_ms']:.0f} ms | {lat['p50_ms']:.0f} ms | {lat['p95_ms']:.0f} ms | "
                     f"{agr['jaw_r']:.3f} | {agr['expression_rms_relative']:.3f} | {lat['late_frames']} |")
    barge = result["barge_in"]
    lines += ["", f"Barge-in (interrupt() to the first frame on the idle face ready, {barge['trials']} trials): "
              f"p50 {barge['p50_ms']:.0f} ms, max {barge['max_ms']:.0f} ms of wall time; "
              f"{barge['timeline_max_ms']:.0f} ms of the frame clock at most."]
    if "drift" in result:
        d = result["drift"]
        lines += ["", f"Drift over {d['minutes']:g} min ({d['frames']} frames, {d['pushed_s']:.1f} s pushed at "
                  f"{d['rate']} Hz, free-running, {d['wall_s']:.0f} s wall): frame clock - audio clock = "
                  f"{d['clock_gap_frames']:+.2f} frames; frames carrying other audio than pushed: "
                  f"{d['frames_with_other_audio']}; jaw-loudness lag {d['lag_first_minute']:+d} frames in the first "
                  f"minute, {d['lag_last_minute']:+d} in the last; peak memory {d['max_rss_mb_before']:.0f} -> "
                  f"{d['max_rss_mb_after']:.0f} MB."]
    for block in result["sessions"]:
        lines += ["", f"Sessions at {block['size']}² (one head, one thread, free-running): sustained in real time: "
                  f"{block['sustained']}", "",
                  "| sessions | total fps | fps each | p95 frame interval (worst session) |", "|---:|---:|---:|---:|"]
        lines += [f"| {r['sessions']} | {r['fps_total']:.1f} | {r['fps_each']:.1f} | "
                  f"{r.get('p95_interval_ms', float('nan')):.0f} ms |" for r in block["rows"]]
    return "\n".join(lines)
