"""`gt-bench batch`: seconds of video made per second of wall time by `gt-render`'s engines (docs/batch.md).

Two parts, in one run:

* throughput: a job list of `jobs` clips of `job_s` seconds each, rendered by the local engine with 1 and 2
  workers and by the Ray engine with 1 and 2 actors (a local Ray started once for the bench), the four cases
  alternating round by round into fresh output folders; medians over the rounds;
* a long clip: one job of `long_s` seconds rendered whole and in `segment_s` segments on 2 local workers,
  alternating.

From the measurements it extrapolates to many machines: each case's worker-seconds per second of video (the cost
that spreads over machines) against the run's fixed costs (worker start, the first head load) and the driver's
per-job cost (the manifest's fsynced append), which do not."""

from __future__ import annotations

import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

DEMO_SPEECH = Path(__file__).resolve().parents[2] / "samples" / "demo_speech.wav"


def _clip(seconds: float, speech: np.ndarray, rate: int) -> np.ndarray:
    """The demo speech repeated to `seconds`."""
    samples = int(round(seconds * rate))
    return np.tile(speech, samples // len(speech) + 1)[:samples]


def _write_jobs(folder: Path, bundle: Path, names: list[str], resolution: int) -> Path:
    import json

    path = folder / f"jobs-{len(names)}-{names[0]}.jsonl"
    lines = [json.dumps({"bundle": str(bundle.absolute()), "audio": name, "out": f"{Path(name).stem}.mp4",
                         "resolution": resolution}) for name in names]
    path.write_text("".join(line + "\n" for line in lines))
    return path


def _manifest_append_ms(folder: Path, count: int = 200) -> float:
    """Median ms of one fsynced manifest append (the driver's own cost per finished job)."""
    from gaussiantalker.batch import Manifest, Record

    manifest = Manifest(folder)
    times = []
    for index in range(count):
        start = time.perf_counter()
        manifest.append(Record(out=f"{index}.mp4", inputs={"bundle": "0" * 64, "audio": "1" * 64},
                               settings="2" * 64, status="ok", output="3" * 64))
        times.append(time.perf_counter() - start)
    return 1000 * statistics.median(times)


def run_batch_bench(bundle: Path, *, resolution: int = 256, jobs: int = 8, job_s: float = 6.0,
                    long_s: float = 600.0, segment_s: float = 60.0, rounds: int = 3, long_rounds: int = 1,
                    ray: bool = True, log: Callable[[str], None] = print) -> dict:
    """Run both parts (see the module docstring) and return their measurements."""
    from gaussiantalker.batch import LocalEngine, read_jobs, run_jobs
    from gaussiantalker.sdk.audio import TARGET_SAMPLE_RATE, load_audio, write_wav

    speech = load_audio(DEMO_SPEECH)
    from gaussiantalker.batch.local import usable_cores

    result: dict = {"bundle": str(bundle), "resolution": resolution, "jobs": jobs, "job_s": job_s,
                    "cores": usable_cores(),
                    "long_s": long_s, "segment_s": segment_s, "rounds": rounds, "cases": {}, "long": {}}
    with tempfile.TemporaryDirectory(prefix="gt-bench-batch-") as tmp:
        folder = Path(tmp)
        names = [f"clip{index}.wav" for index in range(jobs)]
        for index, name in enumerate(names):  # each clip starts elsewhere in the speech: no two are the same
            shift = index * len(speech) // max(jobs, 1)
            write_wav(folder / name, _clip(job_s, np.roll(speech, -shift), TARGET_SAMPLE_RATE))
        write_wav(folder / "long.wav", _clip(long_s, speech, TARGET_SAMPLE_RATE))
        job_list = read_jobs(_write_jobs(folder, bundle, names, resolution))
        long_list = read_jobs(_write_jobs(folder, bundle, ["long.wav"], resolution))
        result["manifest_append_ms"] = _manifest_append_ms(folder / "manifest-bench")

        engines: dict[str, Callable[[], object]] = {"local x1": lambda: LocalEngine(1),
                                                    "local x2": lambda: LocalEngine(2)}
        threads = {"local x1": LocalEngine(1).threads, "local x2": LocalEngine(2).threads, "ray x1": 1, "ray x2": 1}
        ray_engine = None
        if ray:
            from gaussiantalker.batch.ray_engine import RayEngine

            start = time.perf_counter()
            ray_engine = RayEngine(None).__enter__()
            ray_engine.connect()
            result["ray_start_s"] = time.perf_counter() - start
            engines["ray x1"] = lambda: _RayWorkers(ray_engine, 1)
            engines["ray x2"] = lambda: _RayWorkers(ray_engine, 2)
        runs: dict[str, list[dict]] = {name: [] for name in engines}
        try:
            for round_index in range(rounds):
                for name, make in engines.items():
                    summary = run_jobs(job_list, folder / f"out-{name}-{round_index}".replace(" ", ""), make(),
                                       progress=False, segment_s=None)
                    if summary.failed:
                        raise RuntimeError(f"{name}: {summary.failed}")
                    runs[name].append({"wall_s": summary.wall_s, "video_s": summary.video_s,
                                       "rate": summary.video_s / summary.wall_s})
                    log(f"round {round_index + 1}/{rounds} {name}: {summary.describe()}")
        finally:
            if ray_engine is not None:
                ray_engine.__exit__(None, None, None)
        for name, measured in runs.items():
            result["cases"][name] = {"runs": measured, "threads": threads[name],
                                     "rate": statistics.median(r["rate"] for r in measured),
                                     "wall_s": statistics.median(r["wall_s"] for r in measured)}

        long_runs: dict[str, list[dict]] = {"whole": [], "split": []}
        for round_index in range(long_rounds):
            for name, segment in (("whole", None), ("split", segment_s)):
                outdir = folder / f"long-{name}-{round_index}"
                summary = run_jobs(long_list, outdir, LocalEngine(2), progress=False, segment_s=segment)
                if summary.failed:
                    raise RuntimeError(f"long {name}: {summary.failed}")
                from gaussiantalker.batch import Manifest

                record = Manifest(outdir).latest["long.mp4"]
                long_runs[name].append({"wall_s": summary.wall_s, "video_s": summary.video_s,
                                        "rate": summary.video_s / summary.wall_s, "segments": record.segments,
                                        "worker_s": record.seconds})
                log(f"long round {round_index + 1}/{long_rounds} {name}: {summary.describe()} "
                    f"({record.segments} segment(s))")
        for name, measured in long_runs.items():
            result["long"][name] = {"runs": measured, "rate": statistics.median(r["rate"] for r in measured),
                                    "wall_s": statistics.median(r["wall_s"] for r in measured),
                                    "worker_s": statistics.median(r["worker_s"] for r in measured)}
    result["extrapolation"] = extrapolate(result)
    return result


class _RayWorkers:
    """The bench's Ray engine with a fixed actor count (the cluster started once, actors per run)."""

    def __init__(self, engine, workers: int) -> None:
        self.engine, self.workers = engine, workers

    def run(self, jobs, outdir, segment_s=None):
        self.engine.workers = self.workers
        return self.engine.run(jobs, outdir, segment_s)


def extrapolate(result: dict, machines: int = 100, cores: int = 16, jobs: int = 10_000, job_s: float = 60.0
                ) -> dict:
    """What `machines` machines of `cores` cores would do with `jobs` jobs of `job_s` seconds, from this run:
    the rate per core with every core busy (the long clip split over this machine's cores: steady state, head
    loads and joins included), a run's fixed cost (the 2-worker case's wall time less its work at that rate: pool
    start, first head loads), and the driver's own ceiling (fsynced manifest appends per second: one a job)."""
    per_core = result["long"]["split"]["rate"] / result["cores"]
    two = result["cases"]["local x2"]
    fixed_s = max(0.0, two["wall_s"] - result["jobs"] * result["job_s"] / (per_core * result["cores"]))
    workers = machines * cores
    work_s = jobs * job_s / (per_core * workers)
    driver_jobs_per_s = 1000.0 / max(result["manifest_append_ms"], 1e-3)
    wall_s = max(fixed_s + work_s, jobs / driver_jobs_per_s)
    ray_ratio = result["cases"]["ray x2"]["rate"] / two["rate"] if "ray x2" in result["cases"] else None
    return {"machines": machines, "cores": cores, "jobs": jobs, "job_s": job_s, "per_core_rate": per_core,
            "fixed_s": fixed_s, "work_s": work_s, "wall_s": wall_s, "rate": jobs * job_s / wall_s,
            "ideal_rate": per_core * workers, "driver_jobs_per_s": driver_jobs_per_s, "ray_vs_local_x2": ray_ratio,
            # jobs shorter than this finish faster than the driver records them
            "driver_limit_job_s": workers * per_core / driver_jobs_per_s}


def batch_table(result: dict) -> str:
    """The report's tables: the engines' rates, the long clip split and whole, and the extrapolation."""
    lines = ["| engine | splatter threads each | video s / wall s (median) | wall s (median) | vs local x1 |",
             "|---|---|---|---|---|"]
    base = result["cases"]["local x1"]["rate"]
    for name, case in result["cases"].items():
        lines.append(f"| {name} | {case.get('threads', '')} | {case['rate']:.2f} | {case['wall_s']:.1f} | "
                     f"{case['rate'] / base:.2f}x |")
    long = result["long"]
    lines += ["", f"One {result['long_s']:.0f} s clip on 2 local workers:", "",
              "| render | video s / wall s | wall s | worker s | segments |", "|---|---|---|---|---|"]
    for name in ("whole", "split"):
        case = long[name]
        lines.append(f"| {name} | {case['rate']:.2f} | {case['wall_s']:.1f} | {case['worker_s']:.1f} | "
                     f"{case['runs'][0]['segments']} |")
    lines.append(f"\nsplit / whole: {long['split']['rate'] / long['whole']['rate']:.2f}x")
    ext = result["extrapolation"]
    lines += ["", f"Extrapolated to {ext['machines']} machines x {ext['cores']} cores ({ext['jobs']} jobs of "
              f"{ext['job_s']:.0f} s): a busy core renders {ext['per_core_rate']:.2f} s of video per second (the "
              f"long clip split here, every core busy), so the work takes {ext['work_s']:.0f} s on "
              f"{ext['machines'] * ext['cores']} cores, plus a run's fixed cost of ~{ext['fixed_s']:.1f} s "
              f"(measured with 2 workers here); the "
              f"driver's manifest appends allow {ext['driver_jobs_per_s']:.0f} jobs a second, so they are not the "
              f"limit until jobs are shorter than {ext['driver_limit_job_s']:.1f} s. "
              f"About {ext['rate']:.0f} s of video per second in all ({ext['wall_s'] / 60:.1f} min for the list)."]
    return "\n".join(lines)
