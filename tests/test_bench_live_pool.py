"""`gt-bench live-pool` (tools/bench/live_pool.py): the pool's work on a fake clock makes every session's frames
(speech and idle), runs stacked translator calls, and compares two checkouts in fresh processes."""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from tools.bench.app import app
from tools.bench.live_pool import PHASES, alternate_rounds, live_pool_table, median_rows, pool_run, run_live_pool

ROOT = Path(__file__).resolve().parents[1]


def test_a_pool_run_makes_every_sessions_frames(lam_voice_bundle, monkeypatch):
    import gaussiantalker.runtime.live as live_module

    monkeypatch.setattr(live_module, "time", live_module.time)  # pool_run swaps in its fake clock: put it back
    got = pool_run(str(lam_voice_bundle), sessions=3, seconds=2.0)
    assert got["frames"] == 3 * 60  # 30 fps, every frame made on time on the fake clock
    assert 0 < got["calls"] < got["frames"] and got["rows"] >= got["calls"]  # sessions stacked in calls
    assert got["cpu_s"] > 0 and got["cpu_s_per_session_s"] == pytest.approx(got["cpu_s"] / 6.0)
    # the loop's parts, timed apart, are the whole loop (the clock reads between them aside: under 5%)
    parts = [got[f"{phase}_us_per_frame"] for phase in PHASES]
    assert all(part >= 0 for part in parts) and got["translate_us_per_frame"] > 0 and got["frames_us_per_frame"] > 0
    assert sum(parts) == pytest.approx(got["us_per_frame"], rel=0.05)


def test_two_checkouts_alternate_in_fresh_processes(lam_voice_bundle):
    result = run_live_pool(lam_voice_bundle, [2], seconds=1.0, rounds=1, baseline=ROOT, progress=False)
    row = result["rows"][0]
    assert len(row["old"]["rounds"]) == len(row["new"]["rounds"]) == 1
    assert row["old"]["frames"] == row["new"]["frames"] == 2 * 30  # the same code: the same frames
    assert row["ratio"] == pytest.approx(row["new"]["cpu_s_per_session_s"] / row["old"]["cpu_s_per_session_s"])
    table = live_pool_table(result)
    assert "| 2 |" in table and "×" in table and table.splitlines()[1].count("|") == table.splitlines()[0].count("|")
    phases = table.split("\n\n")[1].splitlines()  # where a frame's CPU goes: a row a version
    assert phases[0].count("|") == phases[1].count("|") == len(PHASES) + 3
    assert [line.split("|")[2].strip() for line in phases[2:]] == ["old", "new"]


def test_bad_options_are_refused(lam_voice_bundle, tmp_path):
    runner = CliRunner(env={"COLUMNS": "300"})
    result = runner.invoke(app, ["live-pool", str(lam_voice_bundle), "--baseline-checkout", str(tmp_path)])
    assert result.exit_code != 0 and "not a checkout of this project" in result.output
    result = runner.invoke(app, ["live-pool", str(tmp_path / "none.gtb")])
    assert result.exit_code != 0 and "no such bundle" in result.output


class _Recording:
    def __init__(self) -> None:
        self.pushes: list[int] = []
        self.flushed = False

    def push(self, samples, rate: int) -> None:
        self.pushes.append(samples.shape[0])

    def flush(self) -> None:
        self.flushed = True


def test_the_bench_gives_each_checkouts_voice_as_its_server_does(monkeypatch):
    """This checkout's server feeds a voice at each pool visit (one push of the chunks come); an older one's voice
    came chunk by chunk at each chunk's time: the bench does what the checkout it runs does, a flush after the last."""
    import numpy as np

    import gaussiantalker.serve.voices as voices_module
    from tools.bench.live_pool import _Voices

    speech = np.zeros(1000, np.float32)  # 320-sample chunks at 16 kHz: three whole and one of 40
    fed = _Voices([_Recording()], speech, 16000, [0.0])
    assert not fed.every_tick
    fed.feed(0, 0.05)  # chunks 0..2 have come
    fed.feed(0, 1.0)
    assert fed.lives[0].pushes == [960, 40] and fed.lives[0].flushed
    monkeypatch.delattr(voices_module, "PacedVoice")  # a checkout from before it
    pushed = _Voices([_Recording()], speech, 16000, [0.0])
    assert pushed.every_tick
    pushed.feed(0, 0.05)
    assert pushed.lives[0].pushes == [320, 320, 320] and not pushed.lives[0].flushed
    pushed.feed(0, 1.0)
    assert pushed.lives[0].pushes == [320, 320, 320, 40] and pushed.lives[0].flushed


def test_versions_take_turns_first_and_the_ratio_is_the_median_of_the_rounds_own(tmp_path):
    """Rounds alternate which version runs first, and new / old is the median of each round's own ratio (the two
    run back to back there): here the machine is twice as slow until it speeds up in round 2 between old's turn
    and new's, so old's median is a slow round's and new's a fast one's (their ratio 0.45), while every round's own
    ratio but that one's reads 0.9."""
    order = []

    def run(label, src, n):
        order.append(label)
        return {"cost": None}

    runs = alternate_rounds(tmp_path, [3], 4, "rounds", False, run)
    assert order == ["old", "new", "new", "old", "old", "new", "new", "old"]
    assert len(runs[("old", 3)]) == len(runs[("new", 3)]) == 4
    old = [{"cost": c} for c in (2.0, 2.0, 2.0, 1.0, 1.0)]
    new = [{"cost": c} for c in (1.8, 1.8, 0.9, 0.9, 0.9)]
    row = median_rows({("old", 3): old, ("new", 3): new}, [3], ("cost",), ())[0]
    assert row["old"]["cost"] == 2.0 and row["new"]["cost"] == 0.9
    assert row["ratio"] == pytest.approx(0.9)
