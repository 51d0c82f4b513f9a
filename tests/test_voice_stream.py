"""The built-in voice's streaming graph (exporter/export/voice_stream.py) and live sessions that run it
(runtime/translate_stream.py, runtime/live.py; docs/live.md, "Streaming translators").

Tolerances: the streaming graph computes the windowed graph's convolutions over other lengths, so sums may be
ordered differently; on weights in 0..1 (and FLAME expressions up to ~3) float32 rounding stays below 1e-5, the
bound held for every rig whose frames are the voice's (25 fps). A 30 fps rig reads the 25 fps rows at its frames'
centres: there the bound is against that interpolation of the whole clip's rows (the windowed path, which resamples
each window on its own, is off by up to ~0.3 from it; the test reports it).
"""

from __future__ import annotations

import types
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import pytest
from ci_tools import need_module
from unseen_speech import unseen_speech

from gaussiantalker.exporter.export.voice_stream import is_voice_graph, stream_model_of, voice_layout
from gaussiantalker.exporter.voice.paths import ARKIT_MODEL, FLAME_MODEL
from gaussiantalker.runtime import LiveSession
from gaussiantalker.runtime.stages import open_driver
from gaussiantalker.runtime.translate_stream import REST_FRAMES, StreamJob, pads_exactly, run_stream_jobs
from gaussiantalker.sdk.bundle import STREAM_GRAPH, Bundle
from gaussiantalker.sdk.errors import LiveError

FRAME = 640
EXACT = 1e-5  # float32 rounding of the same convolutions summed in another order


def _sessions(path: Path) -> tuple[ort.InferenceSession, ort.InferenceSession]:
    model = onnx.load(str(path))
    return (ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"]),
            ort.InferenceSession(stream_model_of(model).SerializeToString(), providers=["CPUExecutionProvider"]))


def _rest(stream: ort.InferenceSession) -> np.ndarray:
    size = stream.get_inputs()[1].shape[1]
    out = stream.run(["state_out"], {"audio": np.zeros((1, REST_FRAMES, FRAME), np.float32),
                                     "state": np.zeros((1, size), np.float32),
                                     "keep": np.array([REST_FRAMES], np.float32)})
    return out[0]


@pytest.mark.parametrize("path", [ARKIT_MODEL, FLAME_MODEL], ids=["arkit", "flame"])
def test_the_stream_gives_the_windowed_graphs_rows(path):
    """Fed a frame at a time, or in uneven calls whose tails are provisional (zeros standing in for lookahead not
    yet in, not committed), from the rest state: every row equals the windowed graph's on the whole clip."""
    windowed, stream = _sessions(path)
    names = [o.name for o in windowed.get_outputs()]
    delay = int(stream.run(["delay_frames"], {"audio": np.zeros((1, 1, FRAME), np.float32), "state": _rest(stream),
                                              "keep": np.array([1], np.float32)})[0][0])
    assert delay == 4  # 160 ms: the network's reach into the future, in frames
    rng = np.random.default_rng(0)
    for audio in unseen_speech():
        frames = audio.shape[0] // FRAME
        audio = audio[:frames * FRAME]
        expected = windowed.run(names, {"audio": audio[None]})
        fed = np.concatenate([audio, np.zeros(delay * FRAME, np.float32)]).reshape(-1, FRAME)
        state, rows, position = _rest(stream), [], 0
        while position < fed.shape[0]:
            keep = int(min(rng.integers(1, 6), fed.shape[0] - position))
            provisional = int(rng.integers(0, 3))
            chunk = np.concatenate([fed[position:position + keep], np.zeros((provisional, FRAME), np.float32)])
            feeds = {"audio": chunk[None], "state": state, "keep": np.array([keep], np.float32)}
            out = stream.run(names + ["state_out"], feeds)
            rows.append([o[0, :keep] for o in out[:-1]])
            if provisional:  # a provisional tail: the rows the windowed graph gives with zeros after the audio
                ahead = np.concatenate([fed[:position + keep].reshape(-1), np.zeros(provisional * FRAME,
                                                                                    np.float32)])
                padded = windowed.run(names, {"audio": ahead[None]})
                first = position - delay
                for k, name in enumerate(names):
                    got, want = out[k][0, max(-first, 0):], padded[k][0, max(first, 0):]
                    count = min(got.shape[0], want.shape[0])
                    assert np.abs(got[:count] - want[:count]).max() < EXACT, name
            state, position = out[-1], position + keep
        for k, name in enumerate(names):
            got = np.concatenate([r[k] for r in rows])[delay:delay + frames]
            assert got.shape == expected[k][0].shape
            assert np.abs(got - expected[k][0]).max() < EXACT, name


@pytest.mark.parametrize("per_call", [None, 3, "padded"], ids=["one-call", "split", "padded"])
def test_sessions_batched_in_one_call_get_their_own_rows(monkeypatch, per_call):
    """Four streams at different places in different clips, stacked on the batch axis in one call (what the live
    server's pool does), each get the rows and state they get alone; so do they where the states' bytes allow three
    a call (MAX_CALL_STATE_BYTES: two calls of two, not three and one); and, for a graph that pads exactly, calls of
    1 to 4 frames (one committed) stacked into one, zero-padded to 4."""
    import gaussiantalker.runtime.translate_stream as translate_stream

    _, stream = _sessions(ARKIT_MODEL)
    clips = unseen_speech()[:1] * 4
    states = [_rest(stream) for _ in clips]
    lengths = [1 + k if per_call == "padded" else 1 for k in range(len(clips))]
    chunks = [clip[(7 + 5 * k) * FRAME:(7 + 5 * k + n) * FRAME].reshape(1, n, FRAME)
              for k, (clip, n) in enumerate(zip(clips, lengths, strict=True))]
    alone = [stream.run(None, {"audio": c, "state": s, "keep": np.array([1], np.float32)})
             for c, s in zip(chunks, states, strict=True)]

    class Fake:
        def __init__(self, state):
            self.state = state[0]
            self.state_row = None  # as a stream that no pooled call has finished
            self.spec = types.SimpleNamespace(pads_exactly=per_call == "padded", graphs=None)

    jobs = [StreamJob(Fake(s), c[0], 1) for c, s in zip(chunks, states, strict=True)]

    def run(audio, state, keep, refresh):
        names = [o.name for o in stream.get_outputs()]
        feeds = {"audio": audio, "state": state, "keep": np.array([keep], np.float32)}
        return dict(zip(names, stream.run(names, feeds), strict=True))

    if per_call == 3:
        monkeypatch.setattr(translate_stream, "MAX_CALL_STATE_BYTES", 4 * per_call * jobs[0].stream.state.shape[0])
    assert run_stream_jobs(jobs, run, lambda out: out["blendshapes"]) == ([2, 2] if per_call == 3 else [4])
    for job, single, n in zip(jobs, alone, lengths, strict=True):
        assert job.rows.shape[0] == n
        assert np.abs(job.rows - single[0][0]).max() < EXACT and np.abs(job.state - single[1][0]).max() < EXACT


def test_a_group_too_big_for_one_call_is_split_evenly():
    """The fewest calls within the cap, their sizes one apart at most, in order (`call_bounds`)."""
    from gaussiantalker.runtime.translate_stream import call_bounds

    assert call_bounds(37, 36) == [(0, 19), (19, 37)]
    assert call_bounds(50, 36) == [(0, 25), (25, 50)]
    assert call_bounds(73, 36) == [(0, 25), (25, 49), (49, 73)]
    assert call_bounds(36, 36) == [(0, 36)] and call_bounds(1, 36) == [(0, 1)] and call_bounds(0, 36) == []


def test_the_voice_graph_pads_exactly():
    """The built-in voice's stream reads no frame past its delay, so its spec says it pads exactly (its calls of
    different lengths may share one call); a graph whose rows read the call's later frames is told apart."""
    _, stream = _sessions(ARKIT_MODEL)
    names = [o.name for o in stream.get_outputs()]

    def run(audio, state, keep, refresh):
        feeds = {"audio": audio, "state": state, "keep": np.array([keep], np.float32)}
        return dict(zip(names, stream.run(names, feeds), strict=True))

    def rows_of(out):
        return out["blendshapes"]

    rest = _rest(stream)[0]
    assert pads_exactly(run, rows_of, rest, FRAME)

    def reads_ahead(audio, state, keep, refresh):  # every row scaled by the call's last frame's level
        out = run(audio, state, keep, refresh)
        return {**out, "blendshapes": out["blendshapes"] * (1 + np.abs(audio[:, -1:, :1]))}

    assert not pads_exactly(reads_ahead, rows_of, rest, FRAME)


def test_stream_layout_follows_the_network():
    """The state's parts and the delay are read from the windowed graph's blocks; only the built-in voice has a
    stream."""
    model = onnx.load(str(ARKIT_MODEL))
    assert is_voice_graph(model)
    layout = voice_layout(model)
    from gaussiantalker.exporter.voice.model import SAMPLES_PER_FRAME, VoiceConfig

    config = VoiceConfig()
    assert layout.blocks == config.blocks and layout.channels == config.channels
    assert layout.frame_samples == SAMPLES_PER_FRAME and layout.delay_frames == 4
    stream = stream_model_of(model)
    # docs/voice.md lists these: long-standing standard ops, at the windowed graph's opset; every convolution is a
    # MatMul over its taps
    ops = {n.op_type for n in stream.graph.node}
    assert ops <= {n.op_type for n in model.graph.node} | {"Concat", "Reshape", "Flatten", "Cast", "Constant",
                                                           "MatMul"}
    assert "Conv" not in ops
    assert [o.version for o in stream.opset_import] == [o.version for o in model.opset_import] == [17]
    size = [d.dim_value for d in stream.graph.input[1].type.tensor_type.shape.dim][1]
    assert size == sum(part.size for part in layout.state_parts()) == 4056
    other = onnx.ModelProto.FromString(model.SerializeToString())
    other.producer_name = "someone else"
    assert stream_model_of(other) is None


def _drive_rows(frames) -> np.ndarray:
    rows = []
    for frame in frames:
        drive = frame.drive
        values = [drive.blendshapes] if hasattr(drive, "blendshapes") else [drive.expression, drive.flame_pose]
        rows.append(np.concatenate([np.ravel(v) for v in values]))
    return np.stack(rows)


def _live(driver, pushes, streaming: bool, **options) -> tuple[np.ndarray, LiveSession]:
    """A free-running session fed `pushes` (arrays, or "interrupt"/"flush"), every frame read."""
    frames = []
    with LiveSession(driver, output=None, paced=False, streaming=streaming, **options) as live:
        for item in pushes:
            if isinstance(item, str):
                getattr(live, item)()
                frames += live.poll()
            else:
                live.push(item, 16000)
                frames += live.poll()
        live.end()
        frames += list(live.frames())
    return _drive_rows(frames), live


def _pushes(audio: np.ndarray) -> list:
    """Speech in uneven chunks, a barge-in in the middle, more speech after it."""
    cut = np.cumsum([3000, 320, 7777, 640, 12000])
    pieces = np.split(audio[:cut[-1]], cut[:-1])
    return [*pieces, "interrupt", audio[cut[-1]:cut[-1] + 20000], "flush", audio[:9000]]


def test_a_live_session_streams_the_built_in_flame_voice(ga_voice_bundle):
    """A 25 fps FLAME avatar: the streaming session's drives equal the windowed session's (chunked pushes, a
    barge-in, a flush, lookahead 160 and 80 ms), with fewer translator computations; streaming=False keeps the
    windowed path."""
    driver = open_driver(ga_voice_bundle)
    assert driver.has_stream and driver.stream_spec.delay == 4
    for audio in unseen_speech()[:2]:
        for lookahead in (160.0, 80.0):
            windowed, _ = _live(driver, _pushes(audio), False, lookahead_ms=lookahead)
            streamed, live = _live(driver, _pushes(audio), True, lookahead_ms=lookahead)
            assert windowed.shape == streamed.shape and live.stats.translator_calls > 0
            assert np.abs(windowed - streamed).max() < EXACT * 4, lookahead  # FLAME: the maps' sums on top


def test_a_30_fps_avatar_reads_the_stream_at_its_frame_centres(lam_voice_bundle):
    """A LAM avatar plays at 30 fps; the voice's rows are 25 fps. The stream interpolates them at each frame's
    centre: within 5e-3 of that interpolation of the whole clip's rows (loud speech: no gate applies). Not to
    rounding: a frame's later row can reach up to 40 ms past the session's lookahead, which a free-running session
    given audio in two pushes fills with zeros for the frames just before the first push ends (1.3e-3 measured)."""
    driver = open_driver(lam_voice_bundle)
    windowed_graph, _ = _sessions(ARKIT_MODEL)
    audio = unseen_speech()[0]
    audio = np.clip(audio * (0.5 / np.abs(audio).max()), -1, 1)  # loud: the silence gate stays open
    streamed, _ = _live(driver, [audio[:5000], audio[5000:]], True)
    windowed, _ = _live(driver, [audio[:5000], audio[5000:]], False)
    padded = np.concatenate([audio, np.zeros(5 * FRAME, np.float32)])  # the windowed graph cuts a short tail
    whole = windowed_graph.run(None, {"audio": padded[None]})[0][0]
    count = min(streamed.shape[0], int(audio.shape[0] / (16000 / 30)))
    centres = (np.arange(count) + 0.5) * 25 / 30 - 0.5
    exact = np.stack([np.interp(centres, np.arange(whole.shape[0]), whole[:, k]) for k in range(52)], 1)
    # frame 0's centre lies before the clip's first row: the stream blends in the silent row there
    assert np.abs(streamed[1:count] - exact[1:]).max() < 5e-3
    print(f"30 fps: windowed session off the interpolation by up to {np.abs(windowed[1:count] - exact[1:]).max():.3f}")


def test_a_bundle_carries_the_stream_beside_its_translator_sharing_weights(lam_voice_bundle, small_export,
                                                                           replay_onnx_exports, monkeypatch,
                                                                           tmp_path):
    """The streaming graph's weights are the translator's buffers (stored once); a bundle without a stream (one
    exported before streaming) plays windowed, and asking it for a stream is a clear error."""
    import gaussiantalker.exporter.export.bundle_export as bundle_export

    bundle = Bundle(lam_voice_bundle)
    assert STREAM_GRAPH in bundle.graph_names()
    stream_buffers = set(bundle.graph_info(STREAM_GRAPH)["initializers"].values())
    assert stream_buffers and stream_buffers <= set(bundle.graph_info("translator")["initializers"].values())
    monkeypatch.setattr(bundle_export, "translator_stream_onnx", lambda translator, **options: None)
    replay_onnx_exports([small_export.protos[0], small_export.protos[3]])  # translator, deform
    older = bundle_export.export_bundle(small_export.speaker, tmp_path / "older.gtb", progress=False).path
    driver = open_driver(older)
    assert not driver.has_stream
    with pytest.raises(LiveError, match="no streaming graph"):
        LiveSession(driver, output=None, streaming=True)


def test_an_idle_streaming_session_holds_and_computes_nothing(ga_voice_bundle):
    """Idle frames after speech: once a second of silence has passed, the stream restarts at rest and its known
    audio stays empty, so a quiet session costs no translator calls."""
    import itertools

    driver = open_driver(ga_voice_bundle)
    live = LiveSession(driver, output=None, paced=False, streaming=True)
    live.push(unseen_speech()[0][:8000], 16000)
    live.flush()
    frames = live.frames()  # free-running: idle frames as fast as they are read once the speech is out
    first = list(itertools.islice(frames, 80))
    assert first[0].speaking and not first[-1].speaking
    calls = live.stats.translator_calls
    more = list(itertools.islice(frames, 50))
    assert not any(f.speaking for f in more) and live.stats.translator_calls == calls
    assert live._stream.known.shape[0] == 0 and live._stream.committed == 0
    live.close()


def test_idle_frames_at_rest_take_the_short_path_to_the_same_drives(ga_voice_bundle, monkeypatch):
    """Speech, a long idle gap, speech again, a long gap: the drives, the silence gate's sums and the stream (its
    origin, state and what it knows) are those of the full idle step (every idle frame offered to the stream,
    which resets itself, and zeros pushed through the gate's sums), bit for bit; the short path only moves a stream
    at rest to the gap's end and counts the zeros."""
    import itertools

    from gaussiantalker.runtime import live as live_module
    from gaussiantalker.runtime.translate_stream import TranslatorStream

    speech = unseen_speech()[0]

    def played() -> tuple[list[np.ndarray], tuple, tuple]:
        live = LiveSession(open_driver(ga_voice_bundle), output=None, paced=False, streaming=True)
        frames = live.frames()
        drives = []
        for chunk in (speech[:8000], speech[8000:20000]):
            live.push(chunk, 16000)
            live.flush()
            drives += [np.concatenate([np.ravel(v) for v in f.drive.graph_inputs().values()])
                       for f in itertools.islice(frames, 90)]  # the chunk, then over a second of idle frames
        gate, stream = live._gate, live._stream
        sums = (gate.count, gate.total, gate.squares, list(gate.frames))
        kept = (stream.origin, stream.committed, stream.known.tobytes(), stream.state.tobytes(), stream.quiet)
        live.close()
        return drives, sums, kept

    short = played()
    full_idle = TranslatorStream.idle

    def idle_in_full(self, start, stop):
        self._at_rest = False
        full_idle(self, start, stop)

    monkeypatch.setattr(TranslatorStream, "idle", idle_in_full)
    monkeypatch.setattr(live_module._GateHistory, "push_silence",
                        lambda self, count: self.push((count, *(float(v[0]) for v in live_module.frame_sums(
                            np.zeros((1, count), np.float32))))))
    full = played()
    assert len(short[0]) == len(full[0]) == 180
    for a, b in zip(short[0], full[0], strict=True):
        np.testing.assert_array_equal(a, b)
    assert short[1:] == full[1:]
    assert short[2][1] == 0 and short[2][2] == b""  # the session ended at rest: the short path was taken


def test_paced_sessions_share_one_translator_call_per_tick(ga_voice_bundle):
    """Four paced sessions on one clock grid, stepped as the live server's pool does (every session's planned
    call gathered, run as one, then each steps): one call per tick for all of them, and each session's drives are
    those it makes stepped alone."""
    import time

    driver = open_driver(ga_voice_bundle)
    speech = unseen_speech()[0][:16000]
    starts = [0, 1600, 5000, 9000]

    def sessions():
        out = []
        for offset in starts:
            live = LiveSession(driver, output=None, paced=True, streaming=True, clock_grid_s=0.04)
            live.push(np.concatenate([np.zeros(offset, np.float32), speech]), 16000)
            live.end()
            live._anchor = (time.monotonic() - 100.0, 0)  # every frame due now: no waiting in a test
            out.append(live)
        return out

    def rows_of(lives, together: bool):
        frames, calls = [[] for _ in lives], 0
        while not all(live.finished for live in lives):
            if together:
                jobs = [job for live in lives if (job := live.stream_job()) is not None]
                if jobs:
                    calls += len(run_stream_jobs(jobs, driver.run_stream, driver.stream_rows))
            for k, live in enumerate(lives):
                if not live.finished:
                    live._anchor = (time.monotonic() - 100.0, live._next_index)
                    frame = live.step()
                    if frame is not None:
                        frames[k].append(frame)
        return [_drive_rows(f) for f in frames], calls

    alone, _ = rows_of(sessions(), False)
    together, calls = rows_of(sessions(), True)
    ticks = max(len(r) for r in together)
    assert calls <= ticks  # one call per tick at most, whatever the number of sessions
    for a, b in zip(alone, together, strict=True):
        assert a.shape == b.shape and np.abs(a - b).max() < EXACT * 4


def test_the_mnn_backend_runs_the_stream(tmp_path):
    """A bundle exported with --mnn carries the streaming graph as an MNN model too, and a live session on the MNN
    backend gives the onnxruntime session's drives (1e-4: MNN's own kernels)."""
    need_module("MNN", "mnn")
    from lam_avatars import write_avatar_zip

    from gaussiantalker.exporter.export.bundle_export import export_bundle
    from gaussiantalker.exporter.imports.sources.lam import import_lam
    from gaussiantalker.exporter.voice.attach import builtin_audio_model

    speaker = import_lam(write_avatar_zip(tmp_path / "avatar.zip"), progress=False)
    speaker.audio_model = builtin_audio_model(speaker)
    path = export_bundle(speaker, tmp_path / "avatar.gtb", progress=False, mnn=True).path
    audio = unseen_speech()[0][:24000]
    rows = [_live(open_driver(path, backend=backend), [audio], True)[0] for backend in ("onnxruntime", "mnn")]
    assert rows[0].shape == rows[1].shape and np.abs(rows[0] - rows[1]).max() < 1e-4


def _paced_on_a_clock(driver, utterances: list[np.ndarray], monkeypatch, *, slower_from_s: float,
                      slower_by_s: float, gap_s: float = 0.3, grid_s: float = 0.02) -> tuple[np.ndarray, LiveSession]:
    """A paced session on a clock grid, stepped as the live server's pool steps it, on a simulated clock (1 ms
    ticks): each utterance pushed in 20 ms chunks at real time and flushed, `gap_s` of nothing between them (idle
    frames), the chunks from `slower_from_s` to the end of that utterance `slower_by_s` later (a voice whose chunks
    start landing later mid-utterance); then end(). The spoken frames' drives, and the session."""
    from gaussiantalker.runtime import live as live_module

    clock = [0.0]
    monkeypatch.setattr(live_module, "time", types.SimpleNamespace(monotonic=lambda: clock[0]))
    live = LiveSession(driver, output=None, paced=True, streaming=True, clock_grid_s=grid_s)
    chunks, start = [], 0.0
    for speech in utterances:
        end = start + speech.shape[0] / 16000
        for k in range(0, speech.shape[0], 320):
            at = start + k / 16000
            chunks.append((at + (slower_by_s if slower_from_s <= at < end else 0.0), speech[k:k + 320]))
        chunks.append((chunks[-1][0], "flush"))  # a complete utterance: its last frames need no lookahead
        start = end + gap_s
    frames, pushed = [], 0
    for tick in range(100_000):
        clock[0] = tick / 1000.0
        while pushed < len(chunks) and chunks[pushed][0] <= clock[0]:
            if isinstance(chunks[pushed][1], str):
                live.flush()
            else:
                live.push(chunks[pushed][1], 16000)
            pushed += 1
            if pushed == len(chunks):
                live.end()
        job = live.stream_job()
        if job is not None:
            run_stream_jobs([job], driver.run_stream, driver.stream_rows)
        if (frame := live.step()) is not None:
            frames.append(frame)
        if live.finished:
            break
    return _drive_rows([frame for frame in frames if frame.speaking]), live


def test_a_voice_landing_later_moves_the_clock_instead_of_making_late_frames(ga_voice_bundle, monkeypatch):
    """Mid-utterance the chunks start arriving 45 ms later, just after the session's ticks: a session on a clock
    grid moves its clock a grid step later (MAX_DEFERRALS at most) and makes no late frame, the utterance's drives
    those of the voice that kept time; the idle frames before the next utterance take the steps back, so a long
    session does not drift. Without the deferrals (MAX_DEFERRALS 0) every frame after the change is late."""
    from gaussiantalker.runtime import live as live_module

    driver = open_driver(ga_voice_bundle)
    speech = unseen_speech()[0]
    utterances = [speech[:32000], speech[32000:48000]]
    spoken = 32000 // 640  # the first utterance's frames
    on_time, _ = _paced_on_a_clock(driver, utterances, monkeypatch, slower_from_s=1.0, slower_by_s=0.0)
    later, live = _paced_on_a_clock(driver, utterances, monkeypatch, slower_from_s=1.0, slower_by_s=0.045)
    assert live.stats.late_frames == 0 and 1 <= live.stats.deferrals <= live_module.MAX_DEFERRALS
    assert live._deferrals == 0  # taken back while idle
    assert np.abs(later[:spoken] - on_time[:spoken]).max() < EXACT * 4
    monkeypatch.setattr(live_module, "MAX_DEFERRALS", 0)
    _, late = _paced_on_a_clock(driver, utterances, monkeypatch, slower_from_s=1.0, slower_by_s=0.045)
    assert late.stats.deferrals == 0 and late.stats.late_frames >= 10
