"""`gt-bench stream-calls` (tools/bench/stream_calls.py): every bundle timed on every case, ratios to the first, and
a clear error for a bundle without a streaming graph."""

from __future__ import annotations

import pytest
from typer.testing import CliRunner

from tools.bench.app import app
from tools.bench.stream_calls import run_stream_calls, stream_calls_table


def test_each_bundle_is_timed_on_each_case(lam_voice_bundle):
    result = run_stream_calls([lam_voice_bundle, lam_voice_bundle], [(1, 1), (3, 2)], rounds=2, calls=2,
                              progress=False)
    assert [(row["sessions"], row["frames"]) for row in result["cases"]] == [(1, 1), (3, 2)]
    for row in result["cases"]:
        assert len(row["ms_per_call"]) == 2 and min(row["ms_per_call"]) > 0
        assert row["ratio_to_first"][0] == 1.0
        assert row["ms_per_session_frame"][1] == pytest.approx(
            row["ms_per_call"][1] / (row["sessions"] * row["frames"]))
    table = stream_calls_table(result)
    assert table.count("\n") == 3 and "| 3 | 2 |" in table and "×" in table


def test_a_bundle_without_a_stream_is_named(lam_voice_bundle, monkeypatch):
    import types

    import gaussiantalker.runtime.stages as stages

    monkeypatch.setattr(stages, "open_driver", lambda path, threads=None: types.SimpleNamespace(has_stream=False))
    with pytest.raises(ValueError, match="older.gtb: the bundle has no streaming translator"):
        run_stream_calls([lam_voice_bundle.parent / "older.gtb"], [(1, 1)], rounds=1, calls=1, progress=False)


def test_bad_cases_are_refused(lam_voice_bundle, tmp_path):
    runner = CliRunner(env={"COLUMNS": "300"})
    result = runner.invoke(app, ["stream-calls", str(lam_voice_bundle), "--frames", "9"])
    assert result.exit_code != 0 and "frames a call" in result.output
    result = runner.invoke(app, ["stream-calls", str(tmp_path / "missing.gtb")])
    assert result.exit_code != 0 and "no such bundle" in result.output


def test_the_steady_graph_is_timed_where_the_bundle_has_one(small_export, lam_voice_bundle):
    result = run_stream_calls([small_export.path], [(2, 1)], rounds=1, calls=1, progress=False, graph="steady")
    assert result["graph"] == "steady" and result["cases"][0]["ms_per_call"][0] > 0
    with pytest.raises(ValueError, match="has no steady graph"):
        run_stream_calls([lam_voice_bundle], [(1, 1)], rounds=1, calls=1, progress=False, graph="steady")
    with pytest.raises(ValueError, match="'refreshing' or 'steady'"):
        run_stream_calls([lam_voice_bundle], [(1, 1)], rounds=1, calls=1, progress=False, graph="both")


def test_the_ratio_is_the_median_of_each_rounds_own(monkeypatch):
    """The machine's speed drifts: a bundle's ratio to the first is the median of the rounds' own ratios (the two
    bundles timed back to back in a round, in turn first), so a slowdown that each bundle's median takes from other
    rounds cancels. Here bundle B costs 0.9 of A; the machine is twice as slow until it speeds up in round 2,
    between A's turn and B's: A's median is a slow round's, B's a fast one's (0.45 A), each round's own ratio 0.9
    but that round's 0.45."""
    import types

    import numpy as np

    import gaussiantalker.runtime.stages as stages
    import tools.bench.stream_calls as stream_calls

    calls, clock, made = 2, [0.0], [0]
    slow = [2, 2, 2, 2, 2, 1, 1, 1, 1, 1]  # each turn's speed, in the order the turns run (a warm call and `calls`)

    def driver(cost: float):
        spec = types.SimpleNamespace(frame_samples=4, rest_state=np.zeros(2, np.float32), steady=False)

        def run_stream(audio, state, keep, refresh):
            clock[0] += cost * slow[made[0] // (calls + 1)]
            made[0] += 1

        return types.SimpleNamespace(has_stream=True, stream_spec=spec, run_stream=run_stream)

    drivers = {"a.gtb": driver(1.0), "b.gtb": driver(0.9)}
    monkeypatch.setattr(stages, "open_driver", lambda path, threads=None: drivers[str(path)])
    monkeypatch.setattr(stream_calls.time, "perf_counter", lambda: clock[0])
    result = run_stream_calls(["a.gtb", "b.gtb"], [(1, 1)], rounds=5, calls=calls, progress=False)
    row = result["cases"][0]
    assert row["ms_per_call"] == pytest.approx([2e3, 0.9e3])  # A's median slow, B's fast
    assert row["ratio_to_first"] == pytest.approx([1.0, 0.9])
