"""What runs inside a worker (a local process or a Ray actor): its loaded TalkingHeads, kept between calls (a few
at most), and the three steps of a job (batch/job_steps.py): `start` (a short job rendered whole, or a long one's
drives made once), `segment` (a range of frames into a file of its own) and `join` (the segments' packets and the
clip's audio into the output). Every output goes through a partial name renamed when complete (docs/batch.md)."""

from __future__ import annotations

import contextlib
import os
import time
from collections import OrderedDict
from contextlib import closing
from pathlib import Path

from gaussiantalker.sdk.errors import GaussianTalkerError, VideoError

from .digests import file_digest
from .engine import JobResult, one_line
from .job_steps import Call, SegmentDone, Split
from .jobs import Job
from .outputs import partial_path, segment_path

MAX_HEADS = 4  # loaded heads a worker keeps (each holds its bundle's graphs and a splatter)
# Graph threads of every batch head: the workers are the parallelism, and onnxruntime's results depend on its thread
# count, so one thread makes a job's frames the same whatever the worker count (docs/batch.md).
GRAPH_THREADS = 1
# Depth-sort every frame: with a sort interval a frame's order depends on the frames before it, and a segment or a
# retried job starts afresh, so only sort_interval=1 makes every frame the same however the clip is cut.
SORT_INTERVAL = 1
# Codecs whose segments are not joined (a palette per frame): such jobs render whole.
UNSPLIT_CODECS = ("gif",)
_heads: OrderedDict = OrderedDict()


def init_worker(threads: int) -> None:
    """Set a fresh worker's thread budget before numba loads: the CPU splatter's threads, so N workers share the
    cores instead of each taking all of them."""
    os.environ["NUMBA_NUM_THREADS"] = str(threads)
    os.environ["OMP_NUM_THREADS"] = str(threads)


def loaded_head(job: Job):
    """The worker's TalkingHead for this job's bundle and output settings, loaded once; the least recently used
    is closed beyond MAX_HEADS."""
    from gaussiantalker.runtime import TalkingHead
    from gaussiantalker.runtime.playback import orbited_camera

    key = job.head_key()
    if key in _heads:
        _heads.move_to_end(key)
        return _heads[key]
    head = TalkingHead(job.bundle, resolution=job.resolution, composite=job.composite, threads=GRAPH_THREADS,
                       renderer="auto", sort_interval=SORT_INTERVAL)
    try:
        if job.camera is not None:
            head.camera = orbited_camera(head, *job.camera)
    except BaseException:
        head.close()
        raise
    _heads[key] = head
    while len(_heads) > MAX_HEADS:
        _heads.popitem(last=False)[1].close()
    return head


def drop_head(job: Job) -> None:
    """Close and forget a head whose render failed in an unexpected way (its state is not trusted)."""
    head = _heads.pop(job.head_key(), None)
    if head is not None:
        with contextlib.suppress(Exception):
            head.close()


def run_call(call: Call) -> object:
    """Run one step here: its result, or a failed JobResult with a one-line reason (never raised: the SDK's
    errors by their message, anything else with its type)."""
    step = {"start": start_job, "segment": render_segment, "join": join_segments}[call.step]
    start = time.perf_counter()
    try:
        return step(call.job, Path(call.outdir), *call.args)
    except Exception as exc:
        if not isinstance(exc, GaussianTalkerError):
            drop_head(call.job)
        return JobResult(call.job.out, False, reason=one_line(exc), seconds=time.perf_counter() - start)


def start_job(job: Job, outdir: Path, segment_s: float | None) -> JobResult | Split:
    """A job no longer than `segment_s` (None: any) rendered whole; a longer one's drives made once and cut into
    segments of `segment_s`."""
    from gaussiantalker.runtime.playback import playback, video_drives

    start = time.perf_counter()
    head = loaded_head(job)
    target = outdir / job.out
    plan = head.plan_video(target, codec=job.codec, crf=job.crf)  # checked before any frame
    play = playback(head, job.audio, motion=job.motion)
    fps = job.fps or head.fps
    per_segment = None if segment_s is None else max(1, round(segment_s * fps))
    if per_segment is None or play.frames * fps / head.fps <= per_segment or plan.codec.name in UNSPLIT_CODECS:
        return _render_whole(head, job, target, start)
    drives, shown = video_drives(head, play, job.fps)
    ranges = [(first, min(first + per_segment, len(drives))) for first in range(0, len(drives), per_segment)]
    return Split(drives, shown, ranges, play.composited, fps, time.perf_counter() - start)


def _render_whole(head, job: Job, target: Path, start: float) -> JobResult:
    partial = partial_path(target)
    frames = 0

    def count(_frame) -> None:
        nonlocal frames
        frames += 1

    try:
        head.write_video(partial, job.audio, motion=job.motion, codec=job.codec, crf=job.crf, fps=job.fps,
                         on_frame=count)
        digest = file_digest(partial)
        os.replace(partial, target)
    finally:
        partial.unlink(missing_ok=True)
    return JobResult(job.out, True, output=digest, seconds=time.perf_counter() - start,
                     video_s=frames / (job.fps or head.fps))


def render_segment(job: Job, outdir: Path, drives: list, index: int, shown: list[int], composited: bool,
                   fps: float) -> SegmentDone:
    """A range of the job's frames (their drives, and the speaker frame each shows) into segment file `index` at
    `fps`, no audio."""
    from gaussiantalker.runtime.frame_loops import write_frames
    from gaussiantalker.runtime.playback import drive_frames
    from gaussiantalker.sdk.video import VideoWriter

    start = time.perf_counter()
    head = loaded_head(job)
    plan = head.plan_video(segment_path(outdir / job.out, index), codec=job.codec, crf=job.crf)
    frames = drive_frames(head, drives, composited=composited, reference_frames=shown)
    with closing(frames), VideoWriter(plan.path, fps, plan.size, plan=plan) as out:
        write_frames(out, frames, len(drives), pipelined=head.backend_settings.pipeline is not False, progress=False)
    return SegmentDone(str(plan.path), len(drives), time.perf_counter() - start)


def join_segments(job: Job, outdir: Path, parts: list[SegmentDone], fps: float) -> JobResult:
    """The segments' packets, in order, and the whole clip's audio into the output (no frame decoded or encoded
    again); the segment files are removed."""
    from gaussiantalker.sdk.video import VideoWriter

    start = time.perf_counter()
    head = loaded_head(job)
    target = outdir / job.out
    partial = partial_path(target)
    plan = head.plan_video(partial, codec=job.codec, crf=job.crf)
    samples = None if job.audio is None else head.driver.load_audio(job.audio)
    try:
        with VideoWriter(plan.path, fps, plan.size, audio=samples, sample_rate=head.sample_rate, plan=plan,
                         encoded_like=parts[0].path) as out:
            for part in parts:
                if out.append_encoded(part.path) != part.frames:
                    raise VideoError(f"segment {part.path} holds other than its {part.frames} frames")
        digest = file_digest(partial)
        os.replace(partial, target)
    finally:
        partial.unlink(missing_ok=True)
    for part in parts:
        Path(part.path).unlink(missing_ok=True)
    frames = sum(part.frames for part in parts)
    return JobResult(job.out, True, output=digest, seconds=time.perf_counter() - start, video_s=frames / fps)
