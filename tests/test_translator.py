"""Motion Translator: shapes, length contract, robustness, ONNX dynamic-length parity, demo audio, brief training."""

from __future__ import annotations

import wave

import numpy as np
import pytest
import torch

from gaussiantalker.exporter.demo.audio_signals import (
    jaw_target_from_audio,
    loudness_envelope,
    normalize_audio,
    write_wav,
)
from gaussiantalker.exporter.demo.train_translator import TrainSettings, train_demo_translator
from gaussiantalker.exporter.export.speech import synth_speech
from gaussiantalker.exporter.export.translator_graph import export_translator_onnx
from gaussiantalker.exporter.model.translator import (
    FeatureEncoder,
    MotionTranslator,
    aligned_padding,
    check_audio_length,
    conv_kernels,
    normalize_waveform,
    paper_translator_config,
    translate,
)
from gaussiantalker.sdk.config import TranslatorConfig

N_EXPR = 10
SPF = 640
# Ops a mobile backend (MNN) is expected to run; the exported graph must stay within them.
COMMON_OPS = {
    "Add", "Sub", "Mul", "Div", "MatMul", "Reshape", "Transpose", "Erf", "LayerNormalization", "Conv", "Softmax",
    "ReduceMean", "Slice", "Sqrt", "Reciprocal", "Unsqueeze", "Squeeze", "InstanceNormalization", "Shape",
    "Concat", "Gather", "Constant", "Gelu", "Pow", "Cast", "CastLike", "Identity", "Expand", "Range",
}  # fmt: skip


def _randomized(model: MotionTranslator) -> MotionTranslator:
    """Perturb every weight (the head starts at zero, which would make parity checks vacuous)."""
    gen = torch.Generator().manual_seed(1)
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.05 * torch.randn(p.shape, generator=gen))
    return model.eval()


@pytest.fixture(scope="module")
def model() -> MotionTranslator:
    torch.manual_seed(0)
    return _randomized(MotionTranslator(TranslatorConfig(), N_EXPR, speaker_id=1))


@pytest.mark.parametrize(("kernel", "stride"), [(10, 5), (3, 2), (2, 2), (4, 2), (6, 3)])
def test_aligned_padding_gives_exact_feature_count(kernel: int, stride: int) -> None:
    p = aligned_padding(kernel, stride)
    for m in (1, 2, 7, 64):
        assert (stride * m + 2 * p - kernel) // stride + 1 == m


def test_feature_encoder_gives_one_feature_per_320_samples() -> None:
    cfg = TranslatorConfig()
    assert conv_kernels(cfg.conv_strides) == (10, 3, 3, 3, 3, 2, 2)
    enc = FeatureEncoder(cfg)
    for frames in (1, 4, 9):
        assert enc(torch.randn(1, SPF * frames)).shape == (1, 2 * frames, cfg.conv_channels)


@pytest.mark.parametrize("frames", [1, 3, 8, 25])
@pytest.mark.parametrize("batch", [1, 2])
def test_output_shapes(model: MotionTranslator, frames: int, batch: int) -> None:
    with torch.no_grad():
        expression, jaw_pose = model(torch.randn(batch, SPF * frames))
    assert expression.shape == (batch, frames, N_EXPR)
    assert jaw_pose.shape == (batch, frames, 3)


def test_translate_numpy_helper_shapes(model: MotionTranslator) -> None:
    expression, jaw_pose = translate(model, synth_speech(0.8, seed=3))
    assert expression.shape == (20, N_EXPR) and jaw_pose.shape == (20, 3)
    expression, jaw_pose = translate(model, np.zeros((3, SPF * 2), np.float32))
    assert expression.shape == (3, 2, N_EXPR)


@pytest.mark.parametrize(
    "audio",
    [
        np.zeros(SPF * 6, np.float32),
        np.clip(np.random.default_rng(0).normal(0, 10, SPF * 6), -1, 1).astype(np.float32),
        np.full(SPF * 6, 1e4, np.float32),
        np.full(SPF * 6, 1e-9, np.float32),
    ],
    ids=["silence", "clipped_noise", "huge_dc", "tiny_dc"],
)
def test_extreme_audio_gives_finite_output(model: MotionTranslator, audio: np.ndarray) -> None:
    expression, jaw_pose = translate(model, audio)
    assert np.isfinite(expression).all() and np.isfinite(jaw_pose).all()


@pytest.mark.parametrize("n_samples", [0, 639, 641, 1000, SPF * 3 + 1])
def test_length_not_multiple_of_frame_is_rejected(model: MotionTranslator, n_samples: int) -> None:
    with pytest.raises(ValueError, match="multiple of 640"):
        translate(model, np.zeros(n_samples, np.float32))
    with pytest.raises(ValueError, match="multiple of 640"):
        check_audio_length(n_samples, SPF)


def test_translate_rejects_non_finite_and_bad_rank(model: MotionTranslator) -> None:
    bad = np.zeros(SPF, np.float32)
    bad[3] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        translate(model, bad)
    with pytest.raises(ValueError, match="shape"):
        translate(model, np.zeros((1, 1, SPF), np.float32))


def test_invalid_config_is_rejected() -> None:
    with pytest.raises(ValueError, match="speaker_id"):
        MotionTranslator(TranslatorConfig(), N_EXPR, speaker_id=99)
    with pytest.raises(ValueError, match="head counts"):
        MotionTranslator(TranslatorConfig(encoder_dim=60, encoder_heads=7, pos_conv_groups=4), N_EXPR)


def test_speaker_identity_changes_output() -> None:
    torch.manual_seed(0)
    a = _randomized(MotionTranslator(TranslatorConfig(), N_EXPR, speaker_id=0))
    b = MotionTranslator(TranslatorConfig(), N_EXPR, speaker_id=2).eval()
    b.load_state_dict(a.state_dict())
    audio = synth_speech(0.64, seed=5)
    assert not np.allclose(translate(a, audio)[0], translate(b, audio)[0])


def test_normalisation_matches_numpy_and_keeps_silence_zero() -> None:
    audio = synth_speech(0.5, seed=2)
    torch_norm = normalize_waveform(torch.from_numpy(audio)[None])[0].numpy()
    np.testing.assert_allclose(torch_norm, normalize_audio(audio), atol=1e-5)
    assert not normalize_waveform(torch.zeros(1, SPF)).any()


def _check_translator_file(path, model: MotionTranslator) -> None:
    """The .onnx file: named input/outputs, common ops only, torch's outputs at other lengths than exported (8),
    finite on silence (the normalisation epsilon survived export)."""
    import onnx
    import onnxruntime as ort

    graph = onnx.load(str(path)).graph
    assert [i.name for i in graph.input] == ["audio"]
    assert [o.name for o in graph.output] == ["expression", "jaw_pose"]
    assert {n.op_type for n in graph.node} <= COMMON_OPS
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    for frames, seed in ((8, 11), (21, 12), (1, 13)):
        audio = synth_speech(frames * SPF / 16000, seed=seed)[None]
        with torch.no_grad():
            ref = [t.numpy() for t in model(torch.from_numpy(audio))]
        got = session.run(None, {"audio": audio})
        for r, g in zip(ref, got, strict=True):
            assert g.shape == r.shape
            assert np.abs(g - r).max() < 1e-4
        assert np.abs(ref[1]).max() > 1e-3  # the compared outputs are not all zero
    silent = session.run(None, {"audio": np.zeros((1, SPF * 4), np.float32)})
    assert all(np.isfinite(out).all() for out in silent)


@pytest.mark.slow  # torch.onnx export (~5 s); the quick run checks the session's recorded export of this graph
@pytest.mark.filterwarnings("ignore::FutureWarning")  # torch.export internals (treespec deprecation)
def test_onnx_dynamic_length_parity(model: MotionTranslator, tmp_path) -> None:
    """This translator (10 expressions, speaker id 1) through torch.onnx."""
    path = tmp_path / "translator.onnx"
    export_translator_onnx(model, path, example_frames=8)
    _check_translator_file(path, model)


def test_onnx_dynamic_length_parity_of_the_recorded_export(small_export, tmp_path, replay_onnx_exports) -> None:
    """The small speaker's (trained) translator as torch.onnx exported it for the session's bundle (replayed),
    written by export_translator_onnx."""
    replay_onnx_exports(small_export.protos[:1])
    path = tmp_path / "translator.onnx"
    export_translator_onnx(small_export.speaker.translator, path, example_frames=8)
    _check_translator_file(path, small_export.speaker.translator)


def test_paper_config_is_wav2vec2_large_sized() -> None:
    cfg = paper_translator_config()
    assert (cfg.conv_channels, cfg.encoder_dim, cfg.encoder_layers) == (512, 1024, 24)
    assert (cfg.encoder_heads, cfg.encoder_ffn, cfg.pos_conv_kernel, cfg.pos_conv_groups) == (16, 4096, 128, 16)
    assert cfg.samples_per_feature == 320


def test_synth_speech_is_deterministic_and_speech_like() -> None:
    a, b = synth_speech(2.5, seed=7), synth_speech(2.5, seed=7)
    assert a.dtype == np.float32 and a.shape == (40000,)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, synth_speech(2.5, seed=8))
    for seed in range(4):
        x = synth_speech(3.0, seed=seed)
        assert np.isfinite(x).all() and 0.5 <= np.abs(x).max() <= 0.8
        level = loudness_envelope(x)
        assert level.shape == (75,)
        assert (level < -50).mean() > 0.05  # pauses exist
        assert (level > -30).mean() > 0.4  # but it is mostly speech


def test_jaw_target_follows_loudness() -> None:
    assert not jaw_target_from_audio(np.zeros(SPF * 10)).any()
    audio = synth_speech(4.0, seed=4)
    jaw = jaw_target_from_audio(audio)
    assert jaw.shape == (100,) and jaw.min() >= 0 and 0.25 <= jaw.max() <= 0.35
    assert np.corrcoef(jaw, loudness_envelope(audio))[0, 1] > 0.7
    np.testing.assert_allclose(jaw_target_from_audio(0.3 * audio), jaw, atol=1e-3)  # gain-invariant
    assert jaw_target_from_audio(audio[:1000]).shape == (2,)  # partial frame is zero-padded


def test_write_wav_round_trip(tmp_path) -> None:
    audio = synth_speech(0.25, seed=1)
    path = tmp_path / "clip.wav"
    write_wav(path, audio, 16000)
    with wave.open(str(path), "rb") as handle:
        assert (handle.getnchannels(), handle.getsampwidth(), handle.getframerate()) == (1, 2, 16000)
        pcm = np.frombuffer(handle.readframes(handle.getnframes()), "<i2")
    np.testing.assert_allclose(pcm / 32767.0, audio, atol=1e-4)


def test_tiny_training_run_decreases_loss() -> None:
    torch.manual_seed(0)
    model = MotionTranslator(TranslatorConfig(), N_EXPR)
    settings = TrainSettings(max_steps=20, batch_size=2, crop_frames=25, n_clips=4, warmup_steps=5,
                             heldout_seconds=2.0)  # fmt: skip
    result = train_demo_translator(model, N_EXPR, seconds_budget=60, seed=0, progress=False, settings=settings)
    assert result["steps"] == 20 and result["stop_reason"] == "max_steps"
    assert result["final_loss"] < result["initial_loss"]
    assert -1.0 <= result["heldout_jaw_loudness_corr"] <= 1.0
    with pytest.raises(ValueError, match="n_expr"):
        train_demo_translator(model, N_EXPR + 1, progress=False, settings=settings)
