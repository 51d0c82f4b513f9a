"""Batch rendering (`gaussiantalker.batch`, `gt-render`, docs/batch.md) on the small speaker at 128x128 with 1-2 s
clips cut from samples/demo_speech.wav: the job list's checks (every bad line named), outputs equal to direct
`write_video` renders, resuming, --force, a failing job among good ones, and a worker killed mid-job.

Bounds: each run spawns its worker processes afresh (imports and head loads included); the whole file takes well
under a minute besides the session's `small_export` fixture."""

from __future__ import annotations

import json
import os
import re
import signal
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import av
import numpy as np
import pytest
from typer.testing import CliRunner

from gaussiantalker.batch import BatchError, Manifest, Record, read_jobs, render_jobs
from gaussiantalker.batch.job_file import MAX_LINE_CHARS
from gaussiantalker.cli.render import render_command
from gaussiantalker.sdk.audio import TARGET_SAMPLE_RATE, load_audio, write_wav

DEMO_SPEECH = Path(__file__).resolve().parents[1] / "samples" / "demo_speech.wav"
SIZE = 128


def decoded(path: Path) -> list[np.ndarray]:
    """Every video frame of a file, as rgb24 arrays."""
    with av.open(str(path)) as container:
        return [frame.to_ndarray(format="rgb24") for frame in container.decode(video=0)]


def write_jobs(path: Path, jobs: list[dict]) -> Path:
    path.write_text("".join(json.dumps(job) + "\n" for job in jobs))
    return path


@pytest.fixture(scope="module")
def speech() -> np.ndarray:
    return load_audio(DEMO_SPEECH)


@pytest.fixture()
def clips(tmp_path, speech, small_export) -> Path:
    """A folder with the bundle and clips of 1, 1.5 and 2 s (relative paths in the job lists resolve here)."""
    folder = tmp_path / "in"
    folder.mkdir()
    os.symlink(small_export.path, folder / "speaker.gtb")
    for name, seconds, start in (("a.wav", 1.0, 0.0), ("b.wav", 1.5, 1.0), ("c.wav", 2.0, 2.5)):
        write_wav(folder / name, speech[int(start * TARGET_SAMPLE_RATE):int((start + seconds) * TARGET_SAMPLE_RATE)])
    return folder


def three_jobs(folder: Path) -> Path:
    return write_jobs(folder / "jobs.jsonl", [
        {"bundle": "speaker.gtb", "audio": name, "out": f"{Path(name).stem}.mkv", "resolution": SIZE}
        for name in ("a.wav", "b.wav", "c.wav")])


def test_every_bad_line_is_named(tmp_path):
    (tmp_path / "speaker.gtb").write_bytes(b"x")
    (tmp_path / "a.wav").write_bytes(b"x")
    good = {"bundle": "speaker.gtb", "audio": "a.wav", "out": "ok.mp4"}
    lines = [json.dumps(good),
             json.dumps({**good, "out": "/abs/x.mp4"}),
             json.dumps({**good, "out": "../up.mp4"}),
             json.dumps({**good, "out": "x.avi"}),
             json.dumps({**good, "out": "ok.mp4"}),
             "",
             json.dumps({**good, "out": "r.mp4", "resolution": [0, 5]}),
             json.dumps({**good, "out": "c.mp4", "composite": "maybe"}),
             json.dumps({**good, "out": "f.mp4", "camera": 1}),
             json.dumps({"bundle": "speaker.gtb", "out": "n.mp4"}),
             json.dumps({**good, "out": "m.mp4", "audio": "missing.wav"}),
             "{not json",
             "[1, 2]",
             json.dumps({"audio": "a.wav", "out": ""}),
             json.dumps({**good, "out": "frames/%05d.png"}),
             json.dumps({**good, "out": "v.webm", "codec": "h264"}),
             json.dumps({**good, "out": "k.mkv", "codec": "ffv1", "crf": 10}),
             json.dumps({**good, "out": "q.mp4", "crf": 52}),
             json.dumps({**good, "out": "o.mp4", "camera": {"yaw": 20, "pitch": 95}}),
             json.dumps({**good, "out": "p.mp4", "camera": [10, 0], "composite": True}),
             json.dumps({**good, "out": "y.mp4", "camera": {"yaw": 30, "roll": 2}}),
             json.dumps({**good, "out": "fine.mkv", "camera": {"yaw": -30}, "codec": "ffv1"})]
    (tmp_path / "jobs.jsonl").write_text("\n".join(lines) + "\n")
    with pytest.raises(BatchError) as caught:
        read_jobs(tmp_path / "jobs.jsonl")
    message = str(caught.value)
    expected = {2: "must stay under", 3: "must stay under", 4: "the suffix picks the container",
                5: "already written by line 1", 7: "sides must be", 8: "composite: expected true or false",
                9: "camera: expected {", 10: "needs audio or motion", 11: "missing.wav is not a file",
                12: "not JSON", 13: "a job is a JSON object", 14: "bundle is missing", 15: "image sequences",
                16: "codec: webm holds vp9, not h264", 17: "crf: ffv1 has no crf", 18: "crf: h264 takes 0..51",
                19: "pitch -89..89", 20: "a composited frame is seen through", 21: "not 'roll'"}
    for line, text in expected.items():
        assert re.search(rf"^line {line}: .*{re.escape(text)}", message, re.M), (line, message)
    assert "line 1:" not in message and "line 6:" not in message
    (tmp_path / "jobs.jsonl").write_text(lines[-1] + "\n")
    fine = read_jobs(tmp_path / "jobs.jsonl")[0]
    assert (fine.camera, fine.composite, fine.codec) == ((-30.0, 0.0), False, "ffv1")  # a camera: the bare head
    assert "line 22:" not in message and "19 bad job line(s)" in message
    assert message.index("line 2:") < message.index("line 12:")
    assert "out: expected a relative file name" in message  # line 14 names both of its problems


def test_csv_jobs_and_bounds(tmp_path):
    (tmp_path / "s.gtb").write_bytes(b"x")
    (tmp_path / "a.wav").write_bytes(b"x")
    (tmp_path / "jobs.csv").write_text("bundle,audio,out,resolution,composite\n"
                                       "s.gtb,a.wav,one.webm,96x64,false\n"
                                       "s.gtb,a.wav,two.mov,,\n"
                                       "s.gtb,a.wav,three.mkv,12x,yes\n")
    with pytest.raises(BatchError, match=r"(?m)^line 4: resolution: expected N or WxH") as caught:
        read_jobs(tmp_path / "jobs.csv")
    assert "1 bad job line" in str(caught.value)
    (tmp_path / "jobs.csv").write_text("bundle,audio,out,resolution,composite\ns.gtb,a.wav,one.webm,96x64,false\n"
                                       "s.gtb,a.wav,two.mov,,\n")
    one, two = read_jobs(tmp_path / "jobs.csv")
    assert (one.bundle, one.resolution, one.composite, one.out) == (tmp_path / "s.gtb", (96, 64), False, "one.webm")
    assert (two.resolution, two.composite, two.line) == (None, None, 3)
    (tmp_path / "long.jsonl").write_text("{}\n" + "x" * (MAX_LINE_CHARS + 1) + "\n")
    with pytest.raises(BatchError, match="line 2: .* characters, more than"):
        read_jobs(tmp_path / "long.jsonl")
    (tmp_path / "jobs.txt").write_text("")
    with pytest.raises(BatchError, match="a job list is .jsonl, .ndjson or .csv"):
        read_jobs(tmp_path / "jobs.txt")
    result = CliRunner().invoke(render_command, [str(tmp_path / "long.jsonl"), "-o", str(tmp_path / "out")])
    assert result.exit_code == 2 and "line 2:" in result.output


def test_manifest_tolerates_a_cut_last_line(tmp_path):
    manifest = Manifest(tmp_path)
    record = Record(out="a.mkv", inputs={"bundle": "0" * 64}, settings="1" * 64, status="ok", output="2" * 64)
    manifest.append(record)
    with open(manifest.path, "ab") as handle:
        handle.write(b'{"out": "b.mkv", "inp')  # a crash mid-append
    again = Manifest(tmp_path)
    assert again.latest == {"a.mkv": record}
    again.append(Record(out="c.mkv", inputs={}, settings="3" * 64, status="failed", reason="bad audio"))
    lines = manifest.path.read_text().splitlines()
    assert len(lines) == 2 and all(json.loads(line) for line in lines)
    assert set(Manifest(tmp_path).latest) == {"a.mkv", "c.mkv"}
    manifest.path.write_text('{"out": "a.mkv"}\nnot a record\n{"out": "b"}\n')
    with pytest.raises(BatchError, match="line 1 is not a batch record"):
        Manifest(tmp_path)


def test_render_resume_force(clips, tmp_path, small_export):
    """3 jobs on 2 workers equal direct write_video renders; a rerun skips them all, a changed clip is redone, a
    deleted output is redone, --force redoes all."""
    from gaussiantalker.runtime import TalkingHead

    jobs, outdir = three_jobs(clips), tmp_path / "out"
    summary = render_jobs(jobs, outdir, workers=2, progress=False)
    assert sorted(summary.done) == ["a.mkv", "b.mkv", "c.mkv"] and not summary.failed and not summary.skipped
    assert summary.video_s == pytest.approx(4.5, abs=0.1)
    with TalkingHead(small_export.path, resolution=(SIZE, SIZE), threads=1) as head:
        for name in ("a", "b", "c"):
            direct = head.write_video(tmp_path / f"direct-{name}.mkv", clips / f"{name}.wav")
            got, want = decoded(outdir / f"{name}.mkv"), decoded(direct)
            assert len(got) == len(want) > 20 and all(np.array_equal(g, w) for g, w in zip(got, want, strict=True))
    assert sorted(p.name for p in outdir.iterdir()) == ["a.mkv", "b.mkv", "c.mkv", "manifest.jsonl"]
    records = [json.loads(line) for line in (outdir / "manifest.jsonl").read_text().splitlines()]
    assert {r["out"]: r["status"] for r in records} == {"a.mkv": "ok", "b.mkv": "ok", "c.mkv": "ok"}
    assert set(records[0]["inputs"]) == {"bundle", "audio"}

    again = render_jobs(jobs, outdir, workers=2, progress=False)
    assert (sorted(again.skipped), again.done) == (["a.mkv", "b.mkv", "c.mkv"], [])

    write_wav(clips / "b.wav", load_audio(clips / "a.wav"))  # b's input changes
    (outdir / "c.mkv").unlink()  # c's output is gone
    changed = render_jobs(jobs, outdir, workers=2, progress=False)
    assert (sorted(changed.done), sorted(changed.skipped)) == (["b.mkv", "c.mkv"], ["a.mkv"])
    assert all(np.array_equal(g, w) for g, w in zip(decoded(outdir / "b.mkv"), decoded(outdir / "a.mkv"),
                                                      strict=True))
    result = CliRunner().invoke(render_command, [str(jobs), "-o", str(outdir), "--workers", "2", "--force",
                                                 "--no-progress"])
    assert result.exit_code == 0, result.output
    assert "3 rendered, 0 already done, 0 failed" in result.output


def test_a_failing_job_is_recorded_and_the_others_finish(clips, tmp_path):
    (clips / "bad.wav").write_bytes(b"RIFF this is not audio")
    write_jobs(clips / "jobs.jsonl", [
        {"bundle": "speaker.gtb", "audio": "a.wav", "out": "a.mkv", "resolution": SIZE},
        {"bundle": "speaker.gtb", "audio": "bad.wav", "out": "sub/bad.mkv", "resolution": SIZE},
        {"bundle": "speaker.gtb", "audio": "b.wav", "out": "b.webm", "resolution": SIZE}])
    outdir = tmp_path / "out"
    (outdir / "sub").mkdir(parents=True)
    (outdir / "sub" / "bad.mkv").write_bytes(b"an output of other inputs")
    result = CliRunner().invoke(render_command, [str(clips / "jobs.jsonl"), "-o", str(outdir), "--workers", "2",
                                                 "--no-progress"])
    assert result.exit_code == 1, result.output
    assert re.search(r"failed: sub/bad.mkv: .*bad.wav", result.output), result.output
    assert "2 rendered, 0 already done, 1 failed" in result.output
    assert sorted(str(p.relative_to(outdir)) for p in outdir.rglob("*") if p.is_file()) == [
        "a.mkv", "b.webm", "manifest.jsonl"]
    record = Manifest(outdir).latest["sub/bad.mkv"]
    assert record.status == "failed" and "\n" not in record.reason and record.output is None


@contextmanager
def killing_the_writer_of(outdir: Path, name: str) -> Iterator[list[tuple[int, bool]]]:
    """While the block runs, SIGKILL the process that writes OUTDIR/name once its partial file appears (the file
    names its pid); yields the list that gets (pid, whether the final file existed just after)."""
    killed: list[tuple[int, bool]] = []
    stop = threading.Event()

    def kill() -> None:
        while not stop.is_set() and not killed:
            for path in outdir.glob(f"*{name}.partial-*") if outdir.is_dir() else ():
                pid = int(re.search(r"partial-(\d+)", path.name).group(1))
                os.kill(pid, signal.SIGKILL)
                time.sleep(0.05)
                killed.append((pid, (outdir / name).exists()))
                break
            time.sleep(0.005)

    killer = threading.Thread(target=kill)
    killer.start()
    try:
        yield killed
    finally:
        stop.set()
        killer.join()


def test_a_killed_worker_leaves_no_final_file_and_the_job_is_retried(clips, tmp_path, speech):
    """A worker SIGKILLed while it writes a long job: nothing under the final name, and the retry on a fresh pool
    completes it (the manifest records the second attempt)."""
    write_wav(clips / "long.wav", speech[:8 * TARGET_SAMPLE_RATE])
    jobs = write_jobs(clips / "jobs.jsonl", [
        {"bundle": "speaker.gtb", "audio": "long.wav", "out": "long.mkv", "resolution": SIZE},
        {"bundle": "speaker.gtb", "audio": "a.wav", "out": "a.mkv", "resolution": SIZE}])
    outdir = tmp_path / "out"
    with killing_the_writer_of(outdir, "long.mkv") as killed:
        summary = render_jobs(jobs, outdir, workers=2, progress=False)
    assert killed and killed[0][1] is False  # killed mid-job, and no final file then
    assert sorted(summary.done) == ["a.mkv", "long.mkv"] and not summary.failed
    assert Manifest(outdir).latest["long.mkv"].attempts == 2
    assert sorted(p.name for p in outdir.iterdir()) == ["a.mkv", "long.mkv", "manifest.jsonl"]
    assert len(decoded(outdir / "long.mkv")) == 200


def decoded_audio(path: Path) -> np.ndarray:
    """Every audio sample of a file (its first channel)."""
    with av.open(str(path)) as container:
        return np.concatenate([frame.to_ndarray()[0] for frame in container.decode(audio=0)])


def hidden_files(outdir: Path) -> list[str]:
    return sorted(str(p.relative_to(outdir)) for p in outdir.rglob(".*"))


def test_split_jobs_equal_unsplit_renders(clips, tmp_path, speech, clip_export):
    """Jobs longer than --segment-s: drives made once, segments on 2 workers, joined. On lossless frames (ffv1,
    and h264 at crf 0) the joined video's frames are the unsplit render's bit for bit, composited ones included
    (each segment composites into the reference frames of its own place in the clip), and the audio decodes to the
    same samples; default h264 joins into a file of every frame and the whole sound."""
    write_wav(clips / "long.wav", speech[:4 * TARGET_SAMPLE_RATE])
    os.symlink(clip_export.path, clips / "clip.gtb")
    jobs = write_jobs(clips / "jobs.jsonl", [
        {"bundle": "speaker.gtb", "audio": "long.wav", "out": "bare.mkv", "resolution": SIZE, "codec": "ffv1"},
        {"bundle": "clip.gtb", "audio": "c.wav", "out": "clip.mp4", "crf": 0},
        {"bundle": "speaker.gtb", "audio": "long.wav", "out": "lossy.mp4", "resolution": SIZE,
         "camera": {"yaw": 25, "pitch": -10}},
        {"bundle": "speaker.gtb", "audio": "a.wav", "out": "short.webm", "resolution": SIZE},
        {"bundle": "speaker.gtb", "audio": "c.wav", "out": "reordered.mkv", "resolution": SIZE, "crf": 0}])
    split = render_jobs(jobs, tmp_path / "split", workers=2, segment_s=0.7, progress=False)
    whole = render_jobs(jobs, tmp_path / "whole", workers=2, segment_s=None, progress=False)
    assert not split.failed and not whole.failed and len(split.done) == 5
    assert split.video_s == pytest.approx(whole.video_s) == pytest.approx(4 + 2 + 4 + 1 + 2, abs=0.2)
    for name in ("bare.mkv", "clip.mp4", "reordered.mkv"):  # h264 in Matroska: B-frames, the first dts unset
        got, want = decoded(tmp_path / "split" / name), decoded(tmp_path / "whole" / name)
        assert len(got) == len(want) >= 50
        assert all(np.array_equal(g, w) for g, w in zip(got, want, strict=True)), name
    assert np.array_equal(decoded_audio(tmp_path / "split" / "clip.mp4"),
                          decoded_audio(tmp_path / "whole" / "clip.mp4"))
    lossy, lossy_whole = tmp_path / "split" / "lossy.mp4", tmp_path / "whole" / "lossy.mp4"
    assert len(decoded(lossy)) == len(decoded(lossy_whole)) == 100
    assert np.array_equal(decoded_audio(lossy), decoded_audio(lossy_whole))
    # the orbited camera shows the head from elsewhere: not the bundle camera's frames
    front = render_jobs(write_jobs(clips / "front.jsonl", [{"bundle": "speaker.gtb", "audio": "long.wav",
                                                            "out": "lossy.mp4", "resolution": SIZE}]),
                        tmp_path / "front", workers=1, segment_s=None, progress=False)
    assert not front.failed
    assert np.abs(decoded(tmp_path / "front" / "lossy.mp4")[50].astype(int) - decoded(lossy)[50]).mean() > 2
    for folder in ("split", "whole"):
        assert hidden_files(tmp_path / folder) == [], folder  # no segment or partial file is left
    records = Manifest(tmp_path / "split").latest
    assert {out: r.status for out, r in records.items()} == dict.fromkeys(
        ["bare.mkv", "clip.mp4", "lossy.mp4", "short.webm", "reordered.mkv"], "ok")
    assert {out: r.segments for out, r in records.items()} == {"bare.mkv": 6, "clip.mp4": 3, "lossy.mp4": 6,
                                                               "short.webm": 2, "reordered.mkv": 3}
    assert {r.segments for r in Manifest(tmp_path / "whole").latest.values()} == {1}
    # the unsplit render is write_video's: one head with the batch's settings writes the same frames
    from gaussiantalker.runtime import TalkingHead

    with TalkingHead(clip_export.path, threads=1) as head:
        direct = head.write_video(tmp_path / "direct.mp4", clips / "c.wav", crf=0)
    assert all(np.array_equal(g, w) for g, w in zip(decoded(direct), decoded(tmp_path / "split" / "clip.mp4"),
                                                      strict=True))


def test_segment_s_and_the_ray_flag(tmp_path):
    from gaussiantalker.cli.render import ray_flag_arguments

    assert ray_flag_arguments(["jobs.jsonl", "--ray", "-o", "out"]) == ["jobs.jsonl", "--ray=-", "-o", "out"]
    assert ray_flag_arguments(["--ray", "jobs.jsonl"]) == ["--ray=-", "jobs.jsonl"]
    assert ray_flag_arguments(["--ray", "10.0.0.5:6379", "j.csv"]) == ["--ray", "10.0.0.5:6379", "j.csv"]
    assert ray_flag_arguments(["--ray", "ray://head:10001"]) == ["--ray", "ray://head:10001"]
    assert ray_flag_arguments(["j.csv", "--ray"]) == ["j.csv", "--ray=-"]
    (tmp_path / "s.gtb").write_bytes(b"x")
    (tmp_path / "a.wav").write_bytes(b"x")
    write_jobs(tmp_path / "jobs.jsonl", [{"bundle": "s.gtb", "audio": "a.wav", "out": "a.mp4"}])
    with pytest.raises(BatchError, match="segment_s must be at least"):
        render_jobs(tmp_path / "jobs.jsonl", tmp_path / "out", segment_s=0.01)
    result = CliRunner().invoke(render_command, [str(tmp_path / "jobs.jsonl"), "-o", str(tmp_path / "out"),
                                                 "--segment-s", "-3"])
    assert result.exit_code == 2 and "segment_s must be at least" in result.output


def test_jobs_are_checked_against_their_bundles_and_one_run_holds_a_folder(clips, tmp_path, clip_export):
    """Before anything renders: a file that is not a bundle, compositing asked of a bundle without a reference clip
    and a motion on a composited head are each named with their line; a second run into a folder that a run holds
    is refused."""
    from gaussiantalker.batch.preflight import one_run_at_a_time

    (clips / "fake.gtb").write_bytes(b"not a bundle")
    os.symlink(clip_export.path, clips / "clip.gtb")
    (clips / "motion.npy").write_bytes(b"x")
    jobs = write_jobs(clips / "jobs.jsonl", [
        {"bundle": "speaker.gtb", "audio": "a.wav", "out": "ok.mp4", "resolution": SIZE},
        {"bundle": "fake.gtb", "audio": "a.wav", "out": "fake.mp4"},
        {"bundle": "speaker.gtb", "audio": "a.wav", "out": "odd.mp4", "composite": True},
        {"bundle": "clip.gtb", "motion": "motion.npy", "out": "clip.mp4"}])
    outdir = tmp_path / "out"
    with pytest.raises(BatchError) as caught:
        render_jobs(jobs, outdir, workers=1, progress=False)
    message = str(caught.value)
    assert "3 bad job line(s)" in message and "line 1:" not in message, message
    assert re.search(r"(?m)^line 2: bundle: .*fake.gtb", message), message
    assert re.search(r"(?m)^line 3: .*reference clip", message), message
    assert re.search(r"(?m)^line 4: a composited head follows the reference clip", message), message
    assert not outdir.exists() or not any(outdir.iterdir())
    good = write_jobs(clips / "good.jsonl", [{"bundle": "speaker.gtb", "audio": "a.wav", "out": "ok.mkv",
                                              "resolution": SIZE}])
    outdir.mkdir(exist_ok=True)
    with one_run_at_a_time(outdir), pytest.raises(BatchError, match="another gt-render is writing"):
        render_jobs(good, outdir, workers=1, progress=False)
    assert render_jobs(good, outdir, workers=1, progress=False).done == ["ok.mkv"]  # free again


def test_fps_samples_the_drives_at_the_videos_frame_times(clips, tmp_path, clip_export):
    """`fps` 50 on the 25 fps small speaker: frame 2k of the bare head is frame k of the 25 fps render bit for bit
    and frame 2k+1 a blend between neighbours (neither of them); a composited frame takes the nearest speaker frame
    with its reference picture (frames repeat); split renders at 50 and 30 fps equal the unsplit ones."""
    os.symlink(clip_export.path, clips / "clip.gtb")
    lossless = {"resolution": SIZE, "codec": "ffv1"}
    jobs = write_jobs(clips / "jobs.jsonl", [
        {"bundle": "speaker.gtb", "audio": "a.wav", "out": "native.mkv", **lossless},
        {"bundle": "speaker.gtb", "audio": "a.wav", "out": "fifty.mkv", "fps": 50, **lossless},
        {"bundle": "speaker.gtb", "audio": "b.wav", "out": "thirty.mkv", "fps": 30, **lossless},
        {"bundle": "clip.gtb", "audio": "a.wav", "out": "clip.mkv", "fps": 50, "codec": "ffv1"}])
    split = render_jobs(jobs, tmp_path / "split", workers=2, segment_s=0.3, progress=False)
    whole = render_jobs(jobs, tmp_path / "whole", workers=2, segment_s=None, progress=False)
    assert not split.failed and not whole.failed
    assert Manifest(tmp_path / "split").latest["fifty.mkv"].segments == 4
    for name in ("fifty.mkv", "thirty.mkv", "clip.mkv"):
        got, want = decoded(tmp_path / "split" / name), decoded(tmp_path / "whole" / name)
        assert len(got) == len(want) and all(np.array_equal(g, w) for g, w in zip(got, want, strict=True)), name
    native, fifty = decoded(tmp_path / "whole" / "native.mkv"), decoded(tmp_path / "whole" / "fifty.mkv")
    assert (len(native), len(fifty), len(decoded(tmp_path / "whole" / "thirty.mkv"))) == (25, 50, 45)
    assert all(np.array_equal(fifty[2 * k], native[k]) for k in range(25))
    between = [k for k in range(24) if not np.array_equal(fifty[2 * k + 1], native[k])
               and not np.array_equal(fifty[2 * k + 1], native[k + 1])]
    assert len(between) >= 20  # the face moves between most frames, and the blend is neither end
    clip = decoded(tmp_path / "whole" / "clip.mkv")
    assert len(clip) == 50 and all(np.array_equal(clip[2 * k + 1], clip[2 * k + 2]) for k in range(24))
    with av.open(str(tmp_path / "whole" / "thirty.mkv")) as container:
        assert container.streams.video[0].average_rate == 30
