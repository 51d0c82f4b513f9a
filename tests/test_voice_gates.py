"""The voice drivers' measurements beyond espeak-ng (docs/voice.md, "Measurements" and "Augmentation"): a call's
channel keeps the audio aligned with its targets, speed perturbation stretches both, every driver's mouth is read
in one currency (the FLAME model's as the ARKit model's; a bundle's lip gap measured on its Gaussians), the gates
table and its goals, the real recordings aligned, and `gt-bench voice` end to end on a few clips."""

from __future__ import annotations

import numpy as np
import pytest
from ci_tools import need

from gaussiantalker.exporter.voice import channels, corpus, data, evaluate, families, gates, mouths
from gaussiantalker.exporter.voice.data import Stream, load_utterance
from gaussiantalker.exporter.voice.paths import ARKIT_MODEL, FLAME_MODEL
from gaussiantalker.exporter.voice.targets import arkit_targets
from gaussiantalker.sdk.rig import ARKIT_BLENDSHAPES

HELDOUT = "tests/data/voice_heldout"


@pytest.fixture(scope="module")
def clip():
    return evaluate.make_clip(load_utterance(HELDOUT))


def _lag(x: np.ndarray, y: np.ndarray, span: int = 40) -> int:
    """Samples by which y lags x at the peak of their cross-correlation."""
    core = slice(span, x.size - span)
    scores = [float(np.dot(x[core], y[span + k: x.size - span + k])) for k in range(-span, span + 1)]
    return int(np.argmax(scores)) - span


@pytest.mark.parametrize("name", ["telephone", "opus", "low_pass"])
def test_call_channels_keep_length_and_timing(clip, name):
    """The targets stay aligned with the audio: same length, cross-correlation peak within 2 samples (0.125 ms;
    Opus's resampling leaves 2), finite, and the channel really changes the sound."""
    apply = {"telephone": channels.telephone, "opus": lambda x: channels.opus(x, 8.0),
             "low_pass": lambda x: channels.low_pass(x, 3500.0)}[name]
    x = clip.audio
    y = apply(x)
    assert y.dtype == np.float32 and y.shape == x.shape and np.isfinite(y).all()
    assert abs(_lag(x, y)) <= 2
    spectrum_in, spectrum_out = np.abs(np.fft.rfft(x)), np.abs(np.fft.rfft(y))
    hz = np.fft.rfftfreq(x.size, 1 / 16000)
    high = hz > 4500
    assert spectrum_out[high].sum() < 0.2 * spectrum_in[high].sum()  # all three cut what a call cannot carry
    assert np.array_equal(apply(x), y)  # deterministic


def test_speed_perturbation_stretches_audio_and_targets():
    rng = np.random.default_rng(0)
    utterance = load_utterance(HELDOUT)
    frames = 40
    audio = np.pad(utterance.audio, (0, 640 * 200 - utterance.audio.size))[: 640 * 200]
    stream = Stream(audio, arkit_targets(utterance.phonemes, utterance.text, audio))
    sped = [data.sped_crop([stream], frames, rng) for _ in range(40)]
    assert all(a.shape == (frames * 640,) and t.shape == (frames, 52) for a, t in sped)
    assert all(np.isfinite(a).all() and np.isfinite(t).all() for a, t in sped)
    assert np.isclose(channels.speed(audio, 1.1).size, audio.size / 1.1, atol=1)
    again = np.random.default_rng(0)
    assert all(np.array_equal(a, b[0]) for (a, _), b in zip(sped, [data.sped_crop([stream], frames, again)
                                                                    for _ in range(40)], strict=True))


def test_augment_draws_every_channel_deterministically(clip):
    rng = np.random.default_rng(5)
    outs = [data.augment(clip.audio[: 640 * 50], rng) for _ in range(30)]
    assert all(o.shape == (640 * 50,) and np.isfinite(o).all() and np.abs(o).max() <= 1.0 for o in outs)
    rng = np.random.default_rng(5)
    assert all(np.array_equal(o, data.augment(clip.audio[: 640 * 50], rng)) for o in outs)


def test_flame_voice_reads_the_same_mouth_as_the_arkit_voice(clip):
    """The committed FLAME model is the ARKit network with its jaw = JAW_RADIANS x (jawOpen - mouthClose), so in
    jawOpen units its aperture is the ARKit model's, to float rounding."""
    arkit = mouths.ArkitVoice(ARKIT_MODEL).mouth(clip.audio)
    flame = mouths.FlameVoice(FLAME_MODEL).mouth(clip.audio)
    weights = arkit.weights
    assert np.allclose(arkit.aperture, weights[:, ARKIT_BLENDSHAPES.index("jawOpen")]
                       - weights[:, ARKIT_BLENDSHAPES.index("mouthClose")])
    assert np.abs(flame.aperture - arkit.aperture).max() < 1e-5


def test_lip_gap_on_a_bundle_is_in_jaw_open_units(small_export):
    """On the small demo speaker's Gaussians: the rest pose 0, the jaw at JAW_RADIANS 1 (by definition), half way
    about half (the lips part with the jaw's rotation, so not exactly), and the lips' parting grows with the jaw."""
    speaker = mouths.BundleSpeaker(small_export.path)
    jaw = np.zeros((5, 3), np.float32)
    jaw[:, 0] = np.linspace(0.0, mouths.JAW_RADIANS, 5)
    aperture = speaker.lips.apertures(np.zeros((5, speaker.lips.n_expr), np.float32), jaw)
    assert abs(aperture[0]) < 1e-6 and abs(aperture[-1] - 1.0) < 1e-6
    assert 0.35 < aperture[2] < 0.65 and np.all(np.diff(aperture) > 0)
    track = speaker.mouth(np.zeros(16000, np.float32))
    assert track.aperture.shape == track.jaw.shape == (25,) and track.weights is None


def test_gate_table_and_goals(clip):
    table = gates.gate_table([mouths.ArkitVoice(ARKIT_MODEL)], {"espeak-ng": [clip], "real-unseen": [clip]})
    rows = table["families"]["espeak-ng"]["rows"]
    assert rows["targets"]["closure_share"] == 1.0  # the targets close every onset by construction
    model = rows["ARKit voice"]
    assert model["bilabial_onsets"] == 15 and model["closure_share"] >= 0.9
    assert len(model["mouth_r"]) == 10 and model["mouth_r_mean"] > 0.8
    assert model["passes"]["lag_ms"] is True
    # the rules themselves: each goal's side and the lag's two-sided bound
    assert gates.passes({"closure_share": 0.89, "mouth_r_mean": 0.85, "jaw_loudness_r_median": 0.9,
                         "lag_ms_median": -41.0}) == {"closure": False, "mouth_r": True, "jaw_loudness_r": True,
                                                      "lag_ms": False}
    assert gates.passes({"closure_share": 1.0, "jaw_loudness_r_median": float("nan"), "lag_ms_median": 0.0}
                        )["mouth_r"] is None


def _real() -> families.RealSet:
    from gaussiantalker.exporter.voice import real_speech

    try:
        return families.real_clips()
    except real_speech.RealSpeechMissing as exc:
        need(str(exc), ".ci/install (python -m gaussiantalker.exporter.voice.real_speech fetch)")
        raise


def test_real_clips_are_aligned_and_measured():
    """Every fetched recording aligns well (none poor), its bilabials are found, and the speakers some training
    voice was built from are kept apart."""
    real = _real()
    assert len(real.clips) == len(real.alignment) >= 10
    assert not [clip_id for clip_id, q in real.alignment.items() if q["poor"]]
    onsets = sum(len(evaluate.bilabial_onsets(c.phonemes)) for c in real.clips)
    assert onsets >= 30
    unseen = families.unseen_speakers(real)
    assert 0 < len(unseen) < len(real.clips)
    assert all("awb" not in c.voice and "slt" not in c.voice for c in unseen)


def test_bench_voice_end_to_end(tmp_path):
    """`gt-bench voice` on one clip per synthetic family and the real recordings: every family, every driver, the
    goals marked on the goal families, the alignment and cost tables."""
    _real()
    from tools.bench.voice_gates import run_voice_bench, voice_table

    result = run_voice_bench(clips=1, progress=False, log=lambda *_: None)
    assert set(result["families"]) == set(families.FAMILIES)
    for entry in result["families"].values():
        assert set(entry["rows"]) == {"targets", "ARKit voice", "FLAME voice"}
    text = voice_table(result)
    assert "**festival-diphone** (goals)" in text and "**real-unseen** (goals)" in text
    assert text.count("✓") + text.count("✗") == 2 * 2 * 4 - 2  # two goal families x two drivers x four goals,
    # less the FLAME voice's channel agreement (it has no ARKit channels)
    assert result["drivers"]["ARKit voice"]["ms_per_audio_second"] > 0
    assert set(result["alignment_cost"]) == set(families.ALIGNED_FAMILIES)
    assert "What the aligner alone costs" in text


def test_the_aligners_own_cost_is_measured_on_twins():
    """Clips whose targets are made twice, from the engine's phone times and from pocketsphinx's alignment: the two
    agree closely but not exactly (the aligner's boundaries are not the engine's), and the ARKit voice's agreement
    with each is measured the way the gates measure it."""
    _real()  # pocketsphinx comes with the same install as the real recordings
    twins = families.aligned_twins(3, progress=False)
    assert set(twins) == set(families.ALIGNED_FAMILIES)
    channels = ["jawOpen", "mouthPucker", "mouthPressLeft"]
    for name, twin in twins.items():
        assert len(twin.clips) + len(twin.unaligned) == 3 and twin.clips, (name, twin.unaligned)
        assert all(a.shape == c.targets.shape and np.isfinite(a).all() for a, c in zip(twin.aligned, twin.clips,
                                                                                       strict=True))
        cost = gates.alignment_cost(mouths.ArkitVoice(ARKIT_MODEL), twin.clips, twin.aligned, channels)
        assert 0.7 < cost["targets_r_mean"] < 0.999, cost
        assert 0.5 < cost["driver_r_engine"] <= 1.0 and 0.5 < cost["driver_r_aligned"] <= 1.0, cost
        # the sentences are the word list's alone: the aligner's dictionary has every word
        assert all(w.strip(",.?!").lower() in {x.lower() for x in corpus.WORDS["en"]}
                   for c in twin.clips for w in c.text.split())


def test_vocal_tract_warp_moves_a_tone_up_the_bands():
    """mel_warp(1) is the identity; a 1 kHz tone's band peak moves to about 1.15 kHz's band under factor 1.15,
    and each warped band is a convex mix of two (no gain)."""
    import torch

    from gaussiantalker.exporter.voice.model import (
        FMAX,
        FMIN,
        N_MELS,
        VoiceConfig,
        VoiceNet,
        hz_to_mel,
        mel_to_hz,
        mel_warp,
    )
    from gaussiantalker.exporter.voice.train import warp_voices

    assert np.array_equal(mel_warp(1.0), np.eye(N_MELS, dtype=np.float32))
    warp = mel_warp(1.15)
    assert np.allclose(warp.sum(axis=1), 1.0) and (warp >= 0).all()
    net = VoiceNet(VoiceConfig(channels=8))
    tone = np.sin(2 * np.pi * 1000 * np.arange(16000) / 16000).astype(np.float32)
    features = net.features(torch.from_numpy(tone)[None])[0].numpy()
    centres = mel_to_hz(np.linspace(hz_to_mel(FMIN), hz_to_mel(FMAX), N_MELS + 2))[1:-1]
    middle = features[:, 130]  # in the tone (the front end puts 88 steps of silence before it)
    moved = warp @ middle
    assert abs(centres[int(np.argmax(moved))] / centres[int(np.argmax(middle))] - 1.15) < 0.08
    rng = np.random.default_rng(0)
    batch = torch.from_numpy(np.stack([features] * 6))
    warped = warp_voices(batch, rng)
    changed = [not torch.equal(warped[k], batch[k]) for k in range(6)]
    assert any(changed) and not all(changed)  # WARP_P of the crops


def test_band_masks_and_colour_change_only_what_they_say():
    """mask_bands sets at most MASKS spans of at most MASK_WIDTH bands to the crop's mean level, in its share of the
    crops; colour_bands adds one smooth curve a crop (the same at every step) whose largest gain is COLOUR_GAIN; a
    share of 0 returns the features as they are and draws nothing, so a run without them is the run before them."""
    import torch

    from gaussiantalker.exporter.voice.train import COLOUR_GAIN, MASK_WIDTH, MASKS, colour_bands, mask_bands

    rng = np.random.default_rng(1)
    features = torch.from_numpy(rng.normal(size=(8, 64, 30)).astype(np.float32))
    before = rng.bit_generator.state
    assert mask_bands(features, rng, 0.0) is features and colour_bands(features, rng, 0.0) is features
    assert rng.bit_generator.state == before
    masked = mask_bands(features, rng, 1.0)
    for k in range(8):
        changed = np.flatnonzero((masked[k] != features[k]).any(1).numpy())
        assert 0 < len(changed) <= MASKS * MASK_WIDTH
        assert torch.all(masked[k, changed] == features[k].mean())
    coloured = colour_bands(features, rng, 1.0)
    for k in range(8):
        curve = (coloured[k] - features[k]).numpy()
        assert np.allclose(curve, curve[:, :1], atol=1e-5)  # one gain a band, at every step
        assert abs(np.abs(curve).max() - COLOUR_GAIN) < 1e-5
        assert np.abs(np.diff(curve[:, 0])).max() < 0.2  # smooth over the bands
    half = mask_bands(features, rng, 0.5)
    assert 0 < sum(not torch.equal(half[k], features[k]) for k in range(8)) < 8


def test_closure_term_counts_lips_left_open():
    """The loss grows when the lips stay open on frames the targets close for a /p b m/ (pressed), not when they
    close more, and not on a pause's closed rest."""
    import torch

    from gaussiantalker.exporter.voice.train import CONTEXT_FRAMES, channel_weights, voice_loss

    jaw, close = ARKIT_BLENDSHAPES.index("jawOpen"), ARKIT_BLENDSHAPES.index("mouthClose")
    target = torch.zeros(1, CONTEXT_FRAMES + 10, 52)
    target[:, :, jaw] = 0.3
    target[:, CONTEXT_FRAMES + 3:CONTEXT_FRAMES + 6, close] = 0.3  # closed lips on an open jaw ...
    target[:, CONTEXT_FRAMES + 3:CONTEXT_FRAMES + 6, ARKIT_BLENDSHAPES.index("mouthPressLeft")] = 0.35  # ... a /b/
    weights = channel_weights()
    exact = voice_loss(target.clone(), target, weights)
    opened = target.clone()
    opened[:, CONTEXT_FRAMES + 3:CONTEXT_FRAMES + 6, close] = 0.2  # aperture 0.1 where the targets close
    shut = target.clone()
    shut[:, :, jaw] = 0.25  # the jaw a little less open everywhere: the same squared error, no excess aperture
    assert float(exact) == 0.0
    assert float(voice_loss(opened, target, weights)) > 2 * float(voice_loss(shut, target, weights)) > 0
    rest = target.clone()
    rest[:, CONTEXT_FRAMES + 3:CONTEXT_FRAMES + 6, ARKIT_BLENDSHAPES.index("mouthPressLeft")] = 0.0  # no /b/ there
    opened_rest = opened.clone()
    opened_rest[..., ARKIT_BLENDSHAPES.index("mouthPressLeft")] = 0.0
    assert np.isclose(float(voice_loss(opened_rest, rest, weights)), float(voice_loss(opened_rest, rest, weights, 0.0)))
