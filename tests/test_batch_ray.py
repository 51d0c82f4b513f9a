"""`gt-render --ray` (batch/ray_engine.py, docs/batch.md) on a two-node Ray cluster started on this machine
(`ray.cluster_utils.Cluster`: a head and one more node, one CPU each, so the two actors land on different nodes):
the same job list renders there with frames identical to the local engine's, long jobs split across the nodes; an
actor process SIGKILLed mid-job is restarted by Ray and its call rerun, every output complete and valid and the
manifest true; a node removed mid-run shrinks the pool and its job reruns on the other node.

Bounds: each cluster starts in ~5 s; the renders are the small speaker at 128x128 on 1-8 s clips."""

from __future__ import annotations

import os
import signal
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
from ci_tools import need_module
from test_batch import SIZE, decoded, decoded_audio, hidden_files, killing_the_writer_of, write_jobs

from gaussiantalker.batch import Manifest, render_jobs
from gaussiantalker.batch.digests import file_digest
from gaussiantalker.sdk.audio import TARGET_SAMPLE_RATE, load_audio, write_wav

need_module("ray", "ray", module_level=True)

DEMO_SPEECH = Path(__file__).resolve().parents[1] / "samples" / "demo_speech.wav"


@contextmanager
def two_nodes() -> Iterator:
    """A Ray head and a second node, one CPU each (`.address`, `.remove_node`); the handlers of SIGINT and SIGTERM
    that Ray's node processes install in this process are put back when it ends (later tests see pytest's)."""
    from ray.cluster_utils import Cluster

    handlers = {number: signal.getsignal(number) for number in (signal.SIGINT, signal.SIGTERM)}
    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1, "include_dashboard": False})
    try:
        cluster.second = cluster.add_node(num_cpus=1)
        cluster.wait_for_nodes()
        yield cluster
    finally:
        cluster.shutdown()
        for number, handler in handlers.items():
            signal.signal(number, handler)


@pytest.fixture(scope="module")
def cluster():
    """A two-node cluster the tests connect to by address, as a user would."""
    with two_nodes() as running:
        yield running


@pytest.fixture()
def inputs(tmp_path, small_export) -> Path:
    folder = tmp_path / "in"
    folder.mkdir()
    os.symlink(small_export.path, folder / "speaker.gtb")
    speech = load_audio(DEMO_SPEECH)
    for name, seconds in (("a.wav", 1.0), ("long.wav", 3.0), ("eight.wav", 8.0)):
        write_wav(folder / name, speech[:int(seconds * TARGET_SAMPLE_RATE)])
    return folder


def test_a_two_node_cluster_renders_what_the_local_engine_renders(cluster, inputs, tmp_path):
    jobs = write_jobs(inputs / "jobs.jsonl", [
        {"bundle": "speaker.gtb", "audio": "a.wav", "out": "a.mkv", "resolution": SIZE, "codec": "ffv1"},
        {"bundle": "speaker.gtb", "audio": "long.wav", "out": "long.mkv", "resolution": SIZE, "codec": "ffv1"},
        {"bundle": "speaker.gtb", "audio": "long.wav", "out": "long.mp4", "resolution": SIZE}])
    handlers = signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)
    on_ray = render_jobs(jobs, tmp_path / "ray", ray=cluster.address, segment_s=1.0, progress=False)
    assert (signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)) == handlers  # the app's, not Ray's
    local = render_jobs(jobs, tmp_path / "local", workers=2, segment_s=1.0, progress=False)
    assert not on_ray.failed and not local.failed and sorted(on_ray.done) == ["a.mkv", "long.mkv", "long.mp4"]
    for name in ("a.mkv", "long.mkv"):
        got, want = decoded(tmp_path / "ray" / name), decoded(tmp_path / "local" / name)
        assert len(got) == len(want) >= 25 and all(np.array_equal(g, w) for g, w in zip(got, want, strict=True))
    assert len(decoded(tmp_path / "ray" / "long.mp4")) == 75
    assert np.array_equal(decoded_audio(tmp_path / "ray" / "long.mp4"), decoded_audio(tmp_path / "local" / "long.mp4"))
    records = Manifest(tmp_path / "ray").latest
    assert records["long.mkv"].segments == 3 and records["a.mkv"].segments == 1
    assert all(file_digest(tmp_path / "ray" / out) == r.output for out, r in records.items())
    assert hidden_files(tmp_path / "ray") == []
    again = render_jobs(jobs, tmp_path / "ray", ray=cluster.address, progress=False)  # resumes: all done
    assert sorted(again.skipped) == ["a.mkv", "long.mkv", "long.mp4"] and not again.done


def test_the_actors_are_one_per_cpu_on_both_nodes(cluster):
    from gaussiantalker.batch.ray_engine import ActorCalls, RayEngine

    with RayEngine(cluster.address) as engine:
        calls = ActorCalls(engine.actor_count(), engine.threads, engine.retries)
        try:
            places = calls.places()
        finally:
            calls.close()
    assert len(places) == 2 and len({node for _, node in places}) == 2


def test_a_killed_actor_is_restarted_and_its_job_rerun(cluster, inputs, tmp_path):
    """SIGKILL the actor process writing the 8 s job (its partial file names its pid): no final file then; Ray
    restarts the actor, reruns the call, and the run ends with every output complete and the manifest true."""
    jobs = write_jobs(inputs / "jobs.jsonl", [
        {"bundle": "speaker.gtb", "audio": "eight.wav", "out": "eight.mkv", "resolution": SIZE},
        {"bundle": "speaker.gtb", "audio": "a.wav", "out": "a.mkv", "resolution": SIZE},
        {"bundle": "speaker.gtb", "audio": "long.wav", "out": "long.webm", "resolution": SIZE}])
    outdir = tmp_path / "out"
    with killing_the_writer_of(outdir, "eight.mkv") as killed:
        summary = render_jobs(jobs, outdir, ray=cluster.address, segment_s=None, progress=False)
    assert killed and killed[0][1] is False  # killed mid-job, and no final file then
    assert sorted(summary.done) == ["a.mkv", "eight.mkv", "long.webm"] and not summary.failed, summary.failed
    assert len(decoded(outdir / "eight.mkv")) == 200 and len(decoded(outdir / "long.webm")) == 75
    records = Manifest(outdir).latest
    assert all(r.status == "ok" and file_digest(outdir / out) == r.output for out, r in records.items())
    assert sorted(p.name for p in outdir.iterdir()) == ["a.mkv", "eight.mkv", "long.webm", "manifest.jsonl"]


def test_a_lost_node_shrinks_the_pool_and_its_job_is_rerun(inputs, tmp_path):
    """A cluster of its own (a head and node B, one CPU each): node B is removed while both actors render; B's
    actor cannot come back (the head's CPU is held by the other actor), so its job reruns on the head's actor, and
    the run ends with every output complete, valid and recorded with its true digest (attempts 2)."""
    jobs = write_jobs(inputs / "jobs.jsonl", [
        {"bundle": "speaker.gtb", "audio": "eight.wav", "out": f"{name}.mkv", "resolution": SIZE}
        for name in ("one", "two")] + [
        {"bundle": "speaker.gtb", "audio": "a.wav", "out": "a.mkv", "resolution": SIZE}])
    outdir = tmp_path / "out"
    removed = threading.Event()

    def remove_node_b_when_both_render(lost) -> None:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            if outdir.is_dir() and len(list(outdir.glob(".*.mkv.partial-*"))) >= 2:
                lost.remove_node(lost.second)
                removed.set()
                return
            time.sleep(0.01)

    with two_nodes() as lost:
        remover = threading.Thread(target=remove_node_b_when_both_render, args=(lost,))
        remover.start()
        try:
            summary = render_jobs(jobs, outdir, ray=lost.address, segment_s=None, progress=False)
        finally:
            remover.join()
    assert removed.is_set()
    assert sorted(summary.done) == ["a.mkv", "one.mkv", "two.mkv"] and not summary.failed, summary.failed
    records = Manifest(outdir).latest
    assert all(r.status == "ok" and file_digest(outdir / out) == r.output for out, r in records.items())
    assert sorted(r.attempts for r in records.values()) == [1, 1, 2]
    assert [len(decoded(outdir / name)) for name in ("one.mkv", "two.mkv", "a.mkv")] == [200, 200, 25]
    assert sorted(p.name for p in outdir.iterdir()) == ["a.mkv", "manifest.jsonl", "one.mkv", "two.mkv"]


def test_a_run_with_nothing_to_do_starts_no_ray(inputs, tmp_path, monkeypatch):
    """Everything done already: the Ray engine never connects, so no cluster is reached (nor a local Ray started)
    for a run with nothing to render."""
    import ray

    jobs = write_jobs(inputs / "jobs.jsonl", [{"bundle": "speaker.gtb", "audio": "a.wav", "out": "a.mkv",
                                               "resolution": SIZE}])
    assert render_jobs(jobs, tmp_path / "out", workers=1, progress=False).done == ["a.mkv"]
    monkeypatch.setattr(ray, "init", lambda *args, **kwargs: pytest.fail("ray.init for a run with nothing to do"))
    again = render_jobs(jobs, tmp_path / "out", ray="127.0.0.1:1", progress=False)
    assert again.skipped == ["a.mkv"] and not again.done
