"""`gt-bench batch` (tools/bench/batch_rate.py) end to end on the small speaker at 64x64 with 1 s jobs and a 3 s
long clip cut into 1 s segments, the local engine only (Ray's cases run the same code on RayEngine, which
tests/test_batch_ray.py covers): every case measured, the long clip split into 3 segments, the report's tables and
the extrapolation made from the measurements."""

from __future__ import annotations

from tools.bench.batch_rate import batch_table, run_batch_bench


def test_batch_bench_measures_every_case(small_export):
    result = run_batch_bench(small_export.path, resolution=64, jobs=2, job_s=1.0, long_s=3.0, segment_s=1.0,
                             rounds=1, ray=False, log=lambda _line: None)
    assert set(result["cases"]) == {"local x1", "local x2"}
    for case in result["cases"].values():
        run = case["runs"][0]
        assert run["video_s"] == 2.0 and run["rate"] == case["rate"] > 0
    assert [result["long"][name]["runs"][0]["segments"] for name in ("whole", "split")] == [1, 3]
    assert result["long"]["split"]["runs"][0]["video_s"] == 3.0
    ext = result["extrapolation"]
    assert ext["ideal_rate"] == ext["per_core_rate"] * 100 * 16 and ext["driver_jobs_per_s"] > 0
    assert ext["per_core_rate"] == result["long"]["split"]["rate"] / result["cores"]
    assert ext["wall_s"] >= ext["work_s"] == ext["jobs"] * ext["job_s"] / (ext["per_core_rate"] * 1600)
    table = batch_table(result)
    assert "| local x2 |" in table and "split / whole:" in table and "100 machines" in table
