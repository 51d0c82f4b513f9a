"""The pool's steady frames made together (runtime/live_steady.py) against each session's own `stream_job` and
`step`: the same frame packets, bit for bit, over sessions that start, speak, get interrupted, run out of voice and
idle, with voices whose chunks do and do not line up with the frames (docs/live.md, "Steady frames made
together")."""

from __future__ import annotations

import time
import types
from pathlib import Path

import numpy as np
import pytest

import gaussiantalker.runtime.live as live_module
from gaussiantalker.runtime import LiveSession
from gaussiantalker.runtime.live_rows import make_rows
from gaussiantalker.runtime.live_steady import SteadyFrames
from gaussiantalker.runtime.stages import open_driver
from gaussiantalker.runtime.translate_stream import run_stream_jobs
from gaussiantalker.sdk.audio import load_audio
from gaussiantalker.serve.drive_sessions import clock_grid_s
from gaussiantalker.serve.voices import PacedVoice
from gaussiantalker.serve.wire import encode_drive, encode_frame_packet, frame_packets

SPEECH = Path(__file__).resolve().parents[1] / "samples" / "demo_speech.wav"


def _pool_packets(bundle, together: bool, monkeypatch, seconds: float = 4.0,
                  pose_track: bool = True, short: bool = False) -> tuple[list[list[bytes]], list[int]]:
    """Ten paced sessions on a fake clock, each frame made by its session's `stream_job` and `step`, or (`together`)
    as the server's pool makes them: the steady frames planned together (live_steady.py), every frame made as arrays
    (live_rows.py) and packed as one (`frame_packets`). Every session's frame packets, and how many frames the steady
    path made of each. `short`: every other session at 80 ms of lookahead on the short stream."""
    clock = [1000.0]
    monkeypatch.setattr(live_module, "time", types.SimpleNamespace(monotonic=lambda: clock[0],
                                                                   perf_counter=time.perf_counter, time=time.time))
    driver = open_driver(bundle, threads=1)
    driver.open_stream()
    if not pose_track:  # the sessions' idle sway instead
        driver.pose_track = None
    speech = np.asarray(load_audio(SPEECH, driver.sample_rate)[: int(2.5 * driver.sample_rate)], np.float32)
    grid = clock_grid_s(driver.fps)
    lives = [LiveSession(driver, lookahead_ms=80 if short and k % 2 else 160, audio_rate=driver.sample_rate,
                         output=None, clock_grid_s=grid, streaming=True,
                         stream_delay_ms=80 if short and k % 2 else None) for k in range(10)]
    # chunks of 20 ms (two a frame at 25 fps), 30 ms (out of step with the frames) and 50 ms (a frame's lookahead
    # arriving in bursts: late frames and deferrals)
    chunks = [0.02, 0.02, 0.03, 0.02, 0.05, 0.02, 0.02, 0.03, 0.02, 0.02]
    voices = [PacedVoice(live, speech, driver.sample_rate, chunk, clock[0] + 0.013 * k)
              for k, (live, chunk) in enumerate(zip(lives, chunks, strict=True))]
    # barge-ins mid-utterance (then a second voice), and one right at a voice's start
    interrupts = {(2, 40), (5, 75), (7, 2)}
    packets: list[list[bytes]] = [[] for _ in lives]
    made_steady, tick, steady = [0] * len(lives), 0, SteadyFrames()
    while clock[0] < 1000.0 + seconds:
        due = [k for k, live in enumerate(lives) if live.due <= clock[0]]
        for k in due:
            voices[k].feed(clock[0])
            if (k, tick) in interrupts:
                voices[k].cancel()
                lives[k].interrupt()
                voices[k] = PacedVoice(lives[k], speech[: driver.sample_rate], driver.sample_rate, 0.02, clock[0])
        sessions = [lives[k] for k in due]
        planned = steady.plan(sessions, clock[0]) if together else [None] * len(sessions)
        jobs = [job for job in (mine.job if mine is not None else live.stream_job()
                                for mine, live in zip(planned, sessions, strict=True)) if job is not None]
        if jobs:
            run_stream_jobs(jobs, driver.run_stream, driver.stream_rows)
        if not together:
            for p, live in enumerate(sessions):
                frame = live.step()
                if frame is not None:
                    packets[due[p]].append(encode_frame_packet(encode_drive(
                        frame.index, frame.pts, frame.drive, frame.speaking, live.stats.interrupts), frame.audio))
        else:  # as serve/drive_sessions.py makes them: plans, then the frames as arrays, then the packets
            made = []
            for p, live in enumerate(sessions):
                taken = steady.take(planned[p]) if planned[p] is not None else None
                made_steady[due[p]] += taken is not None
                taken = taken or live.next_plan()
                if taken is not None:
                    made.append((p, live, *taken))
            if made:
                rows = make_rows([item[1] for item in made], [item[2] for item in made])
                values = rows.values()
                assert values is not None and not rows.errors
                for group in _by_length(rows.audio):
                    epochs = np.array([made[k][1].stats.interrupts for k in group])
                    cut = frame_packets(driver.rig, rows.indices[group], rows.pts[group], values[group],
                                        rows.speaking[group], epochs, np.stack([rows.audio[k] for k in group]))
                    for k, packet in zip(group, cut, strict=True):
                        packets[due[made[k][0]]].append(packet.tobytes())
                for item in made:
                    item[1].keep_pace(item[3])
        clock[0] += grid
        tick += 1
    return packets, made_steady


def _by_length(audio: list[np.ndarray]) -> list[list[int]]:
    groups: dict[int, list[int]] = {}
    for k, samples in enumerate(audio):
        groups.setdefault(samples.shape[0], []).append(k)
    return list(groups.values())


def test_steady_frames_made_together_are_each_sessions_own(small_export, monkeypatch):
    """The same packets either way (every byte of every frame of every session), most speaking frames made by the
    steady path, and the refreshing, late and interrupted ones by the sessions' own."""
    alone, none = _pool_packets(small_export.path, False, monkeypatch)
    together, steady = _pool_packets(small_export.path, True, monkeypatch)
    assert sum(none) == 0
    steady = sum(steady)
    frames = sum(len(p) for p in alone)
    assert frames > 900 and [len(p) for p in together] == [len(p) for p in alone]
    for k, (mine, theirs) in enumerate(zip(together, alone, strict=True)):
        first = next((i for i, (a, b) in enumerate(zip(mine, theirs, strict=True)) if a != b), None)
        assert first is None, f"session {k}: frame {first} differs"
    # 2.5 s of speech a session (a second more after a barge-in) of 4 s: more than a third of the frames are steady
    assert 0.35 * frames < steady < frames, (steady, frames)


def test_frames_made_together_sway_as_each_sessions_own(small_export, monkeypatch):
    """A bundle without a pose track: each session's idle sway, made into the rows a session at a time."""
    alone, _ = _pool_packets(small_export.path, False, monkeypatch, seconds=1.5, pose_track=False)
    together, steady = _pool_packets(small_export.path, True, monkeypatch, seconds=1.5, pose_track=False)
    assert sum(steady) > 0 and together == alone and sum(len(p) for p in alone) > 300


def test_two_streams_in_one_pool_make_each_sessions_own_frames(short_stream_export, monkeypatch):
    """Sessions on the main stream at 160 ms and on the short stream at 80 ms (docs/live.md, "A stream for a short
    lookahead") in one pool: their calls are the streams' own, the packets each session's own bit for bit, and the
    80 ms sessions' frames steady too (on the main stream their rows would lag past the lookahead: never steady)."""
    alone, _ = _pool_packets(short_stream_export, False, monkeypatch, short=True)
    together, steady = _pool_packets(short_stream_export, True, monkeypatch, short=True)
    assert together == alone and sum(len(p) for p in alone) > 900
    # every session made steady frames (session 7, barged in on at its start, speaks 1 s of its 4)
    assert min(steady[1::2]) > 15 and sum(steady[1::2]) > 0.35 * sum(len(p) for p in alone[1::2]), steady


def test_a_rig_off_the_streams_frames_makes_no_steady_frames(lam_voice_bundle, monkeypatch):
    """A 30 fps avatar on the 25 fps voice interpolates between rows: its frames stay the sessions' own."""
    alone, _ = _pool_packets(lam_voice_bundle, False, monkeypatch, seconds=1.5)
    together, steady = _pool_packets(lam_voice_bundle, True, monkeypatch, seconds=1.5)
    assert sum(steady) == 0 and together == alone and sum(len(p) for p in alone) > 300


def test_a_lookahead_of_part_of_a_frame_makes_no_steady_frames(short_stream_export):
    """The steady table takes a frame's lookahead as whole frames of the stream's: 100 ms (two and a half 25 fps
    frames, waited for exactly) is left to the sessions' own path; 80 ms on the short stream is taken."""
    driver = open_driver(short_stream_export, threads=1)
    keys = {lookahead: LiveSession(driver, lookahead_ms=lookahead, output=None, streaming=True,
                                   stream_delay_ms=80).steady_key() for lookahead in (80, 100, 120)}
    assert keys[100] is None and keys[80] is not None and keys[120] is not None and keys[80] != keys[120]


@pytest.mark.parametrize("state", ["closed", "interrupted"])
def test_a_steady_frame_closed_or_interrupted_after_planning_is_left_to_step(small_export, monkeypatch, state):
    """A session closed or barged in on between its plan and its frame: make() leaves it to step(), which
    ends the session or makes the idle frame, as it does for a call planned by stream_job."""
    clock = [1000.0]
    monkeypatch.setattr(live_module, "time", types.SimpleNamespace(monotonic=lambda: clock[0],
                                                                   perf_counter=time.perf_counter, time=time.time))
    driver = open_driver(small_export.path, threads=1)
    live = LiveSession(driver, lookahead_ms=160, audio_rate=driver.sample_rate, output=None,
                       clock_grid_s=clock_grid_s(driver.fps), streaming=True)
    speech = np.asarray(load_audio(SPEECH, driver.sample_rate)[: 2 * driver.sample_rate], np.float32)
    voice = PacedVoice(live, speech, driver.sample_rate, 0.02, clock[0])
    planned, steady = None, SteadyFrames()
    while planned is None:  # speak until a frame is steady
        assert clock[0] < 1002.0, "no steady frame in 2 s of speech"
        voice.feed(clock[0])
        if live.due <= clock[0]:
            planned = steady.plan([live], clock[0])[0]
            job = planned.job if planned is not None else live.stream_job()
            if job is not None:
                run_stream_jobs([job], driver.run_stream, driver.stream_rows)
            if planned is None:
                live.step()
        clock[0] += clock_grid_s(driver.fps)
    clock[0] -= clock_grid_s(driver.fps)
    if state == "closed":
        live.close()
    else:
        live.interrupt()
    assert steady.make(planned) is None and len(steady) == 0
    frame = live.step()
    if state == "closed":
        assert frame is None and live.finished
    else:
        assert frame is not None and not frame.speaking
