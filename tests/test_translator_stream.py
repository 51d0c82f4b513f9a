"""The Motion Translator's streaming form (exporter/model/translator_stream.py), its graph in a bundle, and live
sessions that run it (docs/live.md, "Streaming translators").

Tolerances:
* The feature encoder streams exactly: on audio whose statistics are the same in every window (a 25 Hz-periodic
  signal), the streamed features equal the whole clip's within 1e-4 (float32 rounding of convolutions over other
  lengths, ~1.6e-5 measured, on features up to ~3).
* The graph is its torch module: onnxruntime within 1e-5 of torch (2.6e-6 measured).
* On speech the stream normalises each call's new samples with its window's statistics and keeps the features of
  earlier calls as they were made, where the windowed graph renormalises its whole window every call: so its drives
  follow the windowed session's, not to rounding. The bound is on the busiest channels' correlation: against the
  windowed live session at least 0.85, and against the whole clip's (offline) drives no more than 0.05 below the
  windowed live session's own (docs/live.md has the demo speaker's figures).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from unseen_speech import unseen_speech

from gaussiantalker.exporter.export import translator_graph
from gaussiantalker.exporter.export.window_slices import window_gathers_to_slices
from gaussiantalker.exporter.model.translator import PositionalConvEmbedding, conv_kernels, normalize_waveform
from gaussiantalker.exporter.model.translator_stream import (
    MotionTranslatorStream,
    _conv_time_major,
    _pooled,
    _positional_tail,
    conv_plan,
)
from gaussiantalker.runtime import LiveSession
from gaussiantalker.runtime.stages import open_driver
from gaussiantalker.runtime.translate_stream import (
    LOUDNESS_WINDOW_FRAMES,
    REFRESHED_FRAMES,
    REST_FRAMES,
    StreamJob,
    _stacked_states,
    loudness_moved,
    made_after,
    window_loudness,
)
from gaussiantalker.sdk.bundle import STEADY_STREAM_GRAPH, STREAM_GRAPH, Bundle
from tools.bench.translator_stream import busiest_r

FRAME = 640


def _periodic(frames: int, seed: int = 0) -> np.ndarray:
    """Sines at multiples of 25 Hz: every 640-sample frame has the same statistics."""
    rng = np.random.default_rng(seed)
    t = np.arange(frames * FRAME) / 16000
    return sum(rng.uniform(0.01, 0.1) * np.sin(2 * np.pi * 25 * k * t + rng.uniform(0, 6))
               for k in rng.integers(1, 200, 20)).astype(np.float32)


def _rest(stream: MotionTranslatorStream) -> torch.Tensor:
    with torch.no_grad():
        return stream(torch.zeros(1, REST_FRAMES, FRAME), torch.zeros(1, stream.state_size),
                      torch.tensor([float(REST_FRAMES)]))[2]


def test_the_feature_encoder_streams_exactly(small_speaker):
    """Fed a frame at a time, or in uneven calls with a provisional frame after them, the stream's features (the
    feature encoder's output) equal the whole clip's where the statistics agree."""
    translator = small_speaker.translator.eval()
    stream = MotionTranslatorStream(translator).eval()
    frames = 80
    audio = _periodic(frames)
    captured = []
    hook = translator.audio_encoder.feature_projection.register_forward_hook(
        lambda module, args, out: captured.append(args[0][0].detach().numpy()))
    try:
        with torch.no_grad():
            translator(torch.from_numpy(audio[None]))
        whole = captured.pop()
        for sizes, provisional in (((1,), 0), ((3, 1, 5, 2), 1)):
            state, position, got, k = _rest(stream), 0, {}, 0
            captured.clear()
            while position < frames:
                keep = min(sizes[k % len(sizes)], frames - position)
                chunk = np.concatenate([audio[position * FRAME:(position + keep) * FRAME],
                                        np.zeros(provisional * FRAME, np.float32)]).reshape(1, -1, FRAME)
                with torch.no_grad():
                    state = stream(torch.from_numpy(chunk), state, torch.tensor([float(keep)]))[2]
                features = captured.pop()
                # a call makes the features of its refreshed frames again, then the provisional one of the last
                # call, then its own
                first = 2 * (position - stream.refresh_frames) - stream.feature_lag
                for i in range(2 * (stream.refresh_frames + keep)):
                    got[first + i] = features[i]
                position, k = position + keep, k + 1
            # features whose call's window holds no rest-state frame (their statistics differ from the clip's),
            # before the clip's end padding
            first = 2 * (stream.window_frames + max(sizes) + provisional)
            indices = [i for i in sorted(got) if first <= i < 2 * frames - 4]
            error = np.abs(np.stack([got[i] for i in indices]) - whole[indices]).max()
            assert error < 1e-4, (sizes, error)
    finally:
        hook.remove()


def _feed(stream: MotionTranslatorStream, audio: np.ndarray, sizes: tuple[int, ...], provisional: int = 0):
    """Feed `audio` from the rest state in calls of `sizes` committed frames (cycled), each with `provisional`
    zero frames after; yields (committed frames so far, the call's outputs)."""
    state, position, k = _rest(stream), 0, 0
    frames = audio.shape[0] // FRAME
    while position < frames:
        keep = min(sizes[k % len(sizes)], frames - position)
        chunk = np.concatenate([audio[position * FRAME:(position + keep) * FRAME],
                                np.zeros(provisional * FRAME, np.float32)]).reshape(1, -1, FRAME)
        with torch.no_grad():
            out = stream(torch.from_numpy(chunk), state, torch.tensor([float(keep)]))
        state, position, k = out[2], position + keep, k + 1
        yield position, out


def test_a_tail_of_the_whole_window_is_the_windowed_transformers(small_speaker):
    """The K/V-cached transformers with a tail as long as the window keep nothing and run over the whole window:
    once no row of the window comes from the all-zero state's blanks (which the cached form masks), the rows equal
    the uncached stream's (the same ops on the same rows), in uneven calls with provisional frames."""
    translator = small_speaker.translator.eval()
    uncached = MotionTranslatorStream(translator, tail_frames=None).eval()
    whole = MotionTranslatorStream(translator, tail_frames=uncached.window_frames).eval()
    audio = unseen_speech()[0][:60 * FRAME]
    compared = 0
    for (position, a), (_, b) in zip(_feed(uncached, audio, (1, 3, 2), 1), _feed(whole, audio, (1, 3, 2), 1),
                                     strict=True):
        if REST_FRAMES + position - 3 >= whole.seen_cap:  # the call's window is past the masked frames
            assert torch.abs(a[0] - b[0]).max() < 1e-6 and torch.abs(a[1] - b[1]).max() < 1e-6
            compared += 1
    assert compared > 20


def test_the_kept_keys_and_values_are_those_of_their_frames(small_speaker):
    """The encoder's first layer reads only its own row (and the positional convolution's neighbours), so on audio
    whose features stream exactly the keys and values the state keeps for the frames before the tail equal those
    the whole clip's first layer makes for the same frames: the cache holds each frame's, in order, across uneven
    calls and provisional frames (1e-4: the features' own tolerance)."""
    translator = small_speaker.translator.eval()
    stream = MotionTranslatorStream(translator).eval()
    encoder = translator.audio_encoder
    frames = 80
    audio = _periodic(frames)
    with torch.no_grad():
        features = encoder.feature_projection(encoder.feature_norm(encoder.feature_extractor(
            normalize_waveform(torch.from_numpy(audio[None])))))
        layer = encoder.encoder.layers[0]
        _, keys, values = layer.attention.project(layer.layer_norm(encoder.pos_conv_embed(features)))
    whole = torch.stack([keys, values], dim=1)[0]  # [2, H, F, Dh]
    rows = 2 * (stream.window_frames - stream.tail_frames)
    offsets = {name: sum(np.prod(shape) for _, shape in stream.state_parts[:i])
               for i, (name, _) in enumerate(stream.state_parts)}
    shape = dict(stream.state_parts)["encoder0_keys"]
    assert dict(stream.state_parts)["encoder0_values"] == shape
    for sizes, provisional in (((1,), 0), ((3, 1, 5, 2), 1)):
        checked = 0
        for committed, out in _feed(stream, audio, sizes, provisional):
            # the layer's keys, then its values: one [2, H, rows, Dh] block
            start = offsets["encoder0_keys"]
            assert offsets["encoder0_values"] == start + int(np.prod(shape))
            cache = out[2][0, start:start + 2 * int(np.prod(shape))].reshape(2, *shape)
            first = 2 * (committed - stream.window_frames)  # the next window's first feature
            # frames whose window held no rest-state frame and whose positional convolution reads real features
            for row in range(rows):
                index = first + row
                if 2 * (stream.window_frames + max(sizes) + provisional) <= index < 2 * frames - 16:
                    assert torch.abs(cache[:, :, row] - whole[:, :, index]).max() < 1e-4, (sizes, index)
                    checked += 1
        assert checked > 100


def test_conv_plan_keeps_what_each_kernel_reads():
    """wav2vec 2.0's strides: the first layer reads 2 samples past its step, so every later layer lags one step
    and the features one feature; each layer keeps stride * lag_out + padding - lag_in inputs."""
    plans = conv_plan(conv_kernels((5, 2, 2, 2, 2, 2, 2)), (5, 2, 2, 2, 2, 2, 2), FRAME)
    assert [(p.keep, p.lag_in, p.lag_out, p.right_pad) for p in plans] == [
        (8, 0, 1, 2), (2, 1, 1, 0), (2, 1, 1, 0), (2, 1, 1, 0), (2, 1, 1, 0), (1, 1, 1, 0), (1, 1, 1, 0)]
    with pytest.raises(ValueError, match="does not stream"):
        conv_plan((3,), (3,), 640)  # 640 samples are not a whole number of stride-3 steps


def test_the_bundle_graph_is_its_torch_module(small_export):
    """The bundle's streaming graph and its steady form against the torch modules, on the state they share,
    batched, uneven calls, provisional frames and a call that commits nothing; their weights are the translator's
    buffers, stored once."""
    bundle = Bundle(small_export.path)
    assert STREAM_GRAPH in bundle.graph_names() and STEADY_STREAM_GRAPH in bundle.graph_names()
    for graph in (STREAM_GRAPH, STEADY_STREAM_GRAPH):
        stream_buffers = set(bundle.graph_info(graph)["initializers"].values())
        assert stream_buffers and stream_buffers <= set(bundle.graph_info("translator")["initializers"].values())
    driver = open_driver(small_export.path)
    modules = {True: MotionTranslatorStream(small_export.speaker.translator).eval(),
               False: MotionTranslatorStream(small_export.speaker.translator, call_refresh=0).eval()}
    module = modules[True]
    assert driver.has_stream and driver.stream_spec.delay == module.delay_frames == 4 and driver.stream_spec.steady
    rng = np.random.default_rng(1)
    state = np.zeros((3, module.state_size), np.float32)
    for frames, keep, refresh in ((REST_FRAMES, REST_FRAMES, True), (1, 1, False), (5, 3, True), (2, 0, False),
                                  (8, 8, False), (1, 1, True), (3, 2, False)):
        audio = (0.1 * rng.standard_normal((3, frames, FRAME))).astype(np.float32)
        out = driver.run_stream(audio, state, keep, refresh)
        with torch.no_grad():
            expected = modules[refresh](torch.from_numpy(audio), torch.from_numpy(state),
                                        torch.tensor([float(keep)]))
        for name, value in zip(("expression", "jaw_pose", "state_out"), expected, strict=False):
            assert np.abs(out[name] - value.numpy()).max() < 1e-5, (frames, keep, refresh, name)
        state = out["state_out"]


def test_every_window_of_the_state_is_read_by_a_slice(small_speaker, monkeypatch):
    """The stream's windows of its state (each kept part after a call: the statistics, the refreshed audio, the
    features, each convolution's inputs, each transformer layer's keys and values) export as Gathers, which
    window_slices.py makes Slices: every one of them, and none is left in the exported graph. (The statistics: the
    waveform's, and the first convolution's means and variances apart.)"""
    stream = MotionTranslatorStream(small_speaker.translator)
    layers = len(small_speaker.translator.audio_encoder.encoder.layers) + len(
        small_speaker.translator.motion_decoder.decoder.layers)
    windows = 5 + len(stream.plans) + 2 * layers  # a layer's keys and values: two windows
    monkeypatch.setattr(translator_graph, "window_gathers_to_slices", lambda model: 0)
    traced = translator_graph.translator_stream_onnx(small_speaker.translator)
    assert window_gathers_to_slices(traced) == windows
    monkeypatch.undo()
    assert window_gathers_to_slices(translator_graph.translator_stream_onnx(small_speaker.translator)) == 0


def test_a_call_takes_the_last_calls_states_whole_only_when_its_sessions_are_that_calls_in_order():
    """run_stream_jobs passes the last call's state_out itself when a call's sessions are that call's, in its order
    (each stream's state still its row there); any other set or order is stacked from the states, which are the
    same values either way."""
    import types

    last = np.arange(12, dtype=np.float32).reshape(3, 4)

    def jobs_of(rows):
        streams = [types.SimpleNamespace(state=last[k], state_row=(last, k)) for k in rows]
        return [StreamJob(stream, np.zeros((1, 2), np.float32), 1) for stream in streams]

    assert _stacked_states(jobs_of([0, 1, 2])) is last  # that call's sessions in its order: no copy
    for rows in ([0, 2, 1], [0, 1], [1, 2]):  # another order, fewer sessions: stacked
        got = _stacked_states(jobs_of(rows))
        assert got is not last and np.array_equal(got, last[rows])
    fresh = [types.SimpleNamespace(state=last[k].copy(), state_row=None) for k in range(3)]  # never pooled
    got = _stacked_states([StreamJob(stream, np.zeros((1, 2), np.float32), 1) for stream in fresh])
    assert got is not last and np.array_equal(got, last)


@pytest.mark.parametrize(("kernel", "stride"), [(10, 5), (3, 2), (2, 2), (4, 2), (5, 2), (1, 2), (7, 3)])
def test_the_time_major_convolution_is_conv1d(kernel, stride):
    """The stream's feature encoder runs its convolutions time-major, taps side by side into one MatMul: the same
    outputs as F.conv1d for kernels shorter than, equal to, between and at twice the stride, at every input length
    of a few strides (float rounding: 1e-5)."""
    generator = torch.Generator().manual_seed(kernel * 10 + stride)
    weight = torch.randn(6, 4, kernel, generator=generator)
    for length in range(kernel, kernel + 3 * stride):
        x = torch.randn(2, 4, length, generator=generator)
        expected = torch.nn.functional.conv1d(x, weight, None, stride).transpose(1, 2)
        got = _conv_time_major(x.transpose(1, 2).contiguous(), weight, stride)
        assert got.shape == expected.shape
        torch.testing.assert_close(got, expected, atol=1e-5, rtol=1e-5)


def _first_layer_reference(stream, inputs, frames, waveform, weights, own_means, variances):
    """The first convolution and its GroupNorm as the windowed graph takes them, in float64: c = conv(x - m), each
    frame's mean of c (a kept frame's from its mean relative to its own waveform mean, `own_means`) and variance
    pooled over the window, one scale and shift a channel. Returns the outputs and the new frames' means (relative
    to their own waveform means, as kept) and variances."""
    frame_means, window_mean, audio_scale = waveform
    layer, plan = stream.translator.audio_encoder.feature_extractor.conv_layers[0], stream.plans[0]
    weight = layer.conv.weight.double()
    c = torch.nn.functional.conv1d((inputs - window_mean).transpose(1, 2), weight, stride=plan.stride)
    c = c.transpose(1, 2)  # [B, m, C]
    exact = c[:, :frames * stream.conv0_rate].reshape(c.shape[0], frames, stream.conv0_rate, c.shape[2])
    offsets = (frame_means - window_mean[:, 0]).unsqueeze(-1)  # [B, W + n, 1]
    sums = weight.sum(dim=(1, 2))  # [C]: the weight's sum a channel
    new_means, new_vars = exact.mean(2), exact.var(2, unbiased=False)
    means = torch.cat([own_means + offsets[:, :-frames] * sums, new_means], 1)
    mean, var = _pooled(means, torch.cat([variances, new_vars], 1), weights[:, None], dim=1)
    norm = layer.layer_norm
    scale = audio_scale * torch.rsqrt(audio_scale ** 2 * var + stream.group_norm_eps) * norm.weight.double()
    return c * scale + (norm.bias.double() - mean * scale), new_means - offsets[:, -frames:] * sums, new_vars


@pytest.mark.parametrize("signal", ["speech-like noise", "silence", "dc with a whisper", "low sine", "clipped square",
                                    "near silence"])
def test_the_first_layers_statistics_from_its_taps_are_the_convolutions(small_speaker, signal):
    """The stream takes the first convolution's per-frame mean and variance from its taps' mean and covariance and
    folds the GroupNorm into the weight: its outputs equal the convolution of the waveform less the window's mean,
    normalised by its own outputs' statistics (float64 here), finite, for quiet and loud audio, a DC offset with a
    whisper on it, tiny and huge waveform scales, and a window whose kept frames are like the new ones (the pooled
    variance then the new frames' own: near zero for silence). Within 2e-5 (float32 rounding: 6e-6 measured at
    worst, on a low sine whose taps barely differ; 4e-7 for the DC offset at scale 3000, where statistics of the
    raw convolution lost 0.2); the last output, which reads the call's padding (zeros of x, not of x - m, as the
    stream's padding always was: provisional, made again next call), within 1e-4 of its own size (2e-7 measured).
    It keeps the new frames' statistics as the reference has them."""
    stream = MotionTranslatorStream(small_speaker.translator, call_refresh=0).eval()
    layer, plan = stream.translator.audio_encoder.feature_extractor.conv_layers[0], stream.plans[0]
    frames, window, channels = 2, stream.window_frames, stream.channels
    length = plan.keep + frames * FRAME + plan.right_pad
    t = torch.arange(length, dtype=torch.float64) / 16000
    noise = torch.randn(length, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    sig = {"speech-like noise": 0.1 * noise, "silence": torch.zeros(length, dtype=torch.float64),
           "dc with a whisper": 0.5 + 1e-6 * noise, "low sine": 0.9 * torch.sin(2 * np.pi * 20 * t),
           "clipped square": torch.sign(torch.sin(2 * np.pi * 200 * t)), "near silence": 1e-7 * noise}[signal]
    sig[length - plan.right_pad:] = 0.0  # the padding after the call's last sample
    inputs = sig.float().double().reshape(1, length, 1)  # the samples float32 holds (a whisper on 0.5 keeps 4 bits)
    own = sig[plan.keep:plan.keep + frames * FRAME].reshape(frames, FRAME).mean(1)  # the new frames' means
    # the kept frames' like the first new one; float32 values, as the state keeps them (a kept frame's mean of c is
    # kept relative to its waveform mean as the state holds it, and read back so)
    frame_means = torch.cat([own[:1].expand(window), own])[None].float().double()
    window_mean = frame_means.mean(1).reshape(1, 1, 1).float().double()
    weights = torch.ones(window + frames, dtype=torch.float64)
    for audio_scale in (1.0, 3000.0):
        waveform = (frame_means, window_mean, torch.full((1, 1, 1), audio_scale, dtype=torch.float64))
        kept_stats = [(0.01 * torch.rand(1, window, channels, dtype=torch.float64),
                       1e-3 * torch.rand(1, window, channels, dtype=torch.float64))]
        _, new_means, new_vars = _first_layer_reference(stream, inputs, frames, waveform, weights, *kept_stats[0])
        kept_stats.append((new_means[:, :1].expand(1, window, channels),
                           new_vars[:, :1].expand(1, window, channels)))  # the window like its new frames
        for means, variances in kept_stats:
            expected, new_means, new_vars = _first_layer_reference(stream, inputs, frames, waveform, weights, means,
                                                                   variances)
            kept, made = {"conv0_means": means.float(), "conv0_variances": variances.float()}, {}
            with torch.no_grad():
                got = stream._normalised_first(inputs.float(), frames, tuple(part.float() for part in waveform),
                                               weights.float(), kept, made, layer, plan)
            assert torch.isfinite(got).all()
            error, exact = torch.abs(got.double() - expected), frames * stream.conv0_rate
            assert error[:, :exact].max() < 2e-5, (signal, audio_scale)
            assert error[:, exact:].max() < 1e-4 * max(1.0, float(expected[:, exact:].abs().max())), signal
            assert torch.abs(made["conv0_means"][:, window:].double() - new_means).max() < 1e-5
            assert torch.abs(made["conv0_variances"][:, window:].double() - new_vars).max() < 1e-5


@pytest.mark.parametrize("kernel", [3, 4, 15, 16])
def test_the_positional_tail_is_the_embeddings_last_rows(kernel):
    """The stream computes only the tail's rows of the positional convolution: they equal the whole window's last
    rows (float32 rounding of a convolution over another length, ~6e-7 measured), the window longer than the
    rows it reads or not."""
    embedding = PositionalConvEmbedding(32, kernel, 4).eval()
    for length, tail in ((21, 12), (12, 12), (40, 3), (7, 7)):
        x = torch.randn(2, length, 32, generator=torch.Generator().manual_seed(length))
        with torch.no_grad():
            expected, rows = embedding(x)[:, length - tail:], _positional_tail(embedding, x, tail)
        assert rows.shape == expected.shape and torch.abs(rows - expected).max() < 1e-5, (length, tail)


def _verdicts(powers: np.ndarray, batch: int = 1) -> list[bool]:
    """The loudness gate's verdict for each call of `batch` frames over frames of mean squares `powers`, from rest."""
    made, verdicts = np.zeros(REFRESHED_FRAMES), []
    for end in range(batch, powers.shape[0] + 1, batch):
        now = window_loudness(powers[:end])
        verdicts.append(loudness_moved(now, made))
        made = made_after(made, batch, verdicts[-1], now)
    return verdicts


def test_the_steady_graph_runs_while_the_loudness_holds():
    """A call refreshes where the window's loudness is off by the ratio from the loudness the frames it would make
    again were made at (an utterance's start after silence, its end), and not where it holds (steady speech,
    silence)."""
    speech = np.full(60, 0.01)
    assert not any(_verdicts(np.zeros(40)))  # silence stays silence
    start = _verdicts(np.concatenate([np.zeros(40), speech]))
    # the first loud frame after silence, then wherever the window's loudness passed twice the loudness its last
    # frames were made at (each refresh made them again at the loudness then): 3 refreshes as the window fills
    assert [k - 40 for k, moved in enumerate(start) if moved] == [0, 2, 6]
    assert not any(_verdicts(speech * np.linspace(0.8, 1.2, 60))[LOUDNESS_WINDOW_FRAMES:])  # drifting, not jumping
    # its end: the window's loudness falls gradually as silence fills it, and past the ratio at its last frames
    end = _verdicts(np.concatenate([speech, np.zeros(LOUDNESS_WINDOW_FRAMES)]))
    assert [k - 60 for k, moved in enumerate(end) if moved and k >= 60] == [25, 27, 28]
    # a refresh makes the last frames again: the loudness they were made at is the newest
    assert made_after(np.zeros(REFRESHED_FRAMES), 1, True, 0.5).tolist() == [0.5] * REFRESHED_FRAMES
    assert made_after(np.arange(4.0), 1, False, 9.0).tolist() == [1.0, 2.0, 3.0, 9.0]
    assert made_after(np.arange(4.0), 0, True, 9.0).tolist() == [0.0, 1.0, 2.0, 3.0]  # nothing committed
    # a call of 8 frames moves the window further than one of a frame: its verdicts are its own
    assert _verdicts(np.concatenate([np.zeros(16), speech[:16]]), 8) == [False, False, True, True]


def test_a_live_session_calls_the_steady_graph_mid_utterance(small_export):
    """A live session of a bundle with the steady graph calls it for most frames of unseen speech and the
    refreshing graph where the loudness moves (its start after silence)."""
    driver = open_driver(small_export.path)
    calls = []
    run_stream = driver.run_stream

    def recording(audio, state, keep, refresh=True):
        calls.append(refresh)
        return run_stream(audio, state, keep, refresh)

    driver.run_stream = recording
    audio = unseen_speech()[0]
    live_rows(driver, np.concatenate([np.zeros(16000, np.float32), audio]), None)
    steady = calls.count(False)
    assert calls[0] is True and 0 < calls.count(True) < steady, (calls.count(True), steady)


def live_rows(driver, audio: np.ndarray, streaming: bool, **options) -> tuple[np.ndarray, LiveSession]:
    """A free-running session fed `audio` in uneven chunks then flushed: every frame's expression and jaw."""
    frames = []
    with LiveSession(driver, output=None, paced=False, streaming=streaming, **options) as live:
        for piece in np.split(audio, np.cumsum([3000, 320, 7777, 640, 12000])):
            live.push(piece, 16000)
            frames += live.poll()
        live.flush()
        live.end()
        frames += list(live.frames())
    return np.stack([_row(frame.drive) for frame in frames]), live


def _row(drive) -> np.ndarray:
    return np.concatenate([drive.expression, np.ravel(drive.flame_pose)])


@pytest.mark.parametrize("batch_frames", [1, 8])
def test_live_sessions_stream_the_speakers_translator(small_export, batch_frames):
    """By default a live session of the speaker streams (fewer translator computations for the same calls); on
    unseen speech its drives follow the windowed session's and the whole clip's (module docstring's bounds)."""
    driver = open_driver(small_export.path)
    for audio in unseen_speech():
        options = {"min_batch_frames": batch_frames}
        streamed, live = live_rows(driver, audio, None, **options)
        windowed, _ = live_rows(driver, audio, False, **options)
        assert live._stream is not None and streamed.shape == windowed.shape
        offline = np.stack([_row(drive) for drive in driver.drives(audio, 16000)])
        count = min(offline.shape[0], streamed.shape[0])
        live_r = busiest_r(streamed, windowed)
        stream_offline, windowed_offline = (busiest_r(rows[:count], offline[:count]) for rows in (streamed, windowed))
        print(f"batch {batch_frames}: stream~windowed live r {live_r:.3f}; against offline: stream "
              f"{stream_offline:.3f}, windowed live {windowed_offline:.3f}")
        assert live_r >= 0.85
        assert stream_offline >= windowed_offline - 0.05


def test_the_bench_compares_the_stream_with_the_windowed_calls(small_speaker, monkeypatch):
    """`gt-bench translator-stream` on one clip: the windowed translator's and the streams' (whole-window and
    K/V-cached transformers) rows scored against offline, each stream within 0.05 of the windowed calls there, and
    a cost row per case with the windowed graph as the reference."""
    import tools.bench.translator_stream as bench

    clip = unseen_speech()[0]
    monkeypatch.setattr(bench, "unseen_clips", lambda: [("held-out", clip[:clip.shape[0] // FRAME * FRAME])])
    variants = bench.stream_variants([0, 4], [None, 3, 5])
    assert variants == [(0, None), (0, 5), (4, None), (4, 5)]  # a tail of 3 is shorter than the delay
    quality = bench.run_quality(small_speaker.translator, [(4, None), (4, 5)], [1])
    scores = quality["clips"][0]["r"]
    assert set(scores) == {"windowed, 1 a call", "stream, refresh 4, 1 a call", "stream, refresh 4, tail 5, 1 a call"}
    assert scores["stream, refresh 4, 1 a call"] >= scores["windowed, 1 a call"] - 0.05
    assert scores["stream, refresh 4, tail 5, 1 a call"] >= scores["windowed, 1 a call"] - 0.05
    cost = bench.run_cost(small_speaker.translator, [(4, None), (4, 5)], [(2, 1)], rounds=1)
    assert set(cost[0]["ms_per_session_frame"]) == {"windowed", "stream, refresh 4", "stream, refresh 4, tail 5"}
    table = bench.translator_stream_table({"quality": quality, "cost": cost})
    assert "| held-out |" in table and "| 2 | 1 |" in table and "× less" in table and "BASE" not in table
    table = bench.translator_stream_table({"quality": quality, "cost": cost, "cost_base_size": cost})
    assert table.count("| 2 | 1 |") == 2 and "wav2vec 2.0 BASE's size" in table


def test_the_stream_gets_its_onnxruntime_session_on_first_use(small_export):
    """Opening a bundle checks the streaming graph with the others but builds its session only when a live session
    first runs it: offline rendering never pays for it."""
    driver = open_driver(small_export.path)
    assert driver.has_stream and STREAM_GRAPH not in driver.graphs.sessions
    assert driver.stream_spec.delay == 4  # the first call
    assert STREAM_GRAPH in driver.graphs.sessions
