"""How well the voice model does, on speech it never heard (docs/voice.md, "Measurements"; the committed figures:
docs/bench/voice/).

Each held-out clip is an espeak-ng utterance (a held-out voice, a sentence of the held-out stream) with LEAD_S of
silence before it and TAIL_S after, whose phoneme targets are computed as in training. Measures:
* agreement: Pearson r per ARKit channel between the model and the targets over all held-out frames, for the
  TOP_CHANNELS mouth channels the targets move most (largest standard deviation);
* closure: the share of /p b m/ onsets (a run of bilabials counts once) at which the lips close: the aperture
  jawOpen - mouthClose (ARKit's mouthClose shuts the lips on an open jaw) falls to CLOSED_APERTURE or below in some
  frame from one frame before the onset's frame to one frame after the run's last frame;
* jaw against loudness: r between jawOpen and the frame's RMS level in dB (floored LOUDNESS_RANGE_DB below the
  clip's loudest frame) per clip, and the lag of the mouth behind the audio at the peak of their
  cross-correlation (+-MAX_LAG_FRAMES, refined by a parabola through the peak): positive = the mouth follows;
* live against offline: the runtime's own LiveSession (runtime/live.py) at LIVE_LOOKAHEAD_MS, fed in 20 ms chunks,
  against the runtime's offline windows (runtime/translate.py), both at 25 fps (a FLAME speaker's rate) and 30 fps
  (a LAM speaker's): r and the largest difference per channel;
* cost: the model file's size and onnxruntime's time (one thread) per second of audio, offline and per live window.
"""

from __future__ import annotations

import json
import os
import platform
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnxruntime as ort

from gaussiantalker.runtime.live import LiveSession
from gaussiantalker.runtime.translate import SILENCE_GATE_DBFS, blendshape_params, iter_translate
from gaussiantalker.sdk.rig import ARKIT_BLENDSHAPES, ARKIT_RIG

from .data import join
from .espeak import Phoneme, Utterance
from .targets import FPS, arkit_targets, frame_count
from .visemes import SYMBOLS, VOWEL_VISEMES, symbols_of

LEAD_S, TAIL_S = 0.3, 0.4
TOP_CHANNELS = 10
MOUTH_PREFIXES = ("jaw", "mouth", "tongue")
BILABIALS = ("p", "b", "m")
CLOSED_APERTURE = 0.05
LOUDNESS_RANGE_DB = 30.0
MAX_LAG_FRAMES = 4
LIVE_LOOKAHEAD_MS = 160.0
LIVE_CHUNK_S = 0.02
SAMPLE_RATE = 16000
JAW, CLOSE = ARKIT_BLENDSHAPES.index("jawOpen"), ARKIT_BLENDSHAPES.index("mouthClose")


@dataclass
class Clip:
    """A held-out clip: audio (a whole number of 25 fps frames), targets [T, 52], its phonemes, who spoke it."""

    audio: np.ndarray
    targets: np.ndarray
    phonemes: list[Phoneme]
    voice: str
    text: str


def make_clip(utterance: Utterance) -> Clip:
    """An utterance with silence around it and its targets (whole frames)."""
    audio, phonemes, text = join([utterance], [TAIL_S])
    frames = frame_count(audio.shape[0] / SAMPLE_RATE)
    audio = np.pad(audio, (0, frames * 640 - audio.shape[0]))
    return Clip(audio, arkit_targets(phonemes, text, audio), phonemes, utterance.voice, utterance.text)


def session(model_bytes: bytes, threads: int = 1) -> ort.InferenceSession:
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    return ort.InferenceSession(model_bytes, options, providers=["CPUExecutionProvider"])


def run_arkit(sess: ort.InferenceSession, audio: np.ndarray) -> np.ndarray:
    """The model on one whole clip: [T, 52]."""
    return sess.run(["blendshapes"], {"audio": np.ascontiguousarray(audio, np.float32)[None]})[0][0]


def pearson(a: np.ndarray, b: np.ndarray) -> float:
    """Pearson r; NaN when either side is constant."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if a.std() < 1e-12 or b.std() < 1e-12:
        return float("nan")
    return float(np.corrcoef(a, b)[0, 1])


def top_channels(targets: np.ndarray, count: int = TOP_CHANNELS) -> list[str]:
    """The mouth channels the targets move most (largest standard deviation), most first."""
    mouth = [k for k, name in enumerate(ARKIT_BLENDSHAPES) if name.startswith(MOUTH_PREFIXES)]
    spread = targets[:, mouth].std(axis=0)
    return [ARKIT_BLENDSHAPES[mouth[k]] for k in np.argsort(-spread)[:count]]


def bilabial_onsets(phonemes: list[Phoneme]) -> list[tuple[float, float]]:
    """(start, end) seconds of each run of /p b m/ phonemes."""
    runs: list[tuple[float, float]] = []
    previous_bilabial = False
    for phoneme in phonemes:
        symbols = symbols_of(phoneme.ipa)
        bilabial = bool(symbols) and symbols[0] in BILABIALS and len(symbols) == 1
        if bilabial and previous_bilabial and runs:
            runs[-1] = (runs[-1][0], phoneme.end)
        elif bilabial:
            runs.append((phoneme.start, phoneme.end))
        previous_bilabial = bilabial
    return runs


def aperture_of(weights: np.ndarray) -> np.ndarray:
    """The lips' opening of ARKit weights [T, 52]: jawOpen - mouthClose (mouthClose shuts the lips on an open jaw)."""
    return weights[:, JAW] - weights[:, CLOSE]


def closures(aperture: np.ndarray, phonemes: list[Phoneme]) -> tuple[int, int, list[float]]:
    """(onsets closed, onsets, smallest aperture at each onset) for one clip's aperture [T] (module docstring)."""
    closed, smallest = 0, []
    for start, end in bilabial_onsets(phonemes):
        first = int(np.floor(start * FPS))
        last = max(first, int(np.ceil(end * FPS)) - 1)
        window = aperture[max(0, first - 1): min(len(aperture), last + 2)]
        if window.size == 0:
            continue
        smallest.append(float(window.min()))
        closed += smallest[-1] <= CLOSED_APERTURE
    return closed, len(smallest), smallest


def vowels_open(aperture: np.ndarray, phonemes: list[Phoneme]) -> tuple[int, int, list[float]]:
    """(vowels that open, vowels, largest aperture in each) for the vowel phonemes of at least one whole frame:
    the guard against a mouth that passes the closure test by never opening."""
    opened, largest = 0, []
    for phoneme in phonemes:
        symbols = symbols_of(phoneme.ipa)
        if not symbols or SYMBOLS.get(symbols[0]) not in VOWEL_VISEMES:
            continue
        first, last = int(np.ceil(phoneme.start * FPS)), int(np.floor(phoneme.end * FPS)) - 1
        if last < first or last >= len(aperture):
            continue
        largest.append(float(aperture[first:last + 1].max()))
        opened += largest[-1] > CLOSED_APERTURE
    return opened, len(largest), largest


def loudness(audio: np.ndarray, frames: int) -> np.ndarray:
    """Frame RMS level in dB, floored LOUDNESS_RANGE_DB below the clip's loudest frame."""
    chunks = np.pad(audio, (0, max(0, frames * 640 - audio.shape[0])))[: frames * 640].reshape(frames, 640)
    level = 10.0 * np.log10(np.mean(chunks.astype(np.float64) ** 2, axis=1) + 1e-12)
    return np.maximum(level, level.max() - LOUDNESS_RANGE_DB)


def lag_frames(mouth: np.ndarray, level: np.ndarray) -> float:
    """Lag of `mouth` behind `level` (frames) at the peak of their normalised cross-correlation."""
    a = (mouth - mouth.mean()) / (mouth.std() + 1e-12)
    b = (level - level.mean()) / (level.std() + 1e-12)
    lags = np.arange(-MAX_LAG_FRAMES, MAX_LAG_FRAMES + 1)
    corr = np.array([np.mean(a[max(0, k):len(a) + min(0, k)] * b[max(0, -k):len(b) + min(0, -k)]) for k in lags])
    k = int(np.argmax(corr))
    if 0 < k < len(lags) - 1:
        denominator = corr[k - 1] - 2 * corr[k] + corr[k + 1]
        if denominator < 0:
            return float(lags[k] + 0.5 * (corr[k - 1] - corr[k + 1]) / denominator)
    return float(lags[k])


class _VoiceDriver:
    """What a LiveSession reads of a Driver (runtime/driver.py), around the voice model alone: drives are the
    weights themselves, and there is no renderer."""

    rig = ARKIT_RIG
    has_translator = True
    pose_track = None
    silence_gate_dbfs = SILENCE_GATE_DBFS
    sample_rate = SAMPLE_RATE
    param_names = ARKIT_BLENDSHAPES
    param_count = len(ARKIT_BLENDSHAPES)

    def __init__(self, sess: ort.InferenceSession, fps: int) -> None:
        self.sess, self.fps = sess, fps

    def run_translator(self, chunk: np.ndarray) -> dict:
        return {"blendshapes": self.sess.run(["blendshapes"], {"audio": chunk[None]})[0]}

    def params_of(self, out: dict, frames: int) -> np.ndarray:
        return blendshape_params(out, frames)

    def clamp_params(self, params: np.ndarray) -> np.ndarray:
        return np.clip(params, 0.0, 1.0)

    def drive_from_params(self, params: np.ndarray, head_pose=None) -> np.ndarray:
        return np.asarray(params, np.float32)

    def head_pose(self, index: int):
        return None


def offline_frames(sess: ort.InferenceSession, audio: np.ndarray, fps: int) -> np.ndarray:
    """The runtime's offline path: windows, cross-fades and the silence gate (runtime/translate.py)."""
    run = _VoiceDriver(sess, fps).run_translator
    return np.concatenate(list(iter_translate(run, audio, SAMPLE_RATE / fps, params_of=blendshape_params)))


def live_frames(sess: ort.InferenceSession, audio: np.ndarray, fps: int,
                lookahead_ms: float = LIVE_LOOKAHEAD_MS) -> np.ndarray:
    """The runtime's live session, free-running, fed LIVE_CHUNK_S chunks then ended: the weights of its frames."""
    live = LiveSession(_VoiceDriver(sess, fps), lookahead_ms=lookahead_ms, paced=False, output=None)
    chunk = int(LIVE_CHUNK_S * SAMPLE_RATE)
    for start in range(0, audio.shape[0], chunk):
        live.push(audio[start:start + chunk], SAMPLE_RATE)
    live.end()
    rows = [frame.drive for frame in live.frames() if frame.speaking]
    return np.stack(rows)


def live_agreement(sess: ort.InferenceSession, clips: list[Clip], channels: list[str], fps: int) -> dict:
    """Per channel r and largest difference between live and offline frames, pooled over the clips."""
    live, offline = [], []
    for clip in clips:
        a, b = live_frames(sess, clip.audio, fps), offline_frames(sess, clip.audio, fps)
        n = min(len(a), len(b))
        live.append(a[:n])
        offline.append(np.clip(b[:n], 0.0, 1.0))  # the live session clips ARKit weights to 0..1
    live_all, offline_all = np.concatenate(live), np.concatenate(offline)
    out = {}
    for name in channels:
        k = ARKIT_BLENDSHAPES.index(name)
        out[name] = {"r": pearson(live_all[:, k], offline_all[:, k]),
                     "max_abs_diff": float(np.abs(live_all[:, k] - offline_all[:, k]).max())}
    return out


def cpu_cost(sess: ort.InferenceSession, seconds: float = 10.0, rounds: int = 5) -> dict:
    """onnxruntime seconds per second of audio on a clip of `seconds`, and ms per live window (1 s of context,
    8 frames, 160 ms ahead), medians of `rounds` (after one warm-up)."""
    rng = np.random.default_rng(0)
    clip = (0.1 * rng.standard_normal(int(seconds * SAMPLE_RATE))).astype(np.float32)
    window = clip[: int((1.0 + 8 / FPS + 0.16) * SAMPLE_RATE)]
    timings = {}
    for name, audio in (("clip", clip), ("window", window)):
        run_arkit(sess, audio)
        values = []
        for _ in range(rounds):
            start = time.perf_counter()
            run_arkit(sess, audio)
            values.append(time.perf_counter() - start)
        timings[name] = float(np.median(values))
    return {"seconds_per_audio_second": timings["clip"] / seconds, "live_window_ms": 1000 * timings["window"],
            "clip_seconds": seconds}


def mouth_measures(clips: list[Clip], apertures: list[np.ndarray], jaws: list[np.ndarray]) -> dict:
    """Closure at /p b m/, vowels opening, jaw against loudness and the mouth's lag over `clips`, from each
    clip's aperture [T] and jaw [T] (jawOpen units: mouths.py)."""
    closed = total = opened = vowels = 0
    bilabial, vowel_apertures, jaw_r, lags = [], [], [], []
    for clip, aperture, jaw in zip(clips, apertures, jaws, strict=True):
        c, n, smallest = closures(aperture, clip.phonemes)
        closed, total = closed + c, total + n
        bilabial += smallest
        c, n, largest = vowels_open(aperture, clip.phonemes)
        opened, vowels = opened + c, vowels + n
        vowel_apertures += largest
        level = loudness(clip.audio, len(jaw))
        jaw_r.append(pearson(jaw, level))
        lags.append(lag_frames(jaw, level))
    return {
        "closure_share": closed / max(total, 1), "bilabial_onsets": total,
        "bilabial_aperture_median": float(np.median(bilabial)) if bilabial else float("nan"),
        "vowel_open_share": opened / max(vowels, 1), "vowels": vowels,
        "vowel_aperture_median": float(np.median(vowel_apertures)) if vowel_apertures else float("nan"),
        "jaw_loudness_r_median": float(np.nanmedian(jaw_r)), "jaw_loudness_r_mean": float(np.nanmean(jaw_r)),
        "lag_ms_median": float(np.median(lags)) * 1000.0 / FPS,
        "lag_ms_p10_p90": [float(np.percentile(lags, 10)) * 1000.0 / FPS,
                           float(np.percentile(lags, 90)) * 1000.0 / FPS],
    }


def quality(sess: ort.InferenceSession, clips: list[Clip], channels: list[str] | None = None) -> dict:
    """Agreement, closure and jaw/loudness of the model on `clips` (and the same measures of the targets)."""
    predictions = [run_arkit(sess, clip.audio)[: len(clip.targets)] for clip in clips]
    targets = np.concatenate([clip.targets for clip in clips])
    pred = np.concatenate(predictions)
    channels = channels or top_channels(targets)
    agreement = {name: pearson(pred[:, ARKIT_BLENDSHAPES.index(name)], targets[:, ARKIT_BLENDSHAPES.index(name)])
                 for name in channels}
    result: dict = {"clips": len(clips), "frames": int(len(targets)), "agreement_r": agreement}
    for who, tracks in (("model", predictions), ("targets", [clip.targets for clip in clips])):
        result[who] = mouth_measures(clips, [aperture_of(w) for w in tracks], [w[:, JAW] for w in tracks])
    result["rmse_top_channels"] = float(np.sqrt(np.mean([(pred[:, ARKIT_BLENDSHAPES.index(n)] -
                                                          targets[:, ARKIT_BLENDSHAPES.index(n)]) ** 2
                                                         for n in channels])))
    for name in ("eyeBlinkLeft", "browOuterUpLeft", "browInnerUp"):
        k = ARKIT_BLENDSHAPES.index(name)
        result.setdefault("other_r", {})[name] = pearson(pred[:, k], targets[:, k])
    return result


def machine() -> dict:
    """Where a measurement ran."""
    return {"platform": platform.platform(), "processor": platform.processor() or platform.machine(),
            "cpu_count": os.cpu_count(), "onnxruntime": ort.__version__}


def evaluate(arkit_bytes: bytes, heldout: list[Clip], unseen_language: list[Clip], live_clips: int = 8) -> dict:
    """Every measure of the module docstring on the held-out clips (channels chosen on them), the unseen
    language's clips apart, and the live comparison on the first `live_clips` clips."""
    sess = session(arkit_bytes)
    main = quality(sess, heldout)
    channels = list(main["agreement_r"])
    result = {
        "heldout": main,
        "unseen_language": quality(sess, unseen_language, channels) if unseen_language else None,
        "live_vs_offline": {f"{fps}fps": live_agreement(sess, heldout[:live_clips], channels, fps)
                            for fps in (25, 30)},
        "live_lookahead_ms": LIVE_LOOKAHEAD_MS,
        "model_bytes": len(arkit_bytes),
        "cpu": cpu_cost(sess),
        "machine": machine(),
        "voices": sorted({clip.voice for clip in heldout}),
        "definitions": {"closed_aperture": CLOSED_APERTURE, "loudness_range_db": LOUDNESS_RANGE_DB,
                        "lead_s": LEAD_S, "tail_s": TAIL_S},
    }
    return result


def _fmt(value: float, digits: int = 3) -> str:
    return "n/a" if value is None or (isinstance(value, float) and np.isnan(value)) else f"{value:.{digits}f}"


def markdown(result: dict, command: str, record: dict | None = None) -> str:
    """The report page of `evaluate`'s result."""
    main, unseen = result["heldout"], result["unseen_language"]
    lines = ["# Voice driver: held-out measurements", "",
             f"`{command}` (exporter/voice/evaluate.py; what each measure is: docs/voice.md, \"Measurements\").",
             "", f"Held-out: {main['clips']} clips, {main['frames']} frames at 25 fps, voices "
             f"{', '.join(result['voices'])} (none heard in training), sentences from the held-out stream.", ""]
    lines += ["## Agreement with the phoneme targets (Pearson r, all held-out frames)", "",
              "| channel | r held-out | r unseen language |", "|---|---:|---:|"]
    for name, r in main["agreement_r"].items():
        lines.append(f"| {name} | {_fmt(r)} | {_fmt(unseen['agreement_r'][name]) if unseen else 'n/a'} |")
    lines += ["", f"RMS error over these channels: {_fmt(main['rmse_top_channels'])}. Other channels' r (model "
              "against targets): " + ", ".join(f"{k} {_fmt(v)}" for k, v in main["other_r"].items()) + ".", ""]
    lines += ["## Lips, jaw and loudness", "", "| | model | targets |", "|---|---:|---:|"]
    rows = [(f"/p b m/ onsets closed (aperture <= {CLOSED_APERTURE:.2f} within +-1 frame)", "closure_share", 3),
            ("median smallest aperture at /p b m/", "bilabial_aperture_median", 3),
            (f"vowels open (largest aperture > {CLOSED_APERTURE:.2f})", "vowel_open_share", 3),
            ("median largest aperture in vowels", "vowel_aperture_median", 3),
            ("jaw vs loudness r, median of clips", "jaw_loudness_r_median", 3),
            ("jaw vs loudness r, mean of clips", "jaw_loudness_r_mean", 3),
            ("mouth lag behind audio, median (ms)", "lag_ms_median", 1)]
    for label, key, digits in rows:
        lines.append(f"| {label} | {_fmt(main['model'][key], digits)} | {_fmt(main['targets'][key], digits)} |")
    lines.append(f"| /p b m/ onsets counted, vowels counted | {main['model']['bilabial_onsets']}, "
                 f"{main['model']['vowels']} | |")
    if unseen:
        lines += ["", f"Unseen language ({unseen['clips']} clips): closure {_fmt(unseen['model']['closure_share'])}, "
                  f"jaw vs loudness r {_fmt(unseen['model']['jaw_loudness_r_median'])}, lag "
                  f"{_fmt(unseen['model']['lag_ms_median'], 1)} ms."]
    lines += ["", f"## Live ({result['live_lookahead_ms']:.0f} ms lookahead) against offline", "",
              "| channel | r 25 fps | max diff 25 fps | r 30 fps | max diff 30 fps |", "|---|---:|---:|---:|---:|"]
    for name in main["agreement_r"]:
        a, b = result["live_vs_offline"]["25fps"][name], result["live_vs_offline"]["30fps"][name]
        lines.append(f"| {name} | {_fmt(a['r'], 4)} | {_fmt(a['max_abs_diff'], 4)} | {_fmt(b['r'], 4)} | "
                     f"{_fmt(b['max_abs_diff'], 4)} |")
    cpu = result["cpu"]
    lines += ["", "## Cost", "", f"* model file: {result['model_bytes'] / 1e6:.2f} MB",
              f"* onnxruntime, one thread: {1000 * cpu['seconds_per_audio_second']:.1f} ms per second of audio "
              f"({cpu['clip_seconds']:.0f} s clip), {cpu['live_window_ms']:.1f} ms per live window (1.48 s)",
              f"* machine: {result['machine']['processor']}, {result['machine']['cpu_count']} cores, "
              f"{result['machine']['platform']}, onnxruntime {result['machine']['onnxruntime']}"]
    if record:
        lines += ["", "## Training run", "", "```json", json.dumps(record, indent=2), "```"]
    return "\n".join(lines) + "\n"


def write_report(result: dict, out_dir: str | os.PathLike, command: str, record: dict | None = None) -> None:
    """voice.json and voice.md under `out_dir`."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "voice.json").write_text(json.dumps({**result, "command": command, "training": record}, indent=2) + "\n")
    (out / "voice.md").write_text(markdown(result, command, record))


__all__ = ["Clip", "aperture_of", "bilabial_onsets", "closures", "cpu_cost", "evaluate", "lag_frames",
           "live_frames", "loudness", "make_clip", "mouth_measures", "offline_frames", "pearson", "quality",
           "run_arkit", "session", "top_channels", "write_report"]
