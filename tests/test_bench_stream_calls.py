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
