"""One table for every audio driver on every family of voice (docs/voice.md, "Measurements"; the committed
figures: docs/bench/voice/gates.md, made by `gt-bench voice`).

Per driver and family: the ten busiest mouth channels' r against the phoneme targets (ARKit drivers only; the
channels are chosen once, on the espeak-ng held-out targets, and kept for every family), the share of /p b m/
onsets closed within +-1 frame, the share of vowels that open, the jaw against loudness (median r of the clips)
and the mouth's lag behind the audio, all from each driver's `MouthTrack` (mouths.py). GOALS are checked on the
held-out family and on the real speakers no training voice was built from.
"""

from __future__ import annotations

import numpy as np

from gaussiantalker.sdk.rig import ARKIT_BLENDSHAPES

from .evaluate import Clip, aperture_of, mouth_measures, pearson, top_channels
from .mouths import SAMPLE_RATE, MouthTrack

# name: (measure key, goal, whether a larger value passes); lag passes within +-its goal.
GOALS = {"closure": ("closure_share", 0.90, True), "mouth_r": ("mouth_r_mean", 0.85, True),
         "jaw_loudness_r": ("jaw_loudness_r_median", 0.75, True), "lag_ms": ("lag_ms_median", 40.0, None)}


def _fit(track: MouthTrack, frames: int) -> MouthTrack:
    """A track cut or edge-padded to the clip's frame count (drivers round a clip's last frame differently)."""
    def fit(values: np.ndarray | None) -> np.ndarray | None:
        if values is None:
            return None
        values = values[:frames]
        pad = [(0, frames - values.shape[0])] + [(0, 0)] * (values.ndim - 1)
        return np.pad(values, pad, mode="edge")
    return MouthTrack(fit(track.aperture), fit(track.jaw), fit(track.weights))


def channel_r(a: np.ndarray, b: np.ndarray, channels: list[str]) -> dict[str, float]:
    """Pearson r of each named ARKit channel between two [frames, 52] tracks."""
    return {name: pearson(a[:, ARKIT_BLENDSHAPES.index(name)], b[:, ARKIT_BLENDSHAPES.index(name)])
            for name in channels}


def measure(driver, clips: list[Clip], channels: list[str]) -> dict:
    """Every measure of the module docstring for one driver on one family's clips."""
    tracks = [_fit(driver.mouth(clip.audio), len(clip.targets)) for clip in clips]
    result = mouth_measures(clips, [t.aperture for t in tracks], [t.jaw for t in tracks])
    result["clips"] = len(clips)
    if tracks and tracks[0].weights is not None:
        pred = np.concatenate([t.weights for t in tracks])
        targets = np.concatenate([clip.targets for clip in clips])
        agreement = channel_r(pred, targets, channels)
        result["mouth_r"] = agreement
        result["mouth_r_mean"] = float(np.nanmean(list(agreement.values())))
    aperture = np.concatenate([t.aperture for t in tracks])
    result["aperture_r"] = pearson(aperture, np.concatenate([aperture_of(clip.targets) for clip in clips]))
    return result


def targets_row(clips: list[Clip]) -> dict:
    """The same measures of the phoneme targets themselves (what a perfect driver would score)."""
    jaw = ARKIT_BLENDSHAPES.index("jawOpen")
    return mouth_measures(clips, [aperture_of(c.targets) for c in clips], [c.targets[:, jaw] for c in clips])


def passes(result: dict) -> dict[str, bool | None]:
    """Each goal met (None where the driver has no such measure)."""
    out: dict[str, bool | None] = {}
    for name, (key, goal, larger) in GOALS.items():
        value = result.get(key)
        if value is None or (isinstance(value, float) and np.isnan(value)):
            out[name] = None
        elif larger is None:
            out[name] = abs(value) <= goal
        else:
            out[name] = value >= goal if larger else value <= goal
    return out


def gate_table(drivers: list, families: dict[str, list[Clip]], channels: list[str] | None = None) -> dict:
    """{family: {driver name: measures}}, with the targets' own row and the channels used."""
    channels = channels or top_channels(np.concatenate([c.targets for c in families["espeak-ng"]]))
    out: dict = {"channels": channels, "families": {}}
    for family, clips in families.items():
        if not clips:
            continue
        rows = {"targets": targets_row(clips)}
        for driver in drivers:
            rows[driver.name] = measure(driver, clips, channels)
            rows[driver.name]["passes"] = passes(rows[driver.name])
        seconds = sum(clip.audio.shape[0] for clip in clips) / SAMPLE_RATE
        out["families"][family] = {"clips": len(clips), "seconds": round(seconds, 1), "rows": rows}
    return out


def alignment_cost(driver, clips: list[Clip], aligned: list[np.ndarray], channels: list[str]) -> dict:
    """What pocketsphinx's alignment alone costs the channels' agreement (families.aligned_twins): the targets from
    the engine's phone times against those from the alignment (a perfect driver's score on an aligned clip), and an
    ARKit driver's agreement with each; every r over all the clips' frames, then the mean of the channels."""
    if not clips:
        return {"clips": 0}
    engine = np.concatenate([clip.targets for clip in clips])
    from_alignment = np.concatenate(aligned)
    pred = np.concatenate([_fit(driver.mouth(clip.audio), len(clip.targets)).weights for clip in clips])
    targets_r = channel_r(engine, from_alignment, channels)
    out = {"clips": len(clips), "targets_r": targets_r,
           "driver_r_engine": float(np.nanmean(list(channel_r(pred, engine, channels).values()))),
           "driver_r_aligned": float(np.nanmean(list(channel_r(pred, from_alignment, channels).values())))}
    out["targets_r_mean"] = float(np.nanmean(list(targets_r.values())))
    return out


__all__ = ["GOALS", "alignment_cost", "channel_r", "gate_table", "measure", "passes", "targets_row"]
