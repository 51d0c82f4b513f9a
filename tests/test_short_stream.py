"""A trained translator's short stream (`gt-export --short-stream`; docs/live.md, "A stream for a short lookahead"):
its graphs, the live sessions that ask for it (`stream_delay_ms=80`), and the errors around it.

Tolerances: the graphs are their torch modules within 1e-5 (onnxruntime against torch, as the main stream's); a
session on the short stream at 80 ms of lookahead follows the windowed session at 80 ms as the main stream's session
follows the windowed one (tests/test_translator_stream.py's bounds: r >= 0.85 between them, and against the whole
clip's drives no more than 0.05 below the windowed session's own).
"""

from __future__ import annotations

import copy
import types

import numpy as np
import pytest
import torch
from test_translator_stream import live_rows
from unseen_speech import unseen_speech

from gaussiantalker.exporter.export.bundle_export import export_bundle
from gaussiantalker.exporter.model.translator_stream import STREAM_SHORT_DELAY_FRAMES, MotionTranslatorStream
from gaussiantalker.runtime import LiveError, LiveSession
from gaussiantalker.runtime.stages import open_driver
from gaussiantalker.runtime.translate_stream import REST_FRAMES, StreamJob, run_stream_jobs
from gaussiantalker.sdk.bundle import SHORT_STEADY_STREAM_GRAPH, SHORT_STREAM_GRAPH, STREAM_GRAPHS, Bundle
from gaussiantalker.sdk.errors import BundleError
from tools.bench.translator_stream import busiest_r

FRAME = 640
SHORT = (SHORT_STREAM_GRAPH, SHORT_STEADY_STREAM_GRAPH)


def test_the_short_streams_graphs_are_their_torch_modules(short_stream_export, small_export):
    """Both short graphs are in the bundle beside the main ones, their weights the translator's buffers (stored
    once), and against their torch modules on the state they share (batched, uneven calls, provisional frames);
    a bundle exported without --short-stream has only the main stream."""
    bundle = Bundle(short_stream_export)
    for graph in SHORT:
        assert graph in bundle.graph_names()
        buffers = set(bundle.graph_info(graph)["initializers"].values())
        assert buffers and buffers <= set(bundle.graph_info("translator")["initializers"].values())
    driver = open_driver(short_stream_export)
    main, short = driver.stream_specs
    assert (main.delay, short.delay) == (4, STREAM_SHORT_DELAY_FRAMES) and short.graphs == SHORT and short.steady
    assert short.rest_state.shape[0] < main.rest_state.shape[0]  # a shorter window
    assert len(open_driver(small_export.path).stream_specs) == 1
    assert not set(SHORT) & set(Bundle(small_export.path).graph_names())

    translator = small_export.speaker.translator
    modules = {refresh: MotionTranslatorStream(translator, delay_frames=STREAM_SHORT_DELAY_FRAMES,
                                               call_refresh=None if refresh else 0).eval() for refresh in (True, False)}
    rng = np.random.default_rng(1)
    state = np.zeros((3, modules[True].state_size), np.float32)
    for frames, keep, refresh in ((REST_FRAMES, REST_FRAMES, True), (1, 1, False), (5, 3, True), (2, 0, False),
                                  (1, 1, True), (3, 2, False)):
        audio = (0.1 * rng.standard_normal((3, frames, FRAME))).astype(np.float32)
        out = driver.run_stream(audio, state, keep, refresh, graphs=SHORT)
        with torch.no_grad():
            expected = modules[refresh](torch.from_numpy(audio), torch.from_numpy(state), torch.tensor([float(keep)]))
        for name, value in zip(("expression", "jaw_pose", "state_out"), expected, strict=False):
            assert np.abs(out[name] - value.numpy()).max() < 1e-5, (frames, keep, refresh, name)
        assert int(out["delay_frames"][0]) == STREAM_SHORT_DELAY_FRAMES
        state = out["state_out"]


def _session_rows(driver, audio: np.ndarray, **options) -> tuple[np.ndarray, list[tuple[int, int, tuple | None]]]:
    """A free-running 80 ms session fed `audio` in uneven chunks (`live_rows`): every frame's expression and jaw,
    and each stream call's (frames, committed, graphs)."""
    calls, run_stream = [], driver.run_stream

    def recording(audio, state, keep, refresh=True, graphs=None):
        calls.append((audio.shape[1], keep, graphs))
        return run_stream(audio, state, keep, refresh, graphs=graphs)

    driver.run_stream = recording
    try:
        rows, _ = live_rows(driver, audio, options.pop("streaming", None), lookahead_ms=80, **options)
    finally:
        del driver.run_stream
    return rows, calls


def test_a_session_on_the_short_stream_makes_no_provisional_rows_at_80ms(short_stream_export):
    """At 80 ms of lookahead the main stream (rows 160 ms behind) makes two provisional frames a call; the short
    stream commits every frame it is given, and its drives follow the windowed session's and the whole clip's
    (module docstring's bounds)."""
    driver = open_driver(short_stream_export)
    driver.open_stream()  # the streams' specs read (their own calls) before the calls are recorded
    for audio in unseen_speech()[:2]:
        short, short_calls = _session_rows(driver, audio, stream_delay_ms=80)
        _, main_calls = _session_rows(driver, audio)
        windowed, _ = _session_rows(driver, audio, streaming=False)
        assert short_calls and all(graphs == SHORT for _, _, graphs in short_calls)
        # every call commits all its frames, but the one after the voice's end (its last rows read zeros past it)
        assert [call[:2] for call in short_calls if call[0] != call[1]] == [(STREAM_SHORT_DELAY_FRAMES + 1, 0)]
        assert sum(frames - keep for frames, keep, _ in main_calls) > len(main_calls)  # about two a call
        assert all(graphs is None for _, _, graphs in main_calls)
        offline = np.stack([np.concatenate([drive.expression, np.ravel(drive.flame_pose)])
                            for drive in driver.drives(audio, 16000)])
        count = min(offline.shape[0], short.shape[0], windowed.shape[0])
        live_r = busiest_r(short[:count], windowed[:count])
        short_offline, windowed_offline = (busiest_r(rows[:count], offline[:count]) for rows in (short, windowed))
        print(f"short stream~windowed r {live_r:.3f}; against offline: short {short_offline:.3f}, windowed "
              f"{windowed_offline:.3f}")
        assert live_r >= 0.85 and short_offline >= windowed_offline - 0.05


def test_a_session_asks_for_a_stream_the_bundle_has(short_stream_export, small_export):
    """stream_delay_ms names a stream by its delay: 160 is the main one, 80 the short one; any other, one a bundle
    without --short-stream lacks, or one on a windowed session is a LiveError that says what there is."""
    driver = open_driver(short_stream_export)
    for delay, graphs in ((160, None), (80, SHORT), (None, None)):
        with LiveSession(driver, output=None, stream_delay_ms=delay) as live:
            assert live.stream_spec.graphs == graphs
    with pytest.raises(LiveError, match=r"no stream whose rows lag 120 ms \(its streams: 160 ms, 80 ms\)"):
        LiveSession(driver, output=None, stream_delay_ms=120)
    with pytest.raises(LiveError, match=r"its streams: 160 ms\); .*re-export"):
        LiveSession(open_driver(small_export.path), output=None, stream_delay_ms=80)
    with pytest.raises(LiveError, match="translates windows"):
        LiveSession(driver, output=None, streaming=False, stream_delay_ms=80)
    for bad in (-80, float("nan"), "80"):
        with pytest.raises(LiveError, match="stream_delay_ms must be a finite number"):
            LiveSession(driver, output=None, stream_delay_ms=bad)


def test_a_server_refuses_a_stream_its_bundle_lacks_at_start(short_stream_export):
    """gt-serve --stream-delay-ms names the stream every session runs: one the bundle lacks stops the server
    before it listens, with the delays it has."""
    from gaussiantalker.serve.app import ServeOptions, make_app

    make_app(short_stream_export, ServeOptions(client_render=True, stream_delay_ms=80))
    with pytest.raises(LiveError, match="its streams: 160 ms, 80 ms"):
        make_app(short_stream_export, ServeOptions(client_render=True, stream_delay_ms=40))
    with pytest.raises(LiveError, match="sessions translate windows"):
        make_app(short_stream_export, ServeOptions(client_render=True, streaming=False, stream_delay_ms=80))


def test_jobs_of_two_streams_go_to_their_own_calls():
    """run_stream_jobs stacks a stream's jobs only with the same stream's: two calls for two streams' jobs of one
    shape, each to its stream's graphs (the main one's called as a driver without streams of its own is)."""
    seen = []

    def run(audio, state, keep, refresh, **options):
        seen.append((audio.shape[0], options.get("graphs")))
        return {"rows": np.zeros((audio.shape[0], audio.shape[1], 2), np.float32), "state_out": state.copy()}

    def job(graphs):
        spec = types.SimpleNamespace(graphs=graphs, pads_exactly=False)
        stream = types.SimpleNamespace(spec=spec, state=np.zeros(4, np.float32), state_row=None)
        return StreamJob(stream, np.zeros((1, FRAME), np.float32), 1)

    calls = run_stream_jobs([job(None), job(SHORT), job(None), job(SHORT), job(SHORT)], run, lambda out: out["rows"])
    assert calls == [2, 3] and seen == [(2, None), (3, SHORT)]


def test_only_a_trained_translator_has_a_short_stream(small_speaker, tmp_path):
    """An avatar that a voice or an attached audio model drives has one stream: --short-stream is refused before
    anything is exported."""
    voiceless = copy.deepcopy(small_speaker)  # a copy of its own: the session's speaker keeps its translator
    voiceless.translator = None
    with pytest.raises(BundleError, match="short stream .* is a trained Motion Translator's"):
        export_bundle(voiceless, tmp_path / "x.gtb", progress=False, short_stream=True)
    assert not (tmp_path / "x.gtb").exists() and small_speaker.translator is not None
    assert STREAM_GRAPHS[1] == SHORT
