"""`gt-bench translator-stream`: a speaker's Motion Translator streamed against its windowed live calls and its
offline drive, on unseen speech, per number of refreshed frames and of frames the transformers run again (the tail;
the whole window, or a K/V cache before the tail); and what a frame costs each way (docs/live.md, "The speaker's
own translator").

Quality: each clip (the held-out espeak-ng clip and every real recording `.ci/install` fetched) goes through the
torch modules as a live session would call them, a frame a call (or 8): the windowed translator on its window
(1 s of context, the frames, 160 ms of lookahead, zeros before the clip), the streaming module from its rest state.
Each is scored against the whole clip's offline drive: the mean correlation over the ten channels that move most
offline. Cost: the exported graphs in onnxruntime on one thread, sessions stacked on the batch axis as the live
server's pool stacks them, alternating, medians.
"""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

BUSIEST = 10
FRAME = 640

# (refreshed frames, tail frames (None: the transformers over the whole window)[, gated: the steady graph while the
# window's loudness holds, as live sessions call it])
Variant = tuple


def variant_label(variant: Variant) -> str:
    """A stream variant's column name: "stream, refresh 4" (whole window), "stream, refresh 4, tail 7", and
    ", gated" for the gated calls."""
    refresh, tail, *gated = variant
    return (f"stream, refresh {refresh}" + ("" if tail is None else f", tail {tail}")
            + (", gated" if gated and gated[0] else ""))


def stream_variants(refresh: list[int], tails: list[int | None], gated: bool = False) -> list[Variant]:
    """Every (refresh, tail) pair the stream accepts (a tail shorter than the refresh and the delay is not one);
    with `gated`, each refreshing one also gated."""
    from gaussiantalker.exporter.model.translator_stream import STREAM_DELAY_FRAMES

    pairs = [(r, t) for r in refresh for t in tails if t is None or t >= max(r + 1, STREAM_DELAY_FRAMES)]
    return pairs + ([(r, t, True) for r, t in pairs if r > 0] if gated else [])


def busiest_r(got: np.ndarray, reference: np.ndarray, channels: int = BUSIEST) -> float:
    """Mean correlation over the reference's busiest channels (largest variance; constant ones never count)."""
    variance = reference.var(axis=0)
    busiest = [c for c in np.argsort(variance)[::-1][:channels] if variance[c] > 1e-8]
    return float(np.mean([np.corrcoef(got[:, c], reference[:, c])[0, 1] for c in busiest]))


def _offline(translator, audio: np.ndarray) -> np.ndarray:
    with torch.no_grad():
        expression, jaw = translator(torch.from_numpy(audio[None]))
    return torch.cat([expression, jaw], -1)[0].numpy()


def _windowed(translator, audio: np.ndarray, batch: int, context: int, delay: int) -> np.ndarray:
    """Rows of a live session's windowed calls: for frames [p, p + batch), the window [p - context, p + batch +
    delay), zeros outside the clip."""
    frames = audio.shape[0] // FRAME
    padded = np.concatenate([np.zeros(context * FRAME, np.float32), audio, np.zeros((delay + batch) * FRAME,
                                                                                    np.float32)])
    rows = []
    with torch.no_grad():
        for p in range(0, frames, batch):
            window = padded[p * FRAME:(p + context + batch + delay) * FRAME]
            expression, jaw = translator(torch.from_numpy(window[None]))
            rows.append(torch.cat([expression, jaw], -1)[0, context:context + batch].numpy())
    return np.concatenate(rows)[:frames]


def _streamed(stream, audio: np.ndarray, batch: int, steady=None) -> tuple[np.ndarray, float]:
    """Rows of the streaming module fed `batch` frames a call from its rest state (the delay's zeros after), and
    the share of calls that refreshed: with a `steady` module, it runs the calls whose window's loudness held, as
    a live session's stream chooses (runtime/translate_stream.py)."""
    from gaussiantalker.runtime.translate_stream import (
        REFRESHED_FRAMES,
        REST_FRAMES,
        frame_power,
        loudness_moved,
        made_after,
        window_loudness,
    )

    frames, delay = audio.shape[0] // FRAME, stream.delay_frames
    fed = np.concatenate([audio, np.zeros((delay + batch) * FRAME, np.float32)]).reshape(-1, FRAME)
    rows, powers, made, refreshed = [], np.zeros(0), np.zeros(REFRESHED_FRAMES), []
    with torch.no_grad():
        state = stream(torch.zeros(1, REST_FRAMES, FRAME), torch.zeros(1, stream.state_size),
                       torch.tensor([float(REST_FRAMES)]))[2]
        for p in range(0, frames + delay, batch):
            powers = np.concatenate([powers, frame_power(fed[p:p + batch])])
            now = window_loudness(powers)
            refreshed.append(steady is None or loudness_moved(now, made))
            chunk = torch.from_numpy(fed[p:p + batch][None])
            made = made_after(made, chunk.shape[1], refreshed[-1], now)
            module = stream if refreshed[-1] else steady
            expression, jaw, state, _ = module(chunk, state, torch.tensor([float(chunk.shape[1])]))
            rows.append(torch.cat([expression, jaw], -1)[0].numpy())
    return np.concatenate(rows)[delay:delay + frames], float(np.mean(refreshed))


def unseen_clips() -> list[tuple[str, np.ndarray]]:
    """(name, 16 kHz audio cut to whole frames): the held-out espeak-ng clip, then the fetched real recordings."""
    from gaussiantalker.exporter.voice import real_speech
    from gaussiantalker.exporter.voice.data import load_utterance

    held_out = Path(__file__).resolve().parents[2] / "tests" / "data" / "voice_heldout"
    clips = [("held-out espeak-ng", load_utterance(held_out).audio)]
    clips += [(clip.id, clip.audio) for clip in real_speech.load()]
    return [(name, audio[:audio.shape[0] // FRAME * FRAME].astype(np.float32)) for name, audio in clips]


def run_quality(translator, variants: list[Variant], batches: list[int]) -> dict:
    """Per clip and mode, the busiest channels' r against offline; the means."""
    from gaussiantalker.exporter.model.translator_stream import MotionTranslatorStream

    translator = translator.eval()
    streams = {variant_label(v): (MotionTranslatorStream(translator, refresh_frames=v[0], tail_frames=v[1]).eval(),
                                  MotionTranslatorStream(translator, refresh_frames=v[0], tail_frames=v[1],
                                                         call_refresh=0).eval() if v[2:] and v[2] else None)
               for v in variants}
    first = next(iter(streams.values()))[0]
    context, delay = first.context_frames, first.delay_frames
    modes = [f"windowed, {b} a call" for b in batches] + [f"{label}, {b} a call"
                                                           for label in streams for b in batches]
    rows = []
    for name, audio in unseen_clips():
        offline = _offline(translator, audio)
        scores = {f"windowed, {b} a call": busiest_r(_windowed(translator, audio, b, context, delay), offline)
                  for b in batches}
        shares = {}
        for label, (stream, steady) in streams.items():
            for b in batches:
                streamed, shares[f"{label}, {b} a call"] = _streamed(stream, audio, b, steady)
                scores[f"{label}, {b} a call"] = busiest_r(streamed, offline)
        rows.append({"clip": name, "seconds": audio.shape[0] / 16000, "r": scores, "refreshed": shares})
    means = {mode: float(np.mean([row["r"][mode] for row in rows])) for mode in modes}
    refreshed = {mode: float(np.mean([row["refreshed"][mode] for row in rows])) for mode in modes
                 if mode in rows[0]["refreshed"]}
    return {"modes": modes, "clips": rows, "mean_r": means, "refreshed": refreshed, "context_frames": context,
            "delay_frames": delay}


def run_cost(translator, variants: list[Variant], cases: list[tuple[int, int]], rounds: int) -> list[dict]:
    """Per (sessions B, frames a call n): ms a session-frame of the windowed graph (B calls of one window) and of
    each streaming graph (one call, B stacked; and, where B is more than `sessions_per_call`, the live pool's calls
    of that many), onnxruntime on one thread, alternating rounds, medians."""
    import onnxruntime as ort

    from gaussiantalker.exporter.export.translator_graph import translator_onnx, translator_stream_onnx
    from gaussiantalker.exporter.model.translator_stream import MotionTranslatorStream
    from gaussiantalker.runtime.translate_stream import call_bounds, sessions_per_call

    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    windowed = ort.InferenceSession(translator_onnx(translator).SerializeToString(), options,
                                    providers=["CPUExecutionProvider"])
    streams = {}
    for refresh, tail, *gated in variants:
        call = 0 if gated and gated[0] else None  # a gated stream's steady graph: what most of its calls cost
        module = MotionTranslatorStream(translator.eval(), refresh_frames=refresh, tail_frames=tail,
                                        call_refresh=call)
        proto = translator_stream_onnx(translator, refresh_frames=refresh, tail_frames=tail, call_refresh=call)
        label = variant_label((refresh, tail, *gated)).replace(", gated", ", steady graph")
        streams[label] = (
            ort.InferenceSession(proto.SerializeToString(), options, providers=["CPUExecutionProvider"]),
            module.state_size, module.context_frames + module.delay_frames)
    rng = np.random.default_rng(0)
    out = []
    for sessions, n in cases:
        timings: dict[str, list[float]] = {}
        window_frames = next(iter(streams.values()))[2] + n
        window = (0.1 * rng.standard_normal((1, window_frames * FRAME))).astype(np.float32)
        audio = (0.1 * rng.standard_normal((sessions, n, FRAME))).astype(np.float32)
        for _ in range(rounds):
            start = time.perf_counter()
            for _ in range(sessions):
                windowed.run(None, {"audio": window})
            timings.setdefault("windowed", []).append(time.perf_counter() - start)
            for label, (session, size, _) in streams.items():
                state = np.zeros((sessions, size), np.float32)
                keep = np.array([n], np.float32)
                start = time.perf_counter()
                session.run(None, {"audio": audio, "state": state, "keep": keep})
                timings.setdefault(label, []).append(time.perf_counter() - start)
                step = sessions_per_call(size)
                if step < sessions:  # the live pool's split of a group too big for the caches (run_stream_jobs)
                    start = time.perf_counter()
                    for lo, hi in call_bounds(sessions, step):
                        session.run(None, {"audio": audio[lo:hi], "state": state[lo:hi], "keep": keep})
                    timings.setdefault(f"{label}, calls of at most {step}", []).append(time.perf_counter() - start)
        per_frame = {mode: 1000 * float(np.median(t)) / (sessions * n) for mode, t in timings.items()}
        out.append({"sessions": sessions, "frames_a_call": n, "ms_per_session_frame": per_frame})
    return out


def base_size_translator():
    """An untrained Motion Translator of wav2vec 2.0 BASE's size (the paper's encoder is LARGE, 24 layers of width
    1024): what a frame costs when the transformers, not the feature encoder, are most of a call."""
    from gaussiantalker.exporter.model.translator import MotionTranslator, paper_translator_config

    cfg = replace(paper_translator_config(), encoder_dim=768, encoder_layers=12, encoder_heads=12, encoder_ffn=3072)
    torch.manual_seed(0)
    return MotionTranslator(cfg, n_expr=50).eval()


def _cost_cell(values: dict[str, float], mode: str) -> str:
    """One cost cell: ms a session-frame and, for a stream, how many times less than the windowed graph."""
    if mode not in values:
        return "–"
    less = "" if mode == "windowed" else f" ({values['windowed'] / values[mode]:.1f}× less)"
    return f"{values[mode]:.3f}{less}"


def cost_table(rows: list[dict]) -> list[str]:
    """The cost rows as a table: ms a session-frame per mode, and how many times less than the windowed graph ("–"
    where a row has no such mode: the split calls exist only past `sessions_per_call`)."""
    modes = list(dict.fromkeys(mode for row in rows for mode in row["ms_per_session_frame"]))
    lines = ["| sessions | frames a call | " + " | ".join(f"{m} (ms a session-frame)" for m in modes) + " |",
             "|---:|---:|" + "---:|" * len(modes)]
    for row in rows:
        lines.append(f"| {row['sessions']} | {row['frames_a_call']} | "
                     + " | ".join(_cost_cell(row["ms_per_session_frame"], m) for m in modes) + " |")
    return lines


def translator_stream_table(result: dict) -> str:
    """The quality table (per clip, then the mean) and the cost table."""
    quality, modes = result["quality"], result["quality"]["modes"]
    lines = ["| clip | s | " + " | ".join(modes) + " |", "|---|---:|" + "---:|" * len(modes)]
    for row in quality["clips"]:
        lines.append(f"| {row['clip']} | {row['seconds']:.1f} | "
                     + " | ".join(f"{row['r'][m]:.3f}" for m in modes) + " |")
    lines.append("| **mean** | | " + " | ".join(f"**{quality['mean_r'][m]:.3f}**" for m in modes) + " |")
    refreshed = quality.get("refreshed", {})
    if any(share < 1 for share in refreshed.values()):
        lines.append("| calls that refreshed | | " + " | ".join(
            f"{refreshed[m]:.0%}" if m in refreshed else "" for m in modes) + " |")
    lines.append("")
    lines.append(f"The ten channels that move most offline, their mean r against the whole clip's drive; a live "
                 f"window holds {quality['context_frames']} frames of context and {quality['delay_frames']} of "
                 "lookahead.")
    lines += ["", *cost_table(result["cost"])]
    if result.get("cost_base_size"):
        lines += ["", "An untrained translator of wav2vec 2.0 BASE's size (12 transformer layers of width 768, 512 "
                  "convolution channels; its cost only):", "", *cost_table(result["cost_base_size"])]
    return "\n".join(lines)
