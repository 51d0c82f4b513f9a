"""The browser player (web/, docs/web.md) against the Python runtime, in headless Debian chromium.

Fidelity: frames of the web player (onnxruntime-web's wasm backend, WebGL2 on SwiftShader) against TalkingHead's
GL frames (llvmpipe) of the same bundle, drive and camera, at 8 bit. Tolerance: PSNR >= 40 dB (RMS error 2.55
levels). Both sides run the same graphs, the same GLSL and the same draw plan, but not the same float32 maths:
onnxruntime-web's kernels may sum in another order than native onnxruntime's (graph outputs ~1e-7 apart),
SwiftShader rounds exp, division and fused multiply-adds in the shaders its own way, and Gaussians whose depths
come out a few ulps apart may swap order. Each of these moves a few pixels by a level or so (measured: 97-99 dB,
at most 1 level, on these bundles); any real disagreement (a convention, an axis, a missing group of Gaussians,
a wrong drive row) costs far more than 40 dB. The translator rows are held to docs/porting.md's bound for graph
outputs (1e-4 of max(1, max |reference|)).

Rejection: damaged files are refused by the player with the Python reader's message (the file's name for its path).

The browser tests skip without chromium or the player's npm install, except where CI is set: there .ci/browser
installs both, and they fail (tests/ci_tools.py). The rest (generated assets, the CLI's argument checks) always runs.
"""

from __future__ import annotations

import hashlib
import json
import struct
from pathlib import Path

import numpy as np
import pytest
from ci_tools import BROWSER_INSTALL, need, need_chromium
from typer.testing import CliRunner

from gaussiantalker.sdk.bundle import STEADY_STREAM_GRAPH, STREAM_GRAPH, Bundle, BundleWriter
from gaussiantalker.sdk.errors import BundleError
from gaussiantalker.sdk.image import psnr_db
from tools.browser import web_assets
from tools.browser.web_cli import app, parse_size
from tools.browser.web_harness import check_web_player

ROOT = Path(__file__).resolve().parents[1]
MIN_PSNR_DB = 40.0
SIZE = (128, 128)


# -- no browser ----------------------------------------------------------------------------------------------


def test_generated_module_matches_the_shaders_and_constants():
    """web/src/generated.js is what the runtime generates now (shaders/ and the constants have one source)."""
    assert web_assets.stale_message() is None


def test_package_pins_its_dependencies_exactly():
    """onnxruntime-web and fflate, each an exact version that the lockfile holds, and each named in the harness's
    import map (tools/browser/web_harness.py NPM_MODULES)."""
    from tools.browser.web_harness import NPM_MODULES

    package = json.loads((ROOT / "web" / "package.json").read_text())
    lock = json.loads((ROOT / "web" / "package-lock.json").read_text())
    assert set(package["dependencies"]) == set(NPM_MODULES) == {"onnxruntime-web", "fflate"}
    page = (ROOT / "web" / "harness" / "index.html").read_text()
    for name, version in package["dependencies"].items():
        assert version[0].isdigit(), f"{name}: an exact version, not a range"
        assert lock["packages"][f"node_modules/{name}"]["version"] == version, name
        assert NPM_MODULES[name].removeprefix("node_modules/") in page, name


def test_cli_checks_its_arguments_before_starting_a_browser(tmp_path):
    bundle = tmp_path / "x.gtb"
    bundle.write_bytes(b"")
    runner = CliRunner()
    result = runner.invoke(app, ["render", str(bundle), "-o", str(tmp_path / "out")])
    assert result.exit_code == 2 and "exactly one of --audio and --motion" in result.output
    assert parse_size("96x64") == (96, 64) and parse_size("80") == (80, 80)
    result = runner.invoke(app, ["render", str(bundle), "--motion", str(bundle), "--size", "0x9", "-o", str(tmp_path)])
    assert result.exit_code == 2 and "WIDTHxHEIGHT" in result.output
    result = runner.invoke(app, ["render", str(bundle), "--motion", str(bundle), "--graphs", "gpu", "-o", "out"])
    assert result.exit_code == 2 and "--graphs must be auto, wasm or webgpu" in result.output


# -- in the browser ------------------------------------------------------------------------------------------


@pytest.fixture(scope="session")
def player_ready() -> None:
    """Chromium and the player's npm install, checked before any bundle is built (first in each browser test's
    arguments: a skip, or a failure under CI, costs no speaker training)."""
    need_chromium()
    need(check_web_player(), BROWSER_INSTALL)


@pytest.fixture(scope="module")
def page(player_ready):
    """One headless chromium with the player's harness page, for the whole module."""
    from tools.browser.web_harness import WebPlayerPage

    with WebPlayerPage() as page:
        yield page


@pytest.fixture(scope="module")
def speech_wav(tmp_path_factory) -> Path:
    """12 s of the demo speech (16 kHz): 300 frames, so the translator runs two windows with a cross-fade."""
    from gaussiantalker.sdk.audio import load_audio, write_wav

    speech = load_audio(ROOT / "samples" / "demo_speech.wav")
    path = tmp_path_factory.mktemp("web_audio") / "speech12.wav"
    write_wav(path, np.concatenate([speech, speech[: 2 * 16000]]))
    return path


@pytest.fixture(scope="module")
def lam_bundle(tmp_path_factory) -> tuple[Path, Path]:
    """A small synthetic LAM avatar (tests/lam_avatars.py) imported with the built-in voice as `gt-import lam` does
    (so the page also opens its translator and streaming translator graphs) and exported, and a motion file for it.
    Its mesh is subdivided like LAM's and exported with its edge vertices derived in the graph (`midpoints`, what the
    reduced presets do), so the page runs that graph too, its Gaussians in spatial order and its buffers deflated
    (what `compact` does for an ARKit avatar), so the page inflates them."""
    from lam_avatars import AvatarSpec, motion_json, write_avatar_zip

    from gaussiantalker.exporter.export.bundle_export import export_bundle
    from gaussiantalker.exporter.export.presets import ExportSettings
    from gaussiantalker.exporter.imports.sources.lam import import_lam
    from gaussiantalker.exporter.voice.attach import builtin_audio_model

    folder = tmp_path_factory.mktemp("web_lam")
    path = folder / "avatar.gtb"
    speaker = import_lam(write_avatar_zip(folder / "avatar.zip", AvatarSpec(subdivided=True)), progress=False)
    speaker.audio_model = builtin_audio_model(speaker)
    export_bundle(speaker, path, settings=ExportSettings(midpoints=True, spatial_order=True, deflate=True),
                  progress=False)
    entries = Bundle(path).manifest["buffers"]
    assert "deform/midpoint_ends" in entries and any(e.get("compression") == "zlib" for e in entries.values())
    motion = folder / "bsData.json"
    motion.write_text(json.dumps(motion_json()))
    return path, motion


def _python_frames(bundle: Path, indexes: list[int], audio: Path | None = None, motion: Path | None = None,
                   camera=None) -> tuple[list[np.ndarray], np.ndarray]:
    """TalkingHead's GL frames at `indexes` and its drive rows (FLAME from audio: expression then jaw; from a FLAME
    motion: expression, flame_pose, head translation; ARKit: weights)."""
    from gaussiantalker.runtime import TalkingHead

    extra = {"camera": camera} if camera is not None else {}
    with TalkingHead(bundle, resolution=SIZE, renderer="gl", composite=False, **extra) as head:
        drives = list(head.drives(audio) if audio else head.drives(motion=motion))
        frames = [head.render(drives[i]) for i in indexes]
    if audio:
        rows = np.stack([np.concatenate([d.expression, d.flame_pose[6:9]]) for d in drives])
    elif hasattr(drives[0], "flame_pose"):  # a FLAME motion: expression, flame_pose and head translation
        rows = np.stack([np.concatenate([d.expression, d.flame_pose, d.head_translation]) for d in drives])
    else:
        rows = np.stack([d.blendshapes for d in drives])
    return frames, rows


def _check_frames(page, python_frames: list[np.ndarray], indexes: list[int]) -> list[float]:
    scores = []
    for index, reference in zip(indexes, python_frames, strict=True):
        frame, timings = page.render(index)
        assert frame.shape == reference.shape
        scores.append(psnr_db(reference, frame))
        assert scores[-1] >= MIN_PSNR_DB, (index, scores[-1], timings)
    return scores


def test_flame_speaker_from_audio_matches_the_python_runtime(player_ready, page, small_export, speech_wav):
    """The small FLAME speaker: audio decoded and translated in the browser (two windows, a cross-fade), frames
    across the join."""
    indexes = [0, 120, 250, 299]
    info = page.load(small_export.path, size=SIZE)
    assert info["rig"] == "flame" and info["precision"] == "float32" and info["fallback"] is None
    assert page.drive(audio=speech_wav)["frames"] == 300
    python_frames, python_rows = _python_frames(small_export.path, indexes, audio=speech_wav)
    rows = page.drive_rows()
    assert rows.shape == python_rows.shape
    bound = 1e-4 * max(1.0, float(np.abs(python_rows).max()))
    assert float(np.abs(rows - python_rows).max()) <= bound
    _check_frames(page, python_frames, indexes)


def test_a_bundle_with_a_reference_clip_plays_composited(player_ready, page, clip_export):
    """The small speaker with its clip and F: audio's frames composited into the clip in the page (WebCodecs H.264,
    the PNG masks, F in onnxruntime-web) against the Python runtime's composited frames, at the clip's size and
    resized; at least 40 dB (the page converts the pictures' 4:2:0 to RGB itself, up to 3 levels from libswscale,
    and resizes by area averaging, not swscale's filter). Pixels outside every mask's crop are the clip's own."""
    from gaussiantalker.runtime import TalkingHead

    audio = ROOT / "samples" / "demo_speech.wav"
    with TalkingHead(clip_export.path, renderer="gl") as head:
        size = head.frame_size
        frames = list(head.frames(audio))
        indexes = [0, 7, len(frames) - 1]
        expected = [frames[i] for i in indexes]
        pictures = [head.compositor.picture(i)[0] for i in indexes]
    info = page.load(clip_export.path)
    assert info["composited"] and tuple(info["size"]) == size
    assert page.drive(audio=audio)["frames"] == len(frames)
    for index, reference, picture in zip(indexes, expected, pictures, strict=True):
        frame, timings = page.render(index)
        assert frame.shape == reference.shape and "composite" in timings and "reference" in timings
        assert psnr_db(reference, frame) >= MIN_PSNR_DB, (index, psnr_db(reference, frame))
        assert psnr_db(picture, frame) < psnr_db(reference, frame)  # the head is in it, not the clip alone
    with pytest.raises(RuntimeError, match="composited frames are uint8 RGB"):
        page.render(0, output="rgba_float")
    half = (size[0] // 2 // 2 * 2, size[1] // 2 // 2 * 2)
    info = page.load(clip_export.path, size=half)
    assert info["composited"] and tuple(info["size"]) == half
    page.drive(audio=audio)
    with TalkingHead(clip_export.path, renderer="gl", resolution=half) as head:
        reference = list(head.frames(audio))[7]
    frame, _ = page.render(7)
    assert psnr_db(reference, frame) >= MIN_PSNR_DB, psnr_db(reference, frame)
    info = page.load(clip_export.path, size=SIZE, composite=False)
    assert not info["composited"] and tuple(info["size"]) == SIZE
    with pytest.raises(RuntimeError, match="seen through the reference clip's camera"):
        page.load(clip_export.path, camera=head.camera.to_dict())


def test_a_clip_in_groups_of_pictures_with_h264_masks_plays_composited(player_ready, page, clip_export,
                                                                       replay_onnx_exports, tmp_path):
    """The small clip coded as `gt-export --reference-codec crf:23,gop:3,mask-crf:10` (its 4 frames in groups of 3
    and 1, masks as H.264 luma): the page decodes a group at a time, forth and back as the clip plays, and
    composites within MIN_PSNR_DB of the Python runtime's frames (the same bound and reasons as the intra clip's)."""
    from gaussiantalker.exporter.export.bundle_export import export_bundle
    from gaussiantalker.exporter.export.presets import ExportSettings
    from gaussiantalker.runtime import TalkingHead
    from gaussiantalker.sdk.drive import track_row

    replay_onnx_exports(clip_export.protos)
    path = tmp_path / "groups.gtb"
    export_bundle(clip_export.speaker, path, settings=ExportSettings(reference="crf:23,gop:3,mask-crf:10"),
                  progress=False)
    audio = ROOT / "samples" / "demo_speech.wav"
    with TalkingHead(path, renderer="gl") as head:
        assert (head.reference.layout.gop, head.reference.layout.mask_codec) == (3, "h264")
        frames = list(head.frames(audio))
    indexes = [0, 3, 4, 5, 6, 7, 2]  # clip rows 0, 3, 2, 1, 0, 1, 2: both groups, both directions, and a jump back
    assert {track_row(len(head.reference), i) for i in indexes} == {0, 1, 2, 3}
    info = page.load(path)
    assert info["composited"]
    page.drive(audio=audio)
    for index in indexes:
        frame, _ = page.render(index)
        assert psnr_db(frames[index], frame) >= MIN_PSNR_DB, (index, psnr_db(frames[index], frame))


def _stream_reference(bundle: Path, audio: np.ndarray, chunk: int) -> tuple[np.ndarray, dict[str, int]]:
    """What the page's AudioStream (web/src/stream.js) makes of `audio` pushed `chunk` samples at a time, in numpy
    on onnxruntime: the same graph calls (every whole frame committed at once, at most 50 a call, the steady graph
    where the bundle has one and the loudness held; at the end the partial frame and the delay zero-padded), each
    stream row gated over its live window, rig frames at their centres; and how many calls each graph had (the
    rest state's call of silence included)."""
    from gaussiantalker.runtime.stages import open_driver
    from gaussiantalker.runtime.translate import CONTEXT_FRAMES, silence_gain
    from gaussiantalker.runtime.translate_stream import (
        REFRESHED_FRAMES,
        frame_power,
        loudness_moved,
        made_after,
        window_loudness,
    )

    driver = open_driver(bundle)
    spec = driver.stream_spec
    size, delay = spec.frame_samples, spec.delay
    state, pending, committed, rows = spec.rest_state[None], np.zeros(0, np.float32), 0, []
    past = np.zeros(0, np.float32)  # every committed sample
    made = np.zeros(REFRESHED_FRAMES)  # the loudness gate's (`made_after`)
    calls = {STREAM_GRAPH: 1}  # the rest state's call

    def commit(pending, state, committed):
        nonlocal past, made
        while pending.shape[0] >= size:
            count = min(pending.shape[0] // size, 50)
            block = pending[:count * size]
            now = window_loudness(frame_power(np.concatenate([past, block]).reshape(-1, size)))
            refresh = not spec.steady or loudness_moved(now, made)
            made = made_after(made, count, refresh, now)
            out = driver.run_stream(block.reshape(1, count, size), state, count, refresh)
            graph = STREAM_GRAPH if refresh else STEADY_STREAM_GRAPH
            calls[graph] = calls.get(graph, 0) + 1
            state, past = out["state_out"], np.concatenate([past, block])
            for k, row in enumerate(driver.stream_rows(out)[0]):
                j = committed - delay + k
                if j >= 0:
                    lo, hi = (j - CONTEXT_FRAMES) * size, (j + delay + 1) * size
                    window = np.concatenate([np.zeros(max(0, -lo), np.float32), past[max(lo, 0):hi]])
                    rows.append(row * np.float32(silence_gain(window)))
            committed, pending = committed + count, pending[count * size:]
        return pending, state, committed

    for start in range(0, audio.shape[0], chunk):
        pending = np.concatenate([pending, audio[start:start + chunk]])
        pending, state, committed = commit(pending, state, committed)
    tail = np.zeros((-(-pending.shape[0] // size) + delay) * size, np.float32)
    tail[:pending.shape[0]] = pending
    commit(tail, state, committed)
    rig_spf = driver.samples_per_frame
    frames = int(np.ceil(audio.shape[0] / rig_spf - 1e-9))
    if abs(rig_spf - size) < 1e-9:
        return np.stack(rows[:frames]), calls
    table = np.stack([spec.rest_row, *rows])  # row -1 is the rest row
    out = []
    for f in range(frames):
        centre = (f * rig_spf + rig_spf / 2) / size - 0.5
        i = int(np.floor(centre))
        w = np.float32(centre - i)
        left, right = table[i + 1], table[min(i + 2, len(table) - 1)]
        out.append(left * (np.float32(1) - w) + right * w)
    return np.stack(out), calls


@pytest.mark.parametrize("rig", ["flame", "arkit"])
def test_audio_pushed_as_it_arrives_plays_through_the_streaming_translator(player_ready, page, small_export,
                                                                           lam_bundle, speech_wav, rig, tmp_path):
    """Voice pushed in 20 ms chunks through the page's streaming translator (the small speaker's Motion Translator
    at 25 fps; a LAM avatar's built-in voice at 30 fps): frames come while it arrives, the stream's delay behind
    it; the rows are the same graph calls' in Python within 1e-4 relative, the bound of the windowed translator's
    rows (onnxruntime-web's wasm kernels against onnxruntime's, through 100 calls that carry the state: 1.3e-5
    measured), and they follow the whole clip's offline drive."""
    from gaussiantalker.sdk.audio import load_audio, write_wav
    from tools.bench.translator_stream import busiest_r

    bundle = small_export.path if rig == "flame" else lam_bundle[0]
    path = tmp_path / "speech4.wav"
    write_wav(path, load_audio(speech_wav)[:4 * 16000])
    audio = load_audio(path)  # as the page decodes it: 16-bit samples
    info = page.load(bundle, size=SIZE)
    assert info["rig"] == rig
    result = page.stream_drive(path, chunk=320)
    rows = page.drive_rows()
    expected, calls = _stream_reference(bundle, audio, 320)
    # The page ran the same graphs as often: the steady form where the bundle has it (the small speaker's own
    # translator, for most calls), the refreshing form at loudness changes; the voice has no steady form.
    assert result["calls"] == calls, (result["calls"], calls)
    assert (calls.get(STEADY_STREAM_GRAPH, 0) > calls[STREAM_GRAPH]) == (rig == "flame"), calls
    assert result["frames"] == rows.shape[0] == expected.shape[0] == int(np.ceil(4 * info["fps"] - 1e-9))
    assert result["ready"][-1] < result["frames"]  # the last frames wait for end(): their lookahead
    assert result["ready"][-1] >= result["frames"] - (result["delay"] + 2) * info["fps"] / 25
    assert np.abs(rows - expected).max() <= 1e-4 * max(1.0, float(np.abs(expected).max()))
    page.drive(audio=path)
    offline = page.drive_rows()
    r = busiest_r(rows, offline)
    print(f"{rig}: streamed rows against the whole clip's, the ten busiest channels' r {r:.3f}")
    assert r >= 0.9


def test_novel_camera_matches_the_python_runtime(player_ready, page, small_export, speech_wav):
    from gaussiantalker.sdk.camera import Camera

    camera = Camera.from_dict(Bundle(small_export.path).manifest["camera"]).resized(*SIZE)
    target = camera.center + camera.R[2] * float(np.linalg.norm(camera.center))
    novel = camera.orbited(25.0, 10.0, target)
    page.load(small_export.path, size=SIZE, camera=novel.to_dict())
    page.drive(audio=speech_wav)
    python_frames, _ = _python_frames(small_export.path, [40], audio=speech_wav, camera=novel)
    _check_frames(page, python_frames, [40])


def _check_motion(page, bundle: Path, motion: Path, rig: str, frames: int, indexes: list[int]):
    """Load `bundle` (a `rig` speaker), drive it with `motion` (`frames` long): the page's drive rows must be the
    Python runtime's bit for bit and its frames at `indexes` within the bound. Returns (load info, Python frames,
    Python rows)."""
    info = page.load(bundle, size=SIZE)
    assert info["rig"] == rig
    assert page.drive(motion=motion)["frames"] == frames
    python_frames, python_rows = _python_frames(bundle, indexes, motion=motion)
    assert np.array_equal(page.drive_rows(), python_rows)
    _check_frames(page, python_frames, indexes)
    return info, python_frames, python_rows


def test_arkit_avatar_from_a_motion_file_matches_the_python_runtime(player_ready, page, lam_bundle, tmp_path):
    bundle, motion = lam_bundle
    indexes = [0, 3, 11]
    info, python_frames, python_rows = _check_motion(page, bundle, motion, "arkit", 12, indexes)
    flame_motion = tmp_path / "flame_param.npz"
    np.savez(flame_motion, expr=np.zeros((2, 10), np.float32))
    with pytest.raises(Exception, match="an npz motion holds FLAME parameters; this ARKit speaker takes ARKit"):
        page.drive(motion=flame_motion)
    assert page.drive(weights=python_rows, fps=info["fps"])["frames"] == 12  # the same weights given directly
    assert np.array_equal(page.drive_rows(), python_rows)
    _check_frames(page, python_frames[-1:], indexes[-1:])
    page.drive(weights=python_rows[::2], fps=info["fps"] / 2)  # at half the rate: resampled to the speaker's
    assert page.drive_rows().shape == python_rows.shape


@pytest.fixture(scope="module")
def ga_bundle(tmp_path_factory) -> tuple[Path, Path]:
    """A small synthetic GaussianAvatars avatar (tests/gaussian_avatars.py: FLAME's sizes, SH degree 3, 8 tracked
    frames) imported and exported, and its flame_param.npz."""
    from gaussian_avatars import synthetic_flame, write_flame_npz, write_gaussian_avatar

    from gaussiantalker.exporter.export.bundle_export import export_bundle
    from gaussiantalker.exporter.imports.sources.gaussian_avatars import GaussianAvatarsOptions, import_gaussian_avatars

    folder = tmp_path_factory.mktemp("web_ga")
    model = synthetic_flame(0)
    written = write_gaussian_avatar(folder / "avatar", model, n_gaussians=400, frames=8)
    speaker = import_gaussian_avatars(folder / "avatar", write_flame_npz(folder / "flame.npz", model),
                                      GaussianAvatarsOptions(resolution=SIZE[0]))
    path = folder / "avatar.gtb"
    export_bundle(speaker, path, progress=False)
    return path, written["param_path"]


def test_flame_avatar_from_its_tracked_motion_matches_the_python_runtime(player_ready, page, ga_bundle, tmp_path):
    """A GaussianAvatars avatar driven by its flame_param.npz in the page (read by web/src/npz.js), stored and
    deflated: the same drive rows as the Python runtime's, bit for bit, and its frames; the bundle's own motion
    track; a JSON motion refused by name."""
    bundle, params = ga_bundle
    _, _, python_rows = _check_motion(page, bundle, params, "flame", 8, [0, 4, 7])
    with np.load(params) as data:
        compressed = tmp_path / "flame_param_compressed.npz"
        np.savez_compressed(compressed, **{key: data[key] for key in data.files})
    assert page.drive(motion=compressed)["frames"] == 8
    assert np.array_equal(page.drive_rows(), python_rows)
    page.drive()  # the bundle's motion track: the tracked motion the import stored
    assert np.array_equal(page.drive_rows(), python_rows)
    lam_motion = tmp_path / "bsData.json"
    lam_motion.write_text(json.dumps({"frames": [[0.0] * 52]}))
    with pytest.raises(Exception, match="a JSON motion holds ARKit weights; this FLAME speaker takes a FLAME motion"):
        page.drive(motion=lam_motion)


@pytest.fixture(scope="module")
def webgpu_page(player_ready):
    """A second headless chromium offered WebGPU: SwiftShader's software adapter."""
    from tools.browser.web_harness import WEBGPU_FLAGS, WebPlayerPage

    with WebPlayerPage(extra_flags=WEBGPU_FLAGS) as page:
        yield page


def test_graphs_run_on_webgpu_where_asked(player_ready, webgpu_page, page, small_export, speech_wav, tmp_path):
    """graphs 'webgpu' (onnxruntime-web's WebGPU build) on the software adapter: the translator's rows within the
    audio test's 1e-4 of the Python runtime's, and a frame within the fidelity bound; 'auto' keeps to wasm on a
    software adapter; a page without WebGPU refuses 'webgpu' by name. 2 s of audio: SwiftShader runs a graph in
    seconds."""
    from gaussiantalker.sdk.audio import load_audio, write_wav

    short = tmp_path / "speech2.wav"
    write_wav(short, load_audio(speech_wav)[: 2 * 16000])
    info = webgpu_page.load(small_export.path, size=SIZE, settings={"graphs": "webgpu"})
    assert info["graphs"]["name"] == "webgpu" and info["graphs"]["executionProviders"] == ["webgpu", "wasm"]
    assert info["graphs"]["adapter"]["fallback"], info["graphs"]  # headless: SwiftShader's adapter
    assert webgpu_page.drive(audio=short)["frames"] == 50
    python_frames, python_rows = _python_frames(small_export.path, [30], audio=short)
    rows = webgpu_page.drive_rows()
    assert float(np.abs(rows - python_rows).max()) <= 1e-4 * max(1.0, float(np.abs(python_rows).max()))
    _check_frames(webgpu_page, python_frames, [30])
    assert webgpu_page.load(small_export.path, size=SIZE)["graphs"]["name"] == "wasm"  # 'auto', a software adapter
    with pytest.raises(Exception, match="WebGPU is not available in this browser"):
        page.load(small_export.path, size=SIZE, settings={"graphs": "webgpu"})


# -- bundle reading and rejection ----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def tiny_bundle(tmp_path_factory) -> Path:
    """A bundle of one buffer per codec, four sparse ones, one with its mask deflated, codebooks (one sparse, one
    deflated) and a deflated buffer (and a stand-in graph): what the reader checks needs no real graphs."""
    rng = np.random.default_rng(0)
    writer = BundleWriter({"note": "codecs"})
    values = rng.normal(size=(7, 37)).astype(np.float32)
    for codec in ("raw", "fp16", "q16", "q8", "q4"):
        writer.add_buffer(f"values/{codec}", values, codec, chunk=16 if codec.startswith("q") else None)
    writer.add_buffer("values/half", values.astype(np.float16), "q8", chunk=32)
    mostly_zero = np.where(rng.random(values.shape) < 0.8, 0.0, values).astype(np.float32)  # a morph basis's kind
    for codec in ("raw", "fp16", "q8"):
        writer.add_buffer(f"sparse/{codec}", mostly_zero, codec, chunk=16 if codec == "q8" else None, sparse=True)
    runs = np.zeros((9, 2000), np.float32)  # one run per row: the mask is stored deflated (`mask_zlib`)
    for row in range(9):
        start = int(rng.integers(0, 1700))
        runs[row, start: start + 300] = rng.normal(size=300)
    writer.add_buffer("sparse/runs", runs, "q8", chunk=16, sparse=True)
    writer.add_buffer("values/vq", values, "vq", chunk=12)
    writer.add_buffer("values/vq_half", values.astype(np.float16), "vq", chunk=300)  # 9-bit indices
    writer.add_buffer("sparse/vq", mostly_zero, "vq", chunk=5, sparse=True)
    writer.add_buffer("deflated/vq", np.tile(values[:, :4], 200), "vq", chunk=4, compress=True)
    writer.add_buffer("deflated/q8", runs, "q8", chunk=16, compress=True)
    writer.add_buffer("faces", rng.integers(0, 3000, size=(50, 3)).astype(np.int64), "index")
    writer.add_buffer("pose_track", rng.normal(size=(5, 6)).astype(np.float32))
    writer.add_graph("stand_in", b"not an onnx model, never run" * 40, inputs=[], outputs=[])
    path = tmp_path_factory.mktemp("web_bundle") / "tiny.gtb"
    writer.write(path)
    return path


def test_buffers_decode_bit_for_bit_as_in_python(page, tiny_bundle):
    bundle = Bundle(tiny_bundle)
    assert {"deflated/vq", "deflated/q8"} <= {name for name, entry in bundle.manifest["buffers"].items()
                                             if entry.get("compression") == "zlib"}
    for name in bundle.manifest["buffers"]:
        decoded = page.decode(tiny_bundle, name)
        expected = bundle.buffer(name)
        assert decoded.dtype == expected.dtype and decoded.tobytes() == expected.tobytes(), name
    assert page.check(tiny_bundle) is None


def _python_message(path: Path) -> str:
    """The Python reader's refusal, with the file's name for its path (as the player names it)."""
    with pytest.raises(BundleError) as caught:
        Bundle(path).verify_all()
    return f"BundleError: {str(caught.value).replace(str(path), path.name)}"


def _entry_start(path: Path, name: str) -> int:
    bundle = Bundle(path)
    return bundle.payload_start + bundle.manifest["buffers"][name]["offset"]


def test_a_flipped_byte_is_refused_naming_the_entry(page, tiny_bundle, tmp_path):
    data = bytearray(tiny_bundle.read_bytes())
    data[_entry_start(tiny_bundle, "pose_track") + 5] ^= 0x40
    bad = tmp_path / "flipped.gtb"
    bad.write_bytes(bytes(data))
    message = page.check(bad)
    assert message == "BundleError: flipped.gtb: checksum mismatch in buffer 'pose_track' (the file is corrupt)"
    assert message == _python_message(bad)


def test_a_truncated_file_is_refused_naming_the_entry_cut_short(page, tiny_bundle, tmp_path):
    start = _entry_start(tiny_bundle, "faces")
    bad = tmp_path / "cut.gtb"
    bad.write_bytes(tiny_bundle.read_bytes()[: start + 10])
    nbytes = Bundle(tiny_bundle).manifest["buffers"]["faces"]["nbytes"]
    message = page.check(bad)
    assert message == (f"BundleError: cut.gtb: truncated inside buffer 'faces': it needs bytes {start}.."
                       f"{start + nbytes}, the file ends at {start + 10}")
    assert message == _python_message(bad)
    header_only = tmp_path / "header.gtb"
    header_only.write_bytes(tiny_bundle.read_bytes()[:40])
    assert page.check(header_only) == "BundleError: header.gtb: truncated inside the header (40 of 64 bytes)"


def test_a_wrong_magic_is_refused(page, tiny_bundle, tmp_path):
    bad = tmp_path / "magic.gtb"
    bad.write_bytes(b"GTBUNDLX" + tiny_bundle.read_bytes()[8:])
    message = page.check(bad)
    assert message == "BundleError: magic.gtb: not a GaussianTalker bundle (bad magic b'GTBUNDLX')"
    assert message == _python_message(bad)


def test_a_lying_manifest_is_refused(page, tiny_bundle, tmp_path):
    """A manifest whose digest is right but whose buffer claims a huge shape: refused from the manifest alone,
    before anything is allocated; and a manifest whose digest is wrong."""
    data = tiny_bundle.read_bytes()
    length = struct.unpack_from("<Q", data, 16)[0]
    manifest = json.loads(data[64:64 + length])
    manifest["buffers"]["pose_track"]["shape"] = [2**30, 2**20]
    text = json.dumps(manifest, sort_keys=True).encode()
    header = data[:16] + struct.pack("<Q", len(text)) + hashlib.sha256(text).digest() + bytes(8)
    padded = text + bytes(-len(text) % 64)
    bad = tmp_path / "shape.gtb"
    bad.write_bytes(header + padded + data[64 + length + (-length % 64):])
    message = page.check(bad)
    assert message.startswith("BundleError: shape.gtb: buffer 'pose_track' declares dtype float32 shape "
                              "[1073741824, 1048576] (4503599627370496 bytes) but stores 120 bytes")
    assert message == _python_message(bad)
    digest = bytearray(data)
    digest[30] ^= 1
    bad.write_bytes(bytes(digest))
    assert page.check(bad) == "BundleError: shape.gtb: manifest checksum mismatch (corrupt manifest or header)"


# Render settings (docs/precision.md) as the player names them, and as RenderSettings does.
SETTINGS = [
    ({"renderTarget": "float16"}, {"render_target": "float16"}),
    ({"renderTarget": "uint8"}, {"render_target": "uint8"}),
    ({"renderScale": 0.5, "sortKeyBits": 16}, {"render_scale": 0.5, "sort_key_bits": 16}),
    ({"sortInterval": 3}, {"sort_interval": 3}),
]


@pytest.mark.parametrize("web_settings, python_settings", SETTINGS, ids=["float16", "uint8", "scale-16bit", "interval"])
def test_render_settings_match_the_python_runtime(player_ready, page, small_export, speech_wav, web_settings,
                                                   python_settings):
    """The framebuffer tiers, the render scale with 16-bit depth keys and the sort interval, frame for frame (in
    frame order, as a sort interval needs)."""
    from gaussiantalker.runtime import TalkingHead
    from gaussiantalker.sdk.render_settings import RenderSettings

    indexes = [0, 1, 2, 3, 4]
    info = page.load(small_export.path, size=SIZE, settings=web_settings)
    assert info["precision"] == python_settings.get("render_target", "float32")
    page.drive(audio=speech_wav)
    render = RenderSettings(**python_settings)
    with TalkingHead(small_export.path, resolution=SIZE, renderer="gl", render_settings=render) as head:
        drives = list(head.drives(speech_wav))[: len(indexes)]
        python_frames = [head.render(drive) for drive in drives]
    _check_frames(page, python_frames, indexes)


def test_the_page_orbits_and_zooms_as_the_python_camera_does(player_ready, page, small_export):
    """Camera.orbited (yaw about the camera's up axis, then pitch about its right axis, about a target) and a dolly
    toward the target give the Python camera's R and t within 1e-9; the head centre is the median rest-pose
    Gaussian of the Python runtime (`orbited_camera`), within 1e-5 m (float32 means)."""
    from gaussiantalker.runtime import TalkingHead

    page.load(small_export.path, size=SIZE)
    with TalkingHead(small_export.path, resolution=SIZE) as head:
        means = head.frame_renderer.deform(head.driver.drive())["means"]
        centre = np.median(means.astype(np.float64), axis=0)
        camera = head.camera
    assert np.abs(np.array(page.call("window.gtWeb.headCentre()")) - centre).max() < 1e-5
    for yaw, pitch, distance in ((30.0, 0.0, 1.0), (-75.0, 40.0, 0.6), (190.0, -10.0, 2.5)):
        request = {"camera": camera.to_dict(), "yaw": yaw, "pitch": pitch, "target": centre.tolist(),
                   "distance": distance}
        got = page.call(f"window.gtWeb.orbit({json.dumps(request)})")
        orbited = camera.orbited(yaw, pitch, centre)
        eye = centre + distance * (orbited.center - centre)
        assert np.abs(np.array(got["R"]) - orbited.R).max() < 1e-9
        assert np.abs(np.array(got["t"]) + orbited.R @ eye).max() < 1e-9


CANVAS_SUM = ("(() => { const c = document.getElementById('view'); const d = c.getContext('2d')"
              ".getImageData(0, 0, c.width, c.height).data; let sum = 0; for (let i = 0; i < d.length; i++) "
              "sum = (sum * 31 + d[i]) % 1000000007; return sum; })()")


def _sample_page_status(browser, url: str) -> str:
    """Open samples/web/index.html at `url` and wait for its bundle (and drive) to load; its status text."""
    browser.navigate(url)
    browser.evaluate("new Promise((resolve) => { (function poll() { if (window.gtSampleReady) resolve(1); "
                     "else setTimeout(poll, 50); })(); })", timeout=120)
    return browser.evaluate("document.getElementById('status').textContent")


def test_sample_page_plays_a_bundle_with_its_audio(player_ready, small_export, ga_bundle, clip_export):
    """samples/web/index.html: a bundle and a WAV by URL, its audio streamed as it plays (the bundle has a streaming
    translator) and frames drawn on the audio clock (WebAudio allowed to start without a gesture, as a click would);
    a FLAME avatar with its flame_param.npz as the motion, its first frame on the canvas, orbited and zoomed and
    back (the same pixels); a bundle with a reference clip shown composited at the clip's size, not orbited."""
    import time

    from tools.browser.chromium import Chromium
    from tools.browser.web_harness import HarnessServer

    server = HarnessServer(ROOT, {})
    try:
        bundle = server.add("small.gtb", small_export.path)
        audio = server.add("speech.wav", ROOT / "samples" / "demo_speech.wav")
        avatar, params = server.add("avatar.gtb", ga_bundle[0]), server.add("flame_param.npz", ga_bundle[1])
        clip = server.add("clip.gtb", clip_export.path)
        with Chromium(window=(640, 720), extra_flags=("--autoplay-policy=no-user-gesture-required",)) as browser:
            page = f"{server.url}/web/samples/web/index.html"
            status = _sample_page_status(browser, f"{page}?bundle={clip}&audio={audio}")
            assert "composited into its reference clip" in status, status
            camera = "JSON.stringify(window.gtSample.state.player.camera.toDict())"
            before = browser.evaluate(camera)
            browser.evaluate("window.gtSample.look({yaw: 60, distance: 0.7})")  # no orbiting a composited bundle
            assert browser.evaluate(camera) == before
            width, height = browser.evaluate("window.gtSample.state.player.frameSize")
            assert f"{width}x{height} composited" in status and json.loads(before)["width"] == width
            status = _sample_page_status(browser, f"{page}?bundle={avatar}&motion={params}")
            assert status.endswith("ready: 8 frames") and "flame speaker" in status, status
            before = browser.evaluate(CANVAS_SUM)
            browser.evaluate("window.gtSample.look({yaw: 60, distance: 0.7})")  # what a drag and a wheel do
            orbited = browser.evaluate(CANVAS_SUM)
            browser.evaluate("window.gtSample.look({yaw: 0, pitch: 0, distance: 1})")  # a double click
            assert browser.evaluate(CANVAS_SUM) == before != orbited
            status = _sample_page_status(browser, f"{page}?bundle={bundle}&audio={audio}")
            assert status.endswith("ready: 250 frames, translated while they play (streaming)"), status
            browser.evaluate("window.gtSample.play()")
            time.sleep(1.5)
            playing = browser.evaluate("[window.gtSample.state.playing, window.gtSample.state.context.currentTime, "
                                       "window.gtSample.state.drawn]")
            red = browser.evaluate("(() => { const c = document.getElementById('view'); const d = c.getContext('2d')"
                                   ".getImageData(0, 0, c.width, c.height).data; let lo = 255, hi = 0; "
                                   "for (let i = 0; i < d.length; i += 4) { lo = Math.min(lo, d[i]); "
                                   "hi = Math.max(hi, d[i]); } return [lo, hi]; })()")
            browser.evaluate("window.gtSample.stop()")
    finally:
        server.close()
    assert playing[0] and playing[1] > 1.0 and playing[2] >= 1, playing  # frames drawn from the stream
    assert red[0] < 200 < red[1], f"the canvas shows a head over the background (red channel {red})"
