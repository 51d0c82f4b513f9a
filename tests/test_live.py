"""Live sessions (runtime/live.py, docs/live.md): the audio clock, agreement with offline frames, idle motion,
barge-in and bad input. Free-running mode throughout (deterministic); paced mode where the wall clock is the point,
with bounds far from any timing. Most sessions render no image (output=None): the drives are what is checked, and
the renderer is the offline one's (tests/test_runtime_api.py)."""

from __future__ import annotations

import itertools
import json
import threading
import time

import numpy as np
import pytest
from typer.testing import CliRunner

from gaussiantalker.runtime import AudioError, IdleMotion, LiveError, TalkingHead
from gaussiantalker.sdk.audio import load_audio, resample
from tools.bench.app import app
from tools.bench.live_sessions import CHUNK_MS

SPEECH_SECONDS = 4.0


@pytest.fixture(scope="module")
def head(small_export):
    with TalkingHead(small_export.path, resolution=(32, 32), composite=False) as talking_head:
        yield talking_head


@pytest.fixture(scope="module")
def speech(head) -> np.ndarray:
    """The first seconds of the sample speech at the speaker's rate."""
    return load_audio("samples/demo_speech.wav", head.sample_rate)[: int(SPEECH_SECONDS * head.sample_rate)]


def push_in_chunks(live, audio: np.ndarray, rate: int, seed: int, largest: int = 1500) -> None:
    """Push `audio` in random chunk sizes (1..largest samples), as a network or TTS engine would."""
    rng = np.random.default_rng(seed)
    start = 0
    while start < audio.shape[0]:
        size = int(rng.integers(1, largest + 1))
        live.push(audio[start:start + size], rate)
        start += size


def jaw(frames) -> np.ndarray:
    return np.array([frame.drive.flame_pose[6] for frame in frames])


def test_frames_follow_the_audio_clock(head, speech):
    """Every pushed sample is shown once, in order, in the frame its time falls in; pts = index / fps."""
    pcm = np.round(resample(speech, head.sample_rate, 24000) * 32000).astype(np.int16)
    with head.live(paced=False, output=None, audio_rate=24000) as live:
        push_in_chunks(live, pcm, 24000, seed=1)
        live.end()
        frames = list(live.frames())
    assert len(frames) == int(np.ceil(pcm.shape[0] / 24000 * head.fps))
    assert [f.index for f in frames] == list(range(len(frames)))
    assert all(f.pts == f.index / head.fps and f.speaking and f.sample_rate == 24000 for f in frames)
    shown = np.concatenate([f.audio for f in frames])
    # Same rate in and out: the samples pass unchanged (int16 / 32768), the last frame zero-padded.
    assert shown.shape[0] == round(len(frames) * 24000 / head.fps)
    np.testing.assert_array_equal(shown[: pcm.shape[0]], pcm.astype(np.float32) / 32768)
    assert not shown[pcm.shape[0]:].any()


def test_chunking_does_not_change_the_frames(head, speech):
    """Pushed all before reading, the same audio in other chunk sizes gives identical drives."""
    drives = []
    for seed in (2, 3):
        with head.live(paced=False, output=None) as live:
            push_in_chunks(live, speech, head.sample_rate, seed=seed, largest=4000)
            live.end()
            drives.append(np.stack([f.drive.flame_pose for f in live.frames()]))
    np.testing.assert_array_equal(drives[0], drives[1])


@pytest.mark.parametrize("lookahead_ms", [0, 160])
def test_live_agrees_with_offline_frames(head, speech, lookahead_ms):
    """The jaw of frames read while 20 ms chunks arrive follows the offline jaw (goal at 160 ms: r >= 0.95, the
    figure docs/bench/live/live.md reports; 0 ms must still follow the speech, r >= 0.8)."""
    expression, jaw_pose = head.driver.translate(speech)
    frames = []
    with head.live(lookahead_ms=lookahead_ms, paced=False, output=None) as live:
        for start in range(0, speech.shape[0], 320):
            live.push(speech[start:start + 320], head.sample_rate)
            frames += live.poll()
        live.end()
        frames += list(live.frames())
    assert len(frames) == jaw_pose.shape[0]
    corr = np.corrcoef(jaw(frames), jaw_pose[:, 0])[0, 1]
    assert corr >= (0.95 if lookahead_ms >= 160 else 0.8), corr


def test_a_lam_bundle_speaks_live_through_the_builtin_voice(lam_voice_bundle):
    """An imported LAM avatar (ARKit, 30 fps) with the built-in voice driver: 20 ms chunks at 160 ms lookahead give
    one frame per 1/30 s whose jawOpen follows the offline one (r >= 0.95: docs/voice.md measures 0.98 on eight
    held-out clips; the runtime resamples each window's 25 fps rows to 30 fps from another phase live than offline,
    so the two are close, not equal); the mouth is shut before the speech and opens with it."""
    from gaussiantalker.sdk.rig import ARKIT_BLENDSHAPES

    jaw_open = ARKIT_BLENDSHAPES.index("jawOpen")
    speech = load_audio("tests/data/voice_heldout.wav", 16000)
    audio = np.concatenate([np.zeros(8000, np.float32), speech])  # 0.5 s of silence first
    with TalkingHead(lam_voice_bundle, resolution=(32, 32)) as lam:
        offline = lam.driver.translate(audio)[:, jaw_open]
        frames = []
        with lam.live(lookahead_ms=160, paced=False, output=None) as live:
            for start in range(0, audio.shape[0], 320):
                live.push(audio[start:start + 320], 16000)
                frames += live.poll()
            live.end()
            frames += list(live.frames())
    assert lam.fps == 30 and len(frames) == offline.shape[0] == int(np.ceil(audio.shape[0] / (16000 / 30)))
    live_jaw = np.array([frame.drive.blendshapes[jaw_open] for frame in frames])
    assert np.corrcoef(live_jaw, offline)[0, 1] >= 0.95
    assert live_jaw[:10].max() < 0.05 and live_jaw.max() > 0.2


@pytest.mark.parametrize("lookahead_ms", [80, 160])
def test_a_30_fps_avatar_waits_for_its_lookahead_exactly(lam_voice_bundle, lookahead_ms):
    """A 30 fps avatar's frames end between the 16 kHz samples' 20 ms chunks: free-running, chunks of 10 samples,
    frame n comes out at the first chunk that brings the audio to its end plus lookahead_ms (80 ms: 1,280 samples,
    not the 1,600 of three whole frames), and the frames the last lookahead reaches into come with end()."""
    speech = load_audio("tests/data/voice_heldout.wav", 16000)[:16000]
    chunk, lookahead = 10, lookahead_ms * 16
    ready_at: dict[int, int] = {}
    with TalkingHead(lam_voice_bundle, resolution=(32, 32)) as lam, \
            lam.live(lookahead_ms=lookahead_ms, paced=False, output=None) as live:
        pushed = 0
        for start in range(0, speech.shape[0], chunk):
            live.push(speech[start:start + chunk], 16000)
            pushed += speech[start:start + chunk].shape[0]
            ready_at.update((frame.index, pushed) for frame in live.poll())
        live.end()
        rest = [frame.index for frame in live.frames()]
    ends = [round((index + 1) * 16000 / 30) for index in range(len(ready_at))]
    assert list(ready_at) == list(range(len(ready_at))) and len(ready_at) >= 20
    assert list(ready_at.values()) == [-(-(end + lookahead) // chunk) * chunk for end in ends]
    assert rest[0] == len(ready_at) and rest[-1] == 29  # one second: 30 frames
    assert round((rest[0] + 1) * 16000 / 30) + lookahead > speech.shape[0]  # only frames whose lookahead never came


def test_min_batch_frames_translates_that_many_frames_a_call(head, speech):
    """min_batch_frames=4, 20 ms chunks polled as they arrive: the translator runs once per 4 frames, each batch
    comes out when its last frame's audio and lookahead are in (frame n of batch b, b = n // 4, at the audio of
    frames 0..4b + 3 plus the lookahead), and the jaw still follows the offline one (r >= 0.95, as at 1 frame)."""
    per_frame = head.driver.config.samples_per_frame
    expression, jaw_pose = head.driver.translate(speech)
    batches, frames = [], []
    with head.live(lookahead_ms=160, paced=False, output=None, min_batch_frames=4) as live:
        pushed = 0
        for start in range(0, speech.shape[0], per_frame // 2):
            live.push(speech[start:start + per_frame // 2], head.sample_rate)
            pushed += speech[start:start + per_frame // 2].shape[0]
            got = live.poll()
            if got:
                batches.append((len(got), got[0].index, pushed))
            frames += got
        calls = live.stats.translator_calls
        live.end()
        frames += list(live.frames())
    assert {size for size, _, _ in batches} == {4}
    assert calls == len(batches)
    assert all(pushed == (first + 4 + 4) * per_frame for _, first, pushed in batches)  # 4 frames + 160 ms
    assert [f.index for f in frames] == list(range(jaw_pose.shape[0]))
    corr = np.corrcoef(jaw(frames), jaw_pose[:, 0])[0, 1]
    assert corr >= 0.95, corr
    for bad in (0, 9, 2.0):
        with pytest.raises(LiveError, match="min_batch_frames must be a whole number in 1..8"):
            head.live(output=None, min_batch_frames=bad)


@pytest.mark.parametrize("lookahead_ms", [0, 80, 100, 160])
def test_free_running_latency_is_a_frame_and_its_lookahead(head, speech, lookahead_ms):
    """Free-running, 20 ms chunks polled as each arrives: frame n comes out exactly when the audio of frames 0..n
    and of the lookahead after it is in (lookahead_ms exactly, 100 ms being two and a half frames), not a chunk
    earlier or later; the frames the last lookahead reaches into come with end()."""
    per_frame = head.driver.config.samples_per_frame
    lookahead_samples = lookahead_ms * head.sample_rate // 1000
    lookahead_frames = -(-lookahead_samples // per_frame)
    chunk = per_frame // 2
    ready_at: dict[int, int] = {}  # frame index -> samples pushed when poll() first gave it
    with head.live(lookahead_ms=lookahead_ms, paced=False, output=None) as live:
        pushed = 0
        for start in range(0, speech.shape[0], chunk):
            live.push(speech[start:start + chunk], head.sample_rate)
            pushed += speech[start:start + chunk].shape[0]
            ready_at.update((frame.index, pushed) for frame in live.poll())
        live.end()
        rest = [frame.index for frame in live.frames()]
    total, partial = divmod(speech.shape[0], per_frame)
    assert partial == 0  # whole frames: every frame but the lookahead's is ready before end()
    assert list(ready_at) == list(range(total - lookahead_frames))
    assert list(ready_at.values()) == [(index + 1) * per_frame + lookahead_samples for index in ready_at]
    assert rest == list(range(total - lookahead_frames, total))


def test_frames_render_what_the_drive_says(head, speech):
    """A live frame's image is the offline render of its drive (same renderer, same drive: identical pixels)."""
    with head.live(paced=False) as live:
        live.push(speech[: head.sample_rate], head.sample_rate)
        live.end()
        frames = list(live.frames())
    for frame in frames[::10]:
        assert frame.image.shape == (32, 32, 3) and frame.image.dtype == np.uint8
        np.testing.assert_array_equal(frame.image, head.render(frame.drive))


def test_idle_face_blinks_and_keeps_the_pose_track(head):
    """No audio: idle frames keep coming (free-running), neutral mouth, the speaker's blink on its rhythm, the
    head on the bundle's pose track."""
    idle = IdleMotion(blink_interval_s=(1.0, 1.5))
    with head.live(paced=False, output=None, idle=idle) as live:
        frames = list(itertools.islice(live.frames(), 100))
    assert not any(f.speaking for f in frames) and not any(f.audio.any() for f in frames)
    n_expr = head.driver.config.n_expr
    names = head.driver.config.expression_names
    blink = [names.index("blink_left"), names.index("blink_right")]
    closure = np.array([f.drive.expression[blink[0]] for f in frames])
    assert 2 <= np.sum(np.diff((closure > 0.5).astype(int)) == 1) <= 4, closure  # 100 frames = 4 s: 2-4 blinks
    others = np.delete(np.stack([f.drive.expression for f in frames]), blink, axis=1)
    assert not others.any() and not np.stack([f.drive.flame_pose[6:9] for f in frames]).any()
    assert n_expr == len(names)
    for frame in frames[::7]:
        np.testing.assert_array_equal(frame.drive.flame_pose[:3], head.driver.head_pose(frame.index).rotation)


def test_interrupt_eases_to_idle_and_the_next_push_starts_clean(head, speech):
    """Barge-in: queued audio dropped; within 200 ms of frames the face is idle; the next utterance is shown whole
    from the next frame, with a context that does not remember the interrupted one."""
    idle = IdleMotion(blink_ms=0)  # no blinks: idle means exactly the neutral face
    with head.live(paced=False, output=None, idle=idle) as live:
        live.push(speech, head.sample_rate)
        spoken = list(itertools.islice(live.frames(), 30))
        live.interrupt()
        assert live.queued_s == 0.0 and live.stats.dropped_s > 0
        after = list(itertools.islice(live.frames(), 10))
        assert not any(f.speaking for f in after)
        reach = int(np.ceil(0.2 * head.fps))  # frames within 200 ms
        assert not np.stack([f.drive.expression for f in after[reach:]]).any()
        assert abs(after[0].drive.flame_pose[6]) <= abs(spoken[-1].drive.flame_pose[6]) + 1e-7  # eases, no jump
        second = speech[: head.sample_rate]
        live.push(second, head.sample_rate)
        live.end()
        rest = list(live.frames())
    assert [f.speaking for f in rest] == [True] * (head.sample_rate // head.driver.config.samples_per_frame)
    np.testing.assert_array_equal(np.concatenate([f.audio for f in rest]), second)
    with head.live(paced=False, output=None) as fresh:  # the same utterance in a new session: the same face
        fresh.push(second, head.sample_rate)
        fresh.end()
        alone = list(fresh.frames())
    for part in ("expression", "flame_pose"):  # (flame_pose[3:]: the head's own rotation follows the frame index)
        got, want = (np.stack([getattr(f.drive, part) for f in frames]) for frames in (rest, alone))
        np.testing.assert_allclose(got[:, 3:] if part == "flame_pose" else got,
                                   want[:, 3:] if part == "flame_pose" else want, atol=1e-6)


def test_an_hour_of_chunks_keeps_audio_and_frames_in_step(head, speech):
    """Speech and silence at 44.1 kHz in random chunks (a minute here; the benchmark runs an hour): frames =
    the audio's duration, and the jaw peaks with the loudness at the same lag at the start and at the end."""
    rng = np.random.default_rng(4)
    source = resample(speech, head.sample_rate, 44100)
    parts = []
    while sum(p.shape[0] for p in parts) < 60 * 44100:
        parts += [source, np.zeros(int(rng.uniform(0.2, 2.0) * 44100), np.float32)]
    audio = np.concatenate(parts)
    with head.live(paced=False, output=None, audio_rate=44100) as live:
        push_in_chunks(live, audio, 44100, seed=5, largest=2205)
        live.end()
        frames = list(live.frames())
    assert len(frames) == int(np.ceil(audio.shape[0] / 44100 * head.fps))
    np.testing.assert_array_equal(np.concatenate([f.audio for f in frames])[: audio.shape[0]], audio)
    level = np.array([np.sqrt(np.mean(f.audio ** 2)) for f in frames])
    lags = []
    for part in (slice(0, 375), slice(len(frames) - 375, len(frames))):  # the first and last 15 s
        a, b = jaw(frames[part]), level[part]
        a, b = a - a.mean(), b - b.mean()
        lags.append(int(np.argmax([np.dot(np.roll(a, k), b) for k in range(-5, 6)])) - 5)
    assert lags[0] == lags[1], lags


def test_paced_mode_idles_on_the_wall_clock_and_speaks_when_audio_comes(head, speech):
    """Paced: idle frames come while nothing is queued; pushed speech follows within a few frames; close() from
    another thread ends frames()."""
    with head.live(lookahead_ms=80, output=None) as live:
        seen = []
        for frame in live.frames():
            seen.append(frame)
            if len(seen) == 3:
                live.push(speech[: head.sample_rate // 2], head.sample_rate)
                live.flush()
            if len(seen) == 25:
                threading.Timer(0.0, live.close).start()
    assert [f.index for f in seen] == list(range(len(seen)))
    assert not seen[0].speaking and sum(f.speaking for f in seen) == 13  # 0.5 s of speech at 25 fps: 12.5 frames
    first = next(f.index for f in seen if f.speaking)
    assert first <= 3 + 4, first  # at 80 ms lookahead: ready 3 frames after the push, plus a frame of slack


def test_paced_frames_never_run_ahead_of_the_clock(head, speech):
    """Audio queued far ahead (a text-to-speech engine faster than real time) still comes out at the frame rate:
    frame n is not given before start + n / fps (a lower bound only, so a slow machine cannot fail it)."""
    with head.live(output=None) as live:
        live.push(speech[: head.sample_rate], head.sample_rate)
        live.end()
        started = time.monotonic()
        for frame in live.frames():
            assert time.monotonic() - started >= frame.index / head.fps - 0.005, frame.index
    assert frame.index == head.fps - 1


def test_bad_input_gets_clear_errors(head, speech):
    with head.live(paced=False, output=None) as live:
        with pytest.raises(AudioError, match="non-finite"):
            live.push(np.array([0.0, np.nan], np.float32), 16000)
        with pytest.raises(AudioError, match="sample rate"):
            live.push(speech[:100], 0)
        live.push(speech[:1000], 16000)
        live.push(np.clip(speech[:1000] * 50, -1, 1), 48000)  # a changed rate and clipped samples: accepted
        live.push(np.zeros(0, np.int16), 8000)  # an empty chunk: nothing
        live.flush()  # free-running frames wait for lookahead until the utterance is complete
        reader = live.frames()
        next(reader)
        with pytest.raises(LiveError, match="already being read"):
            next(live.frames())
        live.end()
        with pytest.raises(LiveError, match="ended"):
            live.push(speech[:100], 16000)
        assert sum(1 for _ in reader) >= 1
    with pytest.raises(LiveError, match="closed"):
        live.push(speech[:100], 16000)
    with pytest.raises(LiveError, match="lookahead_ms"):
        head.live(lookahead_ms=float("nan"))


def test_a_consumer_that_stops_reading_cannot_grow_memory(head, speech):
    """Pushes beyond max_queued_s are refused with a LiveError naming the cause; what is queued stays bounded."""
    with head.live(paced=False, output=None, max_queued_s=1.0) as live:
        live.push(speech[: head.sample_rate // 2], head.sample_rate)
        with pytest.raises(LiveError, match="not being read"):
            for _ in range(10):
                live.push(speech[: head.sample_rate // 4], head.sample_rate)
        assert live.queued_s <= 1.0


def test_gt_bench_live_writes_every_measure(small_export, head, tmp_path):
    """`gt-bench live` end to end on the small speaker at 32², every measure kept short (docs/bench/live/live.md is
    the full run)."""
    out = tmp_path / "live"
    result = CliRunner().invoke(app, ["live", str(small_export.path), "--size", "32", "--lookaheads", "0,80",
                                      "--utterances", "1", "--barge-trials", "1", "--drift-minutes", "0.1",
                                      "--session-sizes", "32", "--most-sessions", "1", "--out", str(out)])
    assert result.exit_code == 0, result.output
    report = json.loads((out / "live.json").read_text())
    assert [row["lookahead_ms"] for row in report["latency"]] == [0.0, 80.0]
    # A real-time producer has pushed the first frame's audio and lookahead only one chunk before their end: no
    # frame can be ready sooner (a bound on the slow side would measure the machine, not the session).
    for row in report["latency"]:
        lookahead_frames = np.ceil(row["lookahead_ms"] * head.fps / 1000)
        assert row["utterances"] == 1 and row["latency_ms"] == [row["p50_ms"]], row
        assert row["p50_ms"] >= (1 + lookahead_frames) * 1000 / head.fps - CHUNK_MS, row
    assert all(row["jaw_r"] > 0.8 for row in report["agreement"])
    assert report["barge_in"]["timeline_max_ms"] <= 200.0  # the ease (120 ms) plus a frame
    drift = report["drift"]
    assert drift["frames_with_other_audio"] == 0 and abs(drift["clock_gap_frames"]) < 1.0
    (row,) = report["sessions"][0]["rows"]
    assert row["fps_total"] > 0
    # Free-running, a session's frames come a render apart: the p95 interval is not far below the mean (1 / fps).
    assert 1000.0 / row["fps_each"] * 0.5 <= row["p95_interval_ms"] < 60_000, row
    assert "| 80 ms |" in (out / "live.md").read_text()


def test_gt_bench_live_batching_writes_its_table(small_export, tmp_path):
    """`gt-bench live-batching` on 2 s of speech: one row per K, K = 4 making a quarter of K = 1's translator calls
    (to within the utterance's last batch), the drives still following the offline ones."""
    out = tmp_path / "batching"
    result = CliRunner().invoke(app, ["live-batching", str(small_export.path), "--seconds", "2", "--rounds", "1",
                                      "--batch-frames", "1,4", "--out", str(out)])
    assert result.exit_code == 0, result.output
    rows = {row["batch_frames"]: row for row in json.loads((out / "live-batching.json").read_text())["rows"]}
    assert rows[1]["frames"] == rows[4]["frames"] == 50
    assert rows[1]["translator_calls"] >= 45 and rows[4]["translator_calls"] <= rows[1]["translator_calls"] / 4 + 2
    assert all(row["jaw_r"] >= 0.9 and row["cpu_ms_per_speech_s"] > 0 for row in rows.values())
    assert "`--batch-frames 4` | 160 ms |" in (out / "live-batching.md").read_text()


def test_gt_bench_live_batching_compares_the_streaming_translator(lam_voice_bundle, tmp_path):
    """`gt-bench live-batching --stream` on a bundle whose voice streams, at two lookaheads: the stream makes a
    call per frame (a frame's work each, cheaper than a window a frame), its mouth follows the offline one."""
    out = tmp_path / "stream"
    result = CliRunner().invoke(app, ["live-batching", str(lam_voice_bundle), "--seconds", "2", "--rounds", "1",
                                      "--batch-frames", "1", "--stream", "--lookahead-ms", "80,160", "--out",
                                      str(out)])
    assert result.exit_code == 0, result.output
    rows = {(row["mode"], row["lookahead_ms"]): row for row in json.loads((out / "live-batching.json").read_text())
            ["rows"]}
    assert set(rows) == {(mode, ms) for mode in ("K=1", "stream") for ms in (80.0, 160.0)}
    for ms in (80.0, 160.0):
        stream, windowed = rows[("stream", ms)], rows[("K=1", ms)]
        assert stream["frames"] == windowed["frames"] == 60 and stream["translator_calls"] >= 55
        assert stream["mouth_r"] >= 0.9 and stream["cpu_ms_per_speech_s"] > 0
    assert "| streaming | 80 ms |" in (out / "live-batching.md").read_text()


def test_step_paces_frames_on_the_callers_schedule(head, speech):
    """step(): None until a frame is due (frame n never before the first step + n / fps, a lower bound only), the
    frames of frames() in order otherwise (idle, then the pushed speech), `finished` once end() has flushed; one
    session is read with frames() or step(), not both, and step() needs a paced session."""
    with head.live(lookahead_ms=80, output=None) as live:
        assert live.step() is not None  # frame 0 is due at the first step
        started = live.due - 1 / head.fps
        live.push(speech[: head.sample_rate // 2], head.sample_rate)
        live.end()
        frames, empty = [], 0
        while not live.finished:
            frame = live.step()
            if frame is None:
                empty += 1
                time.sleep(max(0.0, live.due - time.monotonic()))
                continue
            assert time.monotonic() - started >= frame.index / head.fps - 0.005, frame.index
            frames.append(frame)
    assert [f.index for f in frames] == list(range(1, len(frames) + 1)) and empty > 0
    assert sum(f.speaking for f in frames) == 13  # 0.5 s of speech at 25 fps
    with head.live(output=None) as live:
        reader = live.frames()
        next(reader)  # an idle frame, at once
        with pytest.raises(LiveError, match="frames\\(\\) or step\\(\\)"):
            live.step()
        reader.close()
    with head.live(paced=False, output=None) as live, pytest.raises(LiveError, match="paced=True"):
        live.step()
