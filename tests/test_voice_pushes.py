"""The server's own voice: serve/voices.py `push_real_time` pushes every chunk in order at its time on the loop's
clock, then a flush; `PacedVoice`, which a pool thread feeds, the chunks whose time has come at each feed; a
cancelled voice (a barge-in) pushes nothing more; a closed session stops it quietly. And `gt-bench voice-pushes`
(tools/bench/voice_pushes.py), which measures `push_real_time`'s CPU beside an older checkout."""

from __future__ import annotations

import asyncio
from pathlib import Path

import numpy as np
import pytest

from gaussiantalker.runtime import LiveError
from gaussiantalker.serve.voices import PacedVoice, push_real_time
from tools.bench.voice_pushes import pushes_run, run_voice_pushes, voice_pushes_table

ROOT = Path(__file__).resolve().parents[1]


class RecordingLive:
    """A live session's push and flush, recorded with the loop's time; `closed_after` pushes raise LiveError."""

    def __init__(self, loop: asyncio.AbstractEventLoop, closed_after: int | None = None) -> None:
        self.loop, self.closed_after = loop, closed_after
        self.pushes: list[tuple[float, np.ndarray, int]] = []
        self.flushed = False

    def push(self, samples: np.ndarray, rate: int) -> None:
        if self.closed_after is not None and len(self.pushes) >= self.closed_after:
            raise LiveError("this live session has been closed")
        self.pushes.append((self.loop.time(), samples.copy(), rate))

    def flush(self) -> None:
        self.flushed = True


def test_every_chunk_goes_in_order_at_its_time_then_a_flush():
    audio = np.arange(1000, dtype=np.float32)

    async def run() -> RecordingLive:
        live = RecordingLive(asyncio.get_running_loop())
        began = asyncio.get_running_loop().time()
        await push_real_time(live, audio, 8000, 0.02)  # 160-sample chunks: six whole and one of 40
        live.began = began
        return live

    live = asyncio.run(run())
    assert [chunk.shape[0] for _, chunk, _ in live.pushes] == [160] * 6 + [40]
    np.testing.assert_array_equal(np.concatenate([chunk for _, chunk, _ in live.pushes]), audio)
    assert {rate for _, _, rate in live.pushes} == {8000} and live.flushed
    offsets = np.array([moment - live.began for moment, _, _ in live.pushes])
    # chunk k at k * 20 ms: never early (the loop's clock; 1 ms for its timer granularity), at most 15 ms late on a
    # busy 2-core machine
    assert np.all(offsets >= np.arange(7) * 0.02 - 1e-3) and np.all(offsets <= np.arange(7) * 0.02 + 0.015)


def test_a_cancelled_voice_pushes_nothing_more_and_does_not_flush():
    async def run() -> RecordingLive:
        live = RecordingLive(asyncio.get_running_loop())
        task = asyncio.ensure_future(push_real_time(live, np.zeros(16000, np.float32), 16000, 0.02))
        await asyncio.sleep(0.05)
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task
        live.at_cancel = len(live.pushes)
        await asyncio.sleep(0.1)  # five chunks' time
        return live

    live = asyncio.run(run())
    assert 1 <= live.at_cancel < 50 and len(live.pushes) == live.at_cancel and not live.flushed


def test_a_closed_session_stops_the_voice_quietly():
    async def run() -> RecordingLive:
        live = RecordingLive(asyncio.get_running_loop(), closed_after=2)
        await push_real_time(live, np.zeros(3200, np.float32), 16000, 0.02)  # returns, raising nothing
        return live

    live = asyncio.run(run())
    assert len(live.pushes) == 2 and not live.flushed


def test_an_empty_voice_only_flushes():
    async def run() -> RecordingLive:
        live = RecordingLive(asyncio.get_running_loop())
        await push_real_time(live, np.zeros(0, np.float32), 16000, 0.02)
        return live

    live = asyncio.run(run())
    assert live.pushes == [] and live.flushed


def test_the_bench_pushes_every_voice_whole_and_compares_checkouts(lam_voice_bundle):
    got = pushes_run(str(lam_voice_bundle), sessions=3, seconds=1.0)
    assert got["chunks"] == 3 * 50  # 1 s in 20 ms chunks, each of the three voices
    assert got["queued_samples"] == 3 * 16000  # nobody reads frames: every pushed sample is still queued
    assert got["cpu_s"] > 0 and got["us_per_chunk"] == pytest.approx(1e6 * got["cpu_s"] / 150)
    result = run_voice_pushes(lam_voice_bundle, [2], seconds=1.0, rounds=1, baseline=ROOT, progress=False)
    row = result["rows"][0]
    assert row["old"]["chunks"] == row["new"]["chunks"] == 2 * 50 and len(row["old"]["rounds"]) == 1
    assert row["ratio"] == pytest.approx(row["new"]["us_per_chunk"] / row["old"]["us_per_chunk"])
    table = voice_pushes_table(result)
    assert "| 2 |" in table and "×" in table and table.splitlines()[1].count("|") == table.splitlines()[0].count("|")


class PoolLive:
    """A live session's push and flush, recorded (a pool thread's feeds, no loop); `closed_after` pushes raise."""

    def __init__(self, closed_after: int | None = None) -> None:
        self.closed_after = closed_after
        self.pushes: list[np.ndarray] = []
        self.flushed = False

    def push(self, samples: np.ndarray, rate: int) -> None:
        if self.closed_after is not None and len(self.pushes) >= self.closed_after:
            raise LiveError("this live session has been closed")
        assert rate == 8000
        self.pushes.append(samples.copy())

    def flush(self) -> None:
        self.flushed = True


def test_a_paced_voice_feeds_the_chunks_whose_time_has_come_then_flushes():
    audio = np.arange(1000, dtype=np.float32)  # 160-sample chunks at 8 kHz and 20 ms: six whole and one of 40
    live = PoolLive()
    voice = PacedVoice(live, audio, 8000, 0.02, start=100.0)
    voice.feed(99.0)  # before its start: nothing
    assert live.pushes == []
    voice.feed(100.0)  # chunk 0's time
    voice.feed(100.019)  # chunk 1 is 1 ms away: nothing new
    voice.feed(100.05)  # chunks 1 and 2, in one push
    voice.feed(100.05)
    assert [chunk.shape[0] for chunk in live.pushes] == [160, 320] and not live.flushed
    voice.feed(100.12)  # chunks 3..6 (the last), then the flush
    assert [chunk.shape[0] for chunk in live.pushes] == [160, 320, 520] and live.flushed and voice.ended
    np.testing.assert_array_equal(np.concatenate(live.pushes), audio)
    voice.feed(101.0)  # ended: nothing more
    assert len(live.pushes) == 3


def test_a_cancelled_paced_voice_pushes_nothing_more_and_does_not_flush():
    live = PoolLive()
    voice = PacedVoice(live, np.zeros(16000, np.float32), 8000, 0.02, start=0.0)
    voice.feed(0.05)
    voice.cancel()  # a barge-in
    voice.feed(10.0)
    assert len(live.pushes) == 1 and not live.flushed and voice.ended


def test_a_closed_session_ends_the_paced_voice_quietly_and_an_empty_one_only_flushes():
    live = PoolLive(closed_after=1)
    voice = PacedVoice(live, np.zeros(3200, np.float32), 8000, 0.02, start=0.0)
    voice.feed(0.0)
    voice.feed(0.1)  # raises LiveError inside: the voice ends, raising nothing
    assert len(live.pushes) == 1 and voice.ended and not live.flushed
    empty = PoolLive()
    PacedVoice(empty, np.zeros(0, np.float32), 8000, 0.02, start=0.0).feed(0.0)
    assert empty.pushes == [] and empty.flushed
