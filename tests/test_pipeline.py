"""The pipelined frame loops (runtime/pipeline.py, TalkingHead's `pipeline` setting).

Bounds, and why:
* Frames with the pipeline on and off are bit-identical (the same stages run on the same inputs in the same order;
  only the threads differ): bare (GL and the CPU splatter), rgba, composited, an ARKit speaker, a motion, and the
  frames `write_video` encodes (an image sequence, so no codec's threading can blur the comparison).
* Threads: once a consumer stops early, fails, or has read everything, no worker thread of the pipeline is left
  (names start with "gt-"); checked right after the loop ends, no sleeping.
* Memory: a source is never more than `depth` + 1 items ahead of its consumer (the queue plus the item in hand),
  however slowly the consumer reads.
* Whole frames at once (the CPU splatter's `frames_at_once`): forced to 3 workers as well, so a machine with fewer
  cores still runs that path; the same bits as one frame after another.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np
import pytest

from gaussiantalker.runtime.pipeline import Ahead, Sink, in_order
from gaussiantalker.sdk.errors import SettingsError

PIPELINE_THREADS = ("gt-prepare", "gt-composite", "gt-encode", "gt-ahead", "gt-stage", "gt-sink", "gt-frame",
                    "gt-picture")


def pipeline_threads() -> list[str]:
    return [t.name for t in threading.enumerate() if t.name.startswith(PIPELINE_THREADS) and t.is_alive()]


# -- the pieces ------------------------------------------------------------------------------------------------

def test_ahead_yields_the_source_in_order_and_ends_its_thread():
    with Ahead(iter(range(50)), depth=3) as ahead:
        assert list(ahead) == list(range(50))
        assert not ahead.alive
    assert pipeline_threads() == []


def test_ahead_stays_bounded_behind_a_slow_consumer():
    produced = []

    def source():
        for i in range(40):
            produced.append(i)
            yield i

    with Ahead(source(), depth=2) as ahead:
        for consumed, item in enumerate(ahead):
            time.sleep(0.002)
            assert item == consumed
            assert len(produced) - (consumed + 1) <= 2 + 1, (len(produced), consumed)


def test_ahead_raises_the_sources_exception_in_the_consumer():
    error = ValueError("frame 3 has a bad pose")

    def source():
        yield from range(3)
        raise error

    ahead = Ahead(source(), depth=2)
    got = []
    with pytest.raises(ValueError, match="frame 3 has a bad pose") as caught:
        for item in ahead:
            got.append(item)
    assert caught.value is error and got == [0, 1, 2]
    assert not ahead.alive and pipeline_threads() == []


def test_ahead_closed_early_stops_the_worker_and_closes_the_source():
    closed = threading.Event()

    def source():
        try:
            yield from range(10_000)
        finally:
            closed.set()

    ahead = Ahead(source(), depth=2)
    assert next(ahead) == 0
    ahead.close()
    assert not ahead.alive and closed.is_set() and pipeline_threads() == []
    with pytest.raises(StopIteration):
        next(ahead)


def test_in_order_keeps_the_order_and_raises_the_functions_exception():
    def slow_square(x):
        time.sleep(0.001 * (x % 3))
        return x * x

    assert list(in_order(slow_square, ((i,) for i in range(20)), depth=2)) == [i * i for i in range(20)]

    def fails_at_5(x):
        if x == 5:
            raise RuntimeError("composite failed at 5")
        return x

    got = []
    with pytest.raises(RuntimeError, match="composite failed at 5"):
        for value in in_order(fails_at_5, ((i,) for i in range(20)), depth=1):
            got.append(value)
    assert got == list(range(5)) and pipeline_threads() == []


def test_in_order_on_several_workers_keeps_the_order_and_delivers_what_came_before_a_source_error():
    started: list[str] = []

    def begin():
        started.append(threading.current_thread().name)

    def slow_square(x):
        time.sleep(0.002 * (3 - x % 3))  # later items often finish first
        return x * x, threading.current_thread().name

    results = list(in_order(slow_square, ((i,) for i in range(30)), depth=5, workers=3, initializer=begin))
    assert [value for value, _ in results] == [i * i for i in range(30)]
    assert len({name for _, name in results}) > 1 and len(started) == len(set(started)) <= 3
    assert pipeline_threads() == []

    def drives():
        yield from ((i,) for i in range(4))
        raise ValueError("no drive for frame 4")

    got = []
    with pytest.raises(ValueError, match="no drive for frame 4"):
        for value, _ in in_order(slow_square, drives(), depth=5, workers=3):
            got.append(value)
    assert got == [0, 1, 4, 9] and pipeline_threads() == []
    with pytest.raises(ValueError, match="workers must be >= 1"):
        list(in_order(slow_square, [(1,)], workers=0))


def test_in_order_closed_early_ends_its_thread():
    results = in_order(lambda x: x, ((i,) for i in range(100)), depth=1)
    assert next(results) == 0
    results.close()
    assert pipeline_threads() == []


def test_sink_writes_in_order_bounded_and_surfaces_errors():
    written, queued_max = [], []
    with Sink(written.append, depth=2) as sink:
        for i in range(30):
            sink.put(i)
            queued_max.append(i + 1 - len(written))
    assert written == list(range(30)) and max(queued_max) <= 2 + 1 and pipeline_threads() == []

    def fails_at_4(x):
        if x == 4:
            raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        with Sink(fails_at_4, depth=2) as sink:
            for i in range(50):
                sink.put(i)
                time.sleep(0.001)
    assert pipeline_threads() == []


def test_the_pipeline_setting():
    from gaussiantalker.runtime import BackendSettings
    from gaussiantalker.runtime.settings import merged_backend

    assert BackendSettings().pipeline is None
    assert merged_backend("onnxruntime", pipeline=False).pipeline is False
    assert merged_backend(BackendSettings("onnxruntime", threads=2), pipeline=False).pipeline is False
    assert merged_backend(BackendSettings(pipeline=False), pipeline=False).pipeline is False
    with pytest.raises(SettingsError, match="pipeline given twice"):
        merged_backend(BackendSettings(pipeline=True), pipeline=False)
    with pytest.raises(SettingsError, match="pipeline must be True, False or None"):
        BackendSettings(pipeline="no")


# -- TalkingHead's frames, on and off ---------------------------------------------------------------------------

def _speech(seconds: float = 0.5):
    from gaussiantalker.exporter.export.speech import synth_speech

    return synth_speech(seconds, seed=5)


def _frames(path, call, **settings) -> dict[bool, list[np.ndarray]]:
    from gaussiantalker.runtime import TalkingHead

    frames = {}
    for pipeline in (False, True):
        with TalkingHead(path, pipeline=pipeline, **settings) as head:
            assert (head.backend_settings.pipeline is not False) is pipeline
            frames[pipeline] = list(call(head))
        assert pipeline_threads() == []
    return frames


def _assert_identical(frames: dict[bool, list[np.ndarray]]) -> None:
    assert len(frames[True]) == len(frames[False]) > 0
    for on, off in zip(frames[True], frames[False], strict=True):
        assert on.dtype == off.dtype and on.shape == off.shape
        assert np.array_equal(on, off)


@pytest.mark.parametrize("renderer", ["gl", "cpu"])
@pytest.mark.parametrize("output", ["uint8", "rgba"])
def test_bare_frames_are_the_same_pipelined_or_not(small_export, renderer, output):
    if renderer == "cpu":
        pytest.importorskip("numba", reason="the cpu extra is not installed")
    speech = _speech()
    _assert_identical(_frames(small_export.path, lambda head: head.frames(speech, 16000, output=output),
                              resolution=(48, 40), renderer=renderer))


@pytest.mark.parametrize("composite", [False, True])
def test_whole_frames_at_once_are_the_frames_made_one_after_another(clip_export, monkeypatch, composite):
    """Three frames made at once on worker threads (more than this machine may have cores: the path runs anyway),
    bare and composited, against the serial loop."""
    pytest.importorskip("numba", reason="the cpu extra is not installed")
    from gaussiantalker.runtime import TalkingHead
    from gaussiantalker.runtime.frame_renderer import FrameRenderer

    speech = _speech()
    with TalkingHead(clip_export.path, renderer="cpu", pipeline=False, composite=composite) as head:
        serial = list(head.frames(speech, 16000))
    monkeypatch.setattr(FrameRenderer, "frames_at_once", lambda self: 3)
    with TalkingHead(clip_export.path, renderer="cpu", composite=composite) as head:
        at_once = list(head.frames(speech, 16000))
    assert pipeline_threads() == []
    _assert_identical({True: at_once, False: serial})


def test_who_makes_whole_frames_at_once(small_export):
    numba = pytest.importorskip("numba", reason="the cpu extra is not installed")
    from gaussiantalker.runtime import TalkingHead
    from gaussiantalker.runtime.splat.cpu import MAX_FRAMES_AT_ONCE, CPUSplatter
    from gaussiantalker.sdk.render_settings import RenderSettings

    cores = min(numba.get_num_threads(), MAX_FRAMES_AT_ONCE)
    assert CPUSplatter().frames_at_once() == cores
    assert CPUSplatter(threads=2).frames_at_once() == 1  # the app chose the kernels' threads for each frame
    assert CPUSplatter(settings=RenderSettings(sort_interval=2)).frames_at_once() == 1  # the sort keeps state
    with TalkingHead(small_export.path, renderer="gl", resolution=(32, 32)) as head:
        assert head.frame_renderer.frames_at_once() == 1  # a GL context is bound to its thread

    class OwnSplatter:  # an app's splatter that does not say how many frames it can draw at once
        def __init__(self, inner):
            self.settings, self.inner = inner.settings, inner

    from gaussiantalker.runtime.frame_renderer import FrameRenderer

    with TalkingHead(small_export.path, renderer="cpu", resolution=(32, 32)) as head:
        assert head.frame_renderer.frames_at_once() == cores
        own = FrameRenderer(head.frame_renderer.graphs, OwnSplatter(head.frame_renderer.splatter),
                            head.frame_renderer.camera, head.frame_renderer.background, rig=head.frame_renderer.rig)
        assert own.frames_at_once() == 1
        own.begin_worker()  # nothing to set up

    splatter, seen = CPUSplatter(), {}

    def worker():
        splatter.begin_worker()
        seen["threads"] = numba.get_num_threads()
        seen["timings"] = splatter.last_timings

    thread = threading.Thread(target=worker)
    thread.start()
    thread.join()
    assert seen["threads"] == 1 and numba.get_num_threads() == numba.config.NUMBA_NUM_THREADS  # per thread
    assert seen["timings"]["draw"] == 0.0  # a thread that has drawn nothing has no timings of another's


def test_composited_frames_are_the_same_pipelined_or_not(clip_export):
    speech = _speech()
    frames = _frames(clip_export.path, lambda head: head.frames(speech, 16000))
    _assert_identical(frames)


def test_arkit_frames_and_motions_are_the_same_pipelined_or_not(lam_voice_bundle):
    speech = _speech()
    _assert_identical(_frames(lam_voice_bundle, lambda head: head.frames(speech, 16000), resolution=(40, 40)))
    weights = np.linspace(0.0, 1.0, 6 * 52, dtype=np.float32).reshape(6, 52)
    _assert_identical(_frames(lam_voice_bundle, lambda head: head.frames(motion=weights), resolution=(40, 40)))


def test_written_frames_are_the_same_pipelined_or_not(small_export, tmp_path):
    from PIL import Image

    from gaussiantalker.runtime import TalkingHead

    def read_png(path):
        with Image.open(path) as picture:
            return np.asarray(picture.convert("RGB"))

    speech = _speech()
    written = {}
    for pipeline in (False, True):
        seen = []
        with TalkingHead(small_export.path, resolution=(32, 24), pipeline=pipeline) as head:
            folder = tmp_path / f"pipeline-{pipeline}"
            folder.mkdir()
            head.write_video(folder / "%05d.png", speech, 16000, on_frame=seen.append)
        assert pipeline_threads() == []
        pictures = sorted(folder.glob("*.png"))
        assert len(pictures) == len(seen) > 0
        written[pipeline] = [read_png(p) for p in pictures]
        for picture, frame in zip(written[pipeline], seen, strict=True):
            assert np.array_equal(picture, frame)
    _assert_identical(written)


def test_a_consumer_that_stops_early_leaves_no_thread(small_export, clip_export):
    from gaussiantalker.runtime import TalkingHead

    speech = _speech(1.0)
    for path, settings in ((small_export.path, {"resolution": (32, 32)}), (clip_export.path, {})):
        with TalkingHead(path, **settings) as head:
            frames = head.frames(speech, 16000)
            next(frames)
            next(frames)
            frames.close()
            assert pipeline_threads() == []
            for index, _ in enumerate(head.frames(speech, 16000)):  # a loop left by break
                if index == 1:
                    break
    assert pipeline_threads() == []


def test_an_error_in_a_stage_reaches_the_consumer(small_export, clip_export, monkeypatch):
    from gaussiantalker.runtime import TalkingHead
    from gaussiantalker.sdk.drive import HeadPose

    def pose(index):
        if index == 3:
            raise ValueError("no pose for frame 3")
        return HeadPose.make()

    speech = _speech(1.0)
    with TalkingHead(small_export.path, resolution=(32, 32)) as head:
        got = []
        with pytest.raises(ValueError, match="no pose for frame 3"):
            for frame in head.frames(speech, 16000, head_pose=pose):
                got.append(frame)
        assert len(got) == 3 and pipeline_threads() == []

    with TalkingHead(clip_export.path) as head:
        def failing_composite(*args):
            raise RuntimeError("F failed")

        monkeypatch.setattr(head.compositor, "blend", failing_composite)  # the stage on the composite thread
        with pytest.raises(RuntimeError, match="F failed"):
            list(head.frames(speech, 16000))
        assert pipeline_threads() == []


def test_an_encoder_error_reaches_write_video(small_export, tmp_path, monkeypatch):
    from gaussiantalker.runtime import TalkingHead
    from gaussiantalker.sdk import video

    calls = []

    def failing_write(self, frame):
        calls.append(1)
        raise OSError("No space left on device")

    monkeypatch.setattr(video.VideoWriter, "write", failing_write)
    with TalkingHead(small_export.path, resolution=(32, 32)) as head:
        with pytest.raises(OSError, match="No space left on device"):
            head.write_video(tmp_path / "talk.mp4", _speech(3.0), 16000)  # frames still to come when it fails
    assert calls == [1] and pipeline_threads() == [] and not (tmp_path / "talk.mp4").exists()


def test_the_bench_report_gives_medians_and_ratios_to_on():
    """`gt-bench pipeline`'s summary: per case and variant the median over rounds, RTF and the ratio to "on"."""
    from tools.bench.pipeline_vs_serial import format_report, summarise

    stages = {"deformation": 5.0, "draw": 20.0}
    runs = {"frames": {v: [{"seconds": s, "frames": 100, "stages_ms": stages, "load_1min": 1.0} for s in seconds]
                       for v, seconds in (("off", (6.0, 5.0, 7.0)), ("on", (4.0, 3.0, 5.0)))},
            "play": {v: [{"seconds": s, "load_1min": 2.0} for s in seconds]
                     for v, seconds in (("off", (9.0, 8.0)), ("on", (4.0, 5.0)))}}
    summary = summarise(runs, audio_s=2.0)
    assert summary["frames"]["off"]["seconds"] == 6.0 and summary["frames"]["on"]["seconds"] == 4.0
    assert summary["frames"]["off"]["ratio_to_on"] == pytest.approx(1.5)
    assert summary["frames"]["on"]["rtf"] == pytest.approx(2.0)
    assert summary["frames"]["on"]["ms_per_frame"] == pytest.approx(40.0)
    assert summary["play"]["off"]["ratio_to_on"] == pytest.approx(8.5 / 4.5)
    report = format_report({"runs": runs, "summary": summary, "audio_s": 2.0, "rounds": 3,
                            "versions": {"on": "this", "off": "this"}}, {"cpu": "x86_64", "cores": 2}, "gt-bench x")
    assert "| frames | off | 6.00 | 3.00 | 60.0 | 1.50 |" in report and "min 1.00, max 2.00" in report


def test_bench_versions_find_their_samples(tmp_path):
    """The version benches run each checkout's own samples/play.py: found above src/gaussiantalker/ in this
    src-layout checkout, and beside the packages in a checkout from before that layout."""
    from tools.bench.compare import PACKAGES, checkout_root, checkout_top, this_version_root

    repo = Path(__file__).resolve().parents[1]
    assert (checkout_top(checkout_root(repo)) / "samples" / "play.py").is_file()
    assert (checkout_top(this_version_root()) / "samples" / "play.py").is_file()
    flat = tmp_path / "old"
    for name in (*PACKAGES, "samples"):
        (flat / name).mkdir(parents=True)
    assert checkout_top(checkout_root(flat)) == flat.resolve()
