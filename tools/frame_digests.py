#!/usr/bin/env python
"""Frame digests of the GaussianTalker runtime: proof that a refactor renders bit-identical frames.

    python tools/frame_digests.py --work DIR --out digests.json         # build missing bundles into DIR, render, hash
    python tools/frame_digests.py --work DIR --out new.json --no-build  # render only (refuses to build anything)
    python tools/frame_digests.py --compare base.json new.json           # identical / DIFFERENT per configuration

Bundles (and the audio, motions) are built ONCE into DIR, with deterministic seeds, by whatever code is importable
when they are missing (use the baseline venv for that); their sha256 are recorded in DIR/bundles.json and checked on
every later run, so old and new code render the very same files. Building imports the exporter (torch) and the test
helpers (tests/lam_avatars.py, tests/gaussian_avatars.py, tests/clip_speaker.py from --tests-dir); rendering uses
only `gaussiantalker.runtime`'s public names: TalkingHead(...), .frames, .motion_frames, .render_params,
.render_blendshapes (and the settings groups RenderSettings / OutputSettings / BackendSettings): names every version
since the settings groups has (a renamed one warns, docs/embedding.md "Renamed names"), so one script runs on both
sides of a change.

A refactor's check (CONTRIBUTING.md): build the bundles with the version before it (a clone of that commit in a
virtualenv of its own, `--tests-dir CLONE/tests`), render them with both, compare.

Each frame's digest is sha256 of its raw bytes (C order) with its shape and dtype. Digests are only comparable on
the same machine and software stack (GL driver, onnxruntime, MNN, numba, CPU): the JSON records them, and
--compare warns when they differ.
"""

from __future__ import annotations

import argparse
import hashlib
import itertools
import json
import os
import platform
import sys
import time
import traceback
import wave
from pathlib import Path

import numpy as np

SCHEMA = 1
MAX_FRAMES = 6           # frames hashed per streamed configuration (the rest of a stream is not drawn)
AUDIO_RATE = 16_000      # the stored audio's rate (every head resamples it to its own)
AUDIO_SEGMENT = (0.60, 0.84)  # seconds of the synthetic speech used: 0.24 s, 6 frames at 25 fps, 8 at 30 fps
SIZE = (160, 160)        # bare FLAME heads
AVATAR_SIZE = (128, 128)  # LAM and GaussianAvatars heads
DEFAULT_TESTS_DIR = str(Path(__file__).resolve().parents[1] / "tests")  # this checkout's test helpers

# -- bundle building (exporter + test helpers; only when a file is missing) -------------------------------------


def _exporter(name: str, *modules: str):
    """`name` from the first of `modules` (dotted, under gaussiantalker.exporter) this version has: the exporter's
    modules moved between versions, and the bundles are built by whichever version is installed."""
    import importlib

    for module in modules:
        try:
            return getattr(importlib.import_module(f"gaussiantalker.exporter.{module}"), name)
        except ModuleNotFoundError:
            continue
    raise ImportError(f"none of {modules} has {name}")

BUNDLES = {  # key -> file name in DIR
    "small": "small.gtb",            # 2k-Gaussian FLAME demo speaker (seed 3, translator trained 100 steps), fp32
    "small_fast": "small_fast.gtb",  # the same, preset "fast" (pruned, quantised, runtime_defaults in manifest)
    "clip": "clip.gtb",              # the small speaker + 4-frame 96x112 demo clip + random F (tests/clip_speaker.py)
    "clip_balanced": "clip_balanced.gtb",  # the clip speaker, preset "balanced" (quantised, clip at CRF 20)
    "clip_cv": "clip_cv.gtb",        # the clip speaker without F: OpenCV fallback compositing
    "clip_mnn": "clip_mnn.gtb",      # the clip speaker exported with --mnn (MNN graphs beside the ONNX ones)
    "lam_voice": "lam_voice.gtb",    # synthetic LAM avatar (tests/lam_avatars.py), built-in voice attached
    "ga": "ga.gtb",                  # synthetic GaussianAvatars avatar (tests/gaussian_avatars.py), 600 Gaussians
}
INPUTS = {  # key -> file name in DIR (not bundles, but fixed inputs all the same)
    "audio": "speech.npy",          # float32 mono at AUDIO_RATE
    "wav": "speech.wav",            # the same, 16-bit PCM (decoded by the runtime's own audio loader)
    "ga_motion": "ga_avatar/avatar/point_cloud/iteration_30000/flame_param.npz",  # GaussianAvatars' tracked motion
}


def _sha256_file(path: Path) -> str:
    digest = hashlib.sha256()
    with path.open("rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def has_mnn() -> bool:
    import importlib.util

    return importlib.util.find_spec("MNN") is not None


class Builder:
    """Builds each missing file of DIR once (deterministic seeds); shared intermediates are made lazily."""

    def __init__(self, work: Path, tests_dir: Path) -> None:
        self.work = work
        self.tests_dir = tests_dir
        self._small = None
        self._clip = None
        self._protos: dict[str, list] = {}
        self.meta: dict[str, dict] = {}  # per bundle: what the renders need to know (FLAME expression size)

    def _imports(self) -> None:
        if str(self.tests_dir) not in sys.path:
            sys.path.insert(0, str(self.tests_dir))
        import torch

        torch.manual_seed(0)

    # speakers
    def small_speaker(self):
        if self._small is None:
            self._imports()
            make_demo_speaker = _exporter("make_demo_speaker", "demo.demo_speaker", "demo.speaker")
            from gaussiantalker.exporter.demo.train_translator import TrainSettings, train_demo_translator

            print("  building the small speaker (2k Gaussians, seed 3, translator 100 steps)...", flush=True)
            speaker, metrics = make_demo_speaker(n_gaussians=2000, seed=3, train_steps=0, progress=False)
            metrics.update(train_demo_translator(speaker.translator, speaker.config.n_expr, seed=3, progress=False,
                                                 seconds_budget=float("inf"), settings=TrainSettings(max_steps=100)))
            speaker.metrics = metrics
            self._small = speaker.eval()
            for key in ("small", "small_fast", "clip", "clip_balanced", "clip_cv", "clip_mnn"):
                self.meta[key] = {"n_expr": int(speaker.config.n_expr)}
        return self._small

    def clip_speaker(self):
        if self._clip is None:
            self._imports()
            from clip_speaker import make_clip_speaker

            self._clip, _ = make_clip_speaker(self.small_speaker())
        return self._clip

    # export helpers: record torch.onnx's protos once per speaker, replay them for re-exports of the same graphs
    def _export(self, speaker, path: Path, record: str | None = None, replay: str | None = None,
                replay_count: int | None = None, **kwargs) -> None:
        import gaussiantalker.exporter.export.onnx_export as onnx_export_module
        export_bundle = _exporter("export_bundle", "export.bundle_export", "export.export")

        real = onnx_export_module.export_onnx
        if replay is not None:
            queue = list(self._protos[replay][:replay_count])

            def patched(*args, **kw):
                if not queue:
                    raise AssertionError("export_onnx called more often than there are recorded protos")
                return queue.pop(0)
        else:
            recorded = self._protos.setdefault(record, []) if record else None

            def patched(*args, **kw):
                proto = real(*args, **kw)
                if recorded is not None:
                    recorded.append(proto)
                return proto
        onnx_export_module.export_onnx = patched
        try:
            tmp = path.with_name(path.name + ".partial.gtb")
            export_bundle(speaker, tmp, progress=False, **kwargs)
            os.replace(tmp, path)
        finally:
            onnx_export_module.export_onnx = real
        if replay is not None and queue:
            raise AssertionError(f"{len(queue)} recorded protos were not used")

    def _ensure_protos(self, name: str) -> None:
        """The recorded protos of `name`'s plain export (exporting it again into a scratch file if this process has
        not exported it: the bundle may already be in DIR from an earlier run)."""
        if name in self._protos:
            return
        speaker = {"small": self.small_speaker, "clip": self.clip_speaker}[name]()
        scratch = self.work / f".scratch-{name}.gtb"
        self._export(speaker, scratch, record=name)
        scratch.unlink()

    # one builder per file
    def build(self, key: str, path: Path) -> None:
        print(f"  building {key} -> {path}", flush=True)
        getattr(self, f"build_{key}")(path)

    def build_small(self, path: Path) -> None:
        self._export(self.small_speaker(), path, record="small")

    def build_small_fast(self, path: Path) -> None:
        self._export(self.small_speaker(), path, preset="fast")  # pruned: its own torch.onnx graphs

    def build_clip(self, path: Path) -> None:
        self._export(self.clip_speaker(), path, record="clip")

    def build_clip_balanced(self, path: Path) -> None:
        self._ensure_protos("clip")
        self._export(self.clip_speaker(), path, replay="clip", preset="balanced")

    def build_clip_cv(self, path: Path) -> None:
        import copy

        self._ensure_protos("clip")
        speaker = copy.deepcopy(self.clip_speaker())
        speaker.inpaint = None
        self._export(speaker, path, replay="clip", replay_count=2)  # translator, deform

    def build_clip_mnn(self, path: Path) -> None:
        self._ensure_protos("clip")
        self._export(self.clip_speaker(), path, replay="clip", mnn=True)

    def build_lam_voice(self, path: Path) -> None:
        self._imports()
        from lam_avatars import write_avatar_zip

        import_lam = _exporter("import_lam", "imports.sources.lam", "imports.lam")
        from gaussiantalker.exporter.voice.attach import builtin_audio_model

        folder = self.work / "lam_avatar"
        folder.mkdir(exist_ok=True)
        speaker = import_lam(write_avatar_zip(folder / "avatar.zip"), progress=False)
        speaker.audio_model = builtin_audio_model(speaker)
        self._export(speaker, path)

    def build_ga(self, path: Path) -> None:
        self._imports()
        from gaussian_avatars import synthetic_flame, write_flame_npz, write_gaussian_avatar

        modules = ("imports.sources.gaussian_avatars", "imports.gaussian_avatars")
        GaussianAvatarsOptions = _exporter("GaussianAvatarsOptions", *modules)
        import_gaussian_avatars = _exporter("import_gaussian_avatars", *modules)

        folder = self.work / "ga_avatar"
        folder.mkdir(exist_ok=True)
        model = synthetic_flame(0)
        write_flame_npz(folder / "flame.npz", model)
        written = write_gaussian_avatar(folder / "avatar", model, n_gaussians=600, frames=6, seed=0)
        expected = self.work / INPUTS["ga_motion"]
        if Path(written["param_path"]).resolve() != expected.resolve():
            raise AssertionError(f"the avatar's motion is at {written['param_path']}, not {expected}")
        speaker = import_gaussian_avatars(folder / "avatar", folder / "flame.npz",
                                          GaussianAvatarsOptions(resolution=64))
        self.meta["ga"] = {"n_expr": int(speaker.config.n_expr)}
        self._export(speaker, path)

    def build_audio(self, path: Path) -> None:
        from gaussiantalker.exporter.export.speech import synth_speech

        speech = synth_speech(2.0, seed=7, sample_rate=AUDIO_RATE).astype(np.float32)
        start, stop = (round(s * AUDIO_RATE) for s in AUDIO_SEGMENT)
        np.save(path, np.ascontiguousarray(speech[start:stop]))

    def build_wav(self, path: Path) -> None:
        audio = np.load(self.work / INPUTS["audio"])
        pcm = np.clip(np.round(audio * 32767.0), -32768, 32767).astype("<i2")
        with wave.open(str(path), "wb") as out:
            out.setnchannels(1)
            out.setsampwidth(2)
            out.setframerate(AUDIO_RATE)
            out.writeframes(pcm.tobytes())

    def build_ga_motion(self, path: Path) -> None:
        self.build_ga(self.work / BUNDLES["ga"])


def prepare_work(work: Path, tests_dir: Path, allow_build: bool) -> dict:
    """Every bundle and input in `work`, built where missing (if allowed), checked against work/bundles.json."""
    work.mkdir(parents=True, exist_ok=True)
    record_path = work / "bundles.json"
    record = json.loads(record_path.read_text()) if record_path.exists() else {"files": {}}
    wanted = {**{k: v for k, v in INPUTS.items()}, **BUNDLES}
    order = ["audio", "wav", *BUNDLES, "ga_motion"]
    builder = None
    for key in order:
        name = wanted[key]
        path = work / name
        if key == "clip_mnn" and not path.exists() and not has_mnn():
            print(f"  skipping {key}: MNN is not importable", flush=True)
            continue
        if not path.exists():
            if not allow_build:
                raise SystemExit(f"{path} is missing and --no-build was given (build the bundles with the baseline)")
            builder = builder or Builder(work, tests_dir)
            builder.build(key, path)
        digest = _sha256_file(path)
        known = record["files"].get(key)
        if known is not None and known["sha256"] != digest:
            raise SystemExit(f"{path} changed since it was recorded in {record_path} (sha256 {digest} != "
                             f"{known['sha256']}); remove DIR to rebuild everything")
        record["files"][key] = {"file": name, "sha256": digest, "bytes": path.stat().st_size}
    if builder is not None:
        record.setdefault("built_with", environment())
        for key, meta in builder.meta.items():
            record.setdefault("meta", {}).setdefault(key, meta)
    record_path.write_text(json.dumps(record, indent=2, sort_keys=True) + "\n")
    return record


# -- rendering: the public runtime API only -----------------------------------------------------------------------


def environment() -> dict:
    import gaussiantalker.runtime as runtime

    env = {"python": sys.version.split()[0], "platform": platform.platform(), "machine": platform.machine(),
           "cpu_count": os.cpu_count(), "numpy": np.__version__, "runtime_module": runtime.__file__,
           "gaussiantalker": getattr(runtime, "__version__", None)}
    for module in ("onnxruntime", "moderngl", "MNN", "numba", "cv2", "av", "soxr"):
        try:
            imported = __import__(module)
            env[module] = str(getattr(imported, "__version__", None) or getattr(imported, "version", lambda: "?")())
        except Exception as exc:  # noqa: BLE001 - recorded, not fatal
            env[module] = f"unavailable ({type(exc).__name__})"
    try:  # the GL driver the splatter will run on (information only; not a render)
        import moderngl

        ctx = moderngl.create_standalone_context(require=330, **({} if os.environ.get("DISPLAY") else
                                                                {"backend": "egl"}))
        env["gl"] = f"{ctx.info['GL_RENDERER']} | {ctx.info['GL_VERSION']}"
        ctx.release()
    except Exception as exc:  # noqa: BLE001
        env["gl"] = f"unavailable ({type(exc).__name__}: {exc})"
    return env


def frame_digest(frame: np.ndarray) -> dict:
    array = np.ascontiguousarray(frame)
    return {"sha256": hashlib.sha256(array.tobytes()).hexdigest(), "shape": list(array.shape),
            "dtype": array.dtype.str}


def _stream(frames, limit: int = MAX_FRAMES):
    """The first `limit` frames of a frame generator; the generator is closed (its worker threads stopped)."""
    try:
        return [np.array(frame, copy=True) for frame in itertools.islice(frames, limit)]
    finally:
        frames.close()


def _params_frames(head, n_expr: int, output: str = "uint8") -> list[np.ndarray]:
    """Single FLAME frames from explicit parameters: neutral, jaw open + expression, neck/eyes/head pose."""
    expr = np.zeros(n_expr, np.float32)
    expr[:10] = np.linspace(-1.5, 1.5, 10)[:n_expr]
    cases = [
        {},
        {"expression": expr, "jaw_pose": [0.25, 0.0, 0.0]},
        {"expression": -0.5 * expr, "jaw_pose": [0.1, 0.02, -0.01], "neck_pose": [0.05, -0.1, 0.02],
         "eye_pose": [0.0, 0.1, 0.0, 0.0, 0.1, 0.0], "head_rotation": [0.05, 0.3, -0.05],
         "head_translation": [0.01, -0.01, 0.02]},
    ]
    frames = []
    for case in cases:
        frames.append(head.render_params(**case, output=output))
    return frames


def _blendshape_frames(head, output: str = "uint8") -> list[np.ndarray]:
    """Single ARKit frames: rest, a weights dict, a [52] array with a [6] head pose."""
    from gaussiantalker.runtime import ARKIT_BLENDSHAPES, HeadPose

    array = (0.5 + 0.5 * np.sin(np.arange(len(ARKIT_BLENDSHAPES)) * 0.7)).astype(np.float32)
    return [head.render_blendshapes(output=output),
            head.render_blendshapes({"jawOpen": 0.8, "eyeBlinkLeft": 1.0, "mouthSmileLeft": 0.5}, output=output),
            head.render_blendshapes(array, head_pose=np.array([0.1, -0.2, 0.05, 0.01, 0.0, -0.02]), output=output),
            head.render_blendshapes({"browInnerUp": 0.7}, head_pose=HeadPose.make([0.0, 0.3, 0.0], [0.0, 0.0, 0.0]),
                                    output=output)]


def _head_pose_track(count: int = MAX_FRAMES + 2) -> np.ndarray:
    t = np.arange(count, dtype=np.float32)[:, None]
    return np.concatenate([0.05 * np.sin(t * [0.9, 1.3, 0.4]), 0.01 * np.cos(t * [0.7, 0.5, 1.1])], 1).astype(
        np.float32)


def _arkit_motion(count: int = MAX_FRAMES) -> np.ndarray:
    """A [T, 52] ARKit weights motion (deterministic, no randomness)."""
    from gaussiantalker.runtime import ARKIT_BLENDSHAPES

    t = np.arange(count, dtype=np.float32)[:, None]
    k = np.arange(len(ARKIT_BLENDSHAPES), dtype=np.float32)[None]
    return np.clip(0.5 + 0.5 * np.sin(0.8 * t + 0.37 * k), 0.0, 1.0).astype(np.float32)


def configurations(work: Path, record: dict) -> list[dict]:
    """name -> bundle key, TalkingHead keywords, and what to call (a function of the head and the inputs)."""
    from gaussiantalker.runtime import BackendSettings, OutputSettings, RenderSettings

    audio = np.load(work / INPUTS["audio"])
    wav = str(work / INPUTS["wav"])
    ga_motion = str(work / INPUTS["ga_motion"])

    def speech(**kw):
        return lambda head: _stream(head.frames(audio, AUDIO_RATE, **kw))

    def speech_file(**kw):
        return lambda head: _stream(head.frames(wav, **kw))

    def motion(source=None, **kw):
        return lambda head: _stream(head.motion_frames(source, **kw))

    def params(output="uint8"):
        return lambda head, n_expr: _params_frames(head, n_expr, output)

    def blendshapes(output="uint8"):
        return lambda head: _blendshape_frames(head, output)

    c = []

    def add(name, bundle, head_kwargs, call, needs=None):
        c.append({"name": name, "bundle": bundle, "head": head_kwargs, "call": call, "needs": needs})

    s = {"resolution": SIZE}
    # FLAME speaker, bare (no clip): audio -> frames, every output, pipelined or not
    add("flame_bare", "small", s, speech())
    add("flame_bare_nopipe", "small", {**s, "pipeline": False}, speech())
    add("flame_bare_wavfile", "small", s, speech_file())
    add("flame_bare_rgba", "small", s, speech(output="rgba"))
    add("flame_bare_float", "small", s, speech(output="float"))
    add("flame_bare_float_nopipe", "small", {**s, "pipeline": False}, speech(output="float"))
    add("flame_bare_rgba_float", "small", s, speech(output="rgba_float"))
    add("flame_bare_head_pose_array", "small", s, speech(head_pose=_head_pose_track()))
    add("flame_bare_background", "small", {**s, "background": (0.1, 0.2, 0.3)}, speech())
    add("flame_bare_native_size", "small", {}, speech())
    add("flame_bare_threads1", "small", {**s, "threads": 1}, speech())
    add("flame_render_params", "small", s, params())
    add("flame_render_params_float", "small", s, params("float"))
    add("flame_render_params_rgba", "small", s, params("rgba"))
    add("flame_render_params_semantic", "small", s, params("semantic"))
    # knobs (runtime/settings.py, sdk/render_settings.py)
    add("knob_render_scale_0.5", "small", {**s, "render_scale": 0.5}, speech())
    add("knob_render_target_float16", "small", {**s, "render_target": "float16"}, speech())
    add("knob_render_target_uint8", "small", {**s, "render_target": "uint8"}, speech())
    add("knob_sort_interval_3", "small", {**s, "sort_interval": 3}, speech())
    add("knob_sort_interval_3_nopipe", "small", {**s, "sort_interval": 3, "pipeline": False}, speech())
    add("knob_sort_key_bits_16", "small", {**s, "sort_key_bits": 16}, speech())
    add("knob_all", "small", {**s, "render_scale": 0.75, "render_target": "float16", "sort_interval": 2,
                              "sort_key_bits": 16}, speech())
    add("knob_all_rgba", "small", {**s, "render_scale": 0.75, "render_target": "float16", "sort_interval": 2,
                                   "sort_key_bits": 16}, speech(output="rgba"))
    add("knob_early_stop", "small", {**s, "render": RenderSettings(early_stop=(0.5,))}, speech())
    add("knob_groups", "small", {"render": RenderSettings(render_scale=0.5, render_target="uint8", sort_interval=2),
                                 "output": OutputSettings(resolution=(144, 176), background=(0.0, 0.0, 0.0)),
                                 "backend": BackendSettings("onnxruntime", threads=1, shader_target="410")},
        speech())
    add("preset_fast_runtime_defaults", "small_fast", s, speech())
    add("preset_fast_overridden", "small_fast", {**s, "render": RenderSettings()}, speech())
    # shader targets
    add("shader_300es", "small", {**s, "shader_target": "300es"}, speech())
    add("shader_300es_rgba_knobs", "small", {**s, "shader_target": "300es", "render_scale": 0.5,
                                             "render_target": "float16"}, speech(output="rgba"))
    add("shader_410", "small", {**s, "shader_target": "410"}, speech())
    # CPU tile splatter
    add("cpu_bare", "small", {**s, "renderer": "cpu"}, speech())
    add("cpu_bare_nopipe", "small", {**s, "renderer": "cpu", "pipeline": False}, speech())
    add("cpu_bare_rgba", "small", {**s, "renderer": "cpu"}, speech(output="rgba"))
    add("cpu_bare_float", "small", {**s, "renderer": "cpu"}, speech(output="float"))
    add("cpu_knobs", "small", {**s, "renderer": "cpu", "render_scale": 0.5, "sort_interval": 2,
                               "sort_key_bits": 16}, speech())
    add("cpu_render_params", "small", {**s, "renderer": "cpu"}, params())
    # reference clip: compositing (learned F, OpenCV fallback, video-coded clip), and its bare head
    add("clip_composited", "clip", {}, speech())
    add("clip_composited_nopipe", "clip", {"pipeline": False}, speech())
    add("clip_composited_wavfile", "clip", {}, speech_file())
    add("clip_composited_resized", "clip", {"resolution": (144, 168)}, speech())
    add("clip_composited_knobs", "clip", {"render_scale": 0.5, "render_target": "float16", "sort_interval": 2},
        speech())
    add("clip_composited_300es", "clip", {"shader_target": "300es"}, speech())
    add("clip_composited_cpu", "clip", {"renderer": "cpu"}, speech())
    add("clip_composited_opencv", "clip_cv", {}, speech(), needs="cv2")
    add("clip_composited_opencv_nopipe", "clip_cv", {"pipeline": False}, speech(), needs="cv2")
    add("clip_composited_balanced", "clip_balanced", {}, speech())
    add("clip_bare", "clip", {"composite": False}, speech())
    add("clip_bare_rgba", "clip", {"composite": False}, speech(output="rgba"))
    add("clip_bare_sized", "clip", {"composite": False, "resolution": (128, 128)}, speech())
    # MNN graph backend
    add("mnn_composited", "clip_mnn", {"backend": "mnn"}, speech(), needs="MNN")
    add("mnn_composited_nopipe", "clip_mnn", {"backend": "mnn", "pipeline": False}, speech(), needs="MNN")
    add("mnn_bare", "clip_mnn", {"backend": "mnn", "composite": False, "resolution": SIZE}, speech(), needs="MNN")
    add("mnn_bare_rgba", "clip_mnn", {"backend": "mnn", "composite": False, "resolution": SIZE},
        speech(output="rgba"), needs="MNN")
    add("mnn_bare_float", "clip_mnn", {"backend": "mnn", "composite": False, "resolution": SIZE},
        speech(output="float"), needs="MNN")  # MNN's own numbers (its uint8 frames may round like onnxruntime's)
    add("mnn_bundle_onnxruntime", "clip_mnn", {"composite": False, "resolution": SIZE}, speech())
    add("mnn_bundle_onnxruntime_float", "clip_mnn", {"composite": False, "resolution": SIZE}, speech(output="float"))
    # LAM (ARKit) avatar: its motion, an array motion, audio through the built-in voice, single blendshape frames
    a = {"resolution": AVATAR_SIZE}
    add("lam_motion", "lam_voice", a, motion())
    add("lam_motion_nopipe", "lam_voice", {**a, "pipeline": False}, motion())
    add("lam_motion_array", "lam_voice", a, motion(_arkit_motion()))
    add("lam_motion_rgba", "lam_voice", a, motion(output="rgba"))
    add("lam_motion_head_pose", "lam_voice", a, motion(head_pose=_head_pose_track()))
    add("lam_motion_cpu", "lam_voice", {**a, "renderer": "cpu"}, motion())
    add("lam_audio", "lam_voice", a, speech())
    add("lam_audio_nopipe", "lam_voice", {**a, "pipeline": False}, speech())
    add("lam_render_blendshapes", "lam_voice", a, blendshapes())
    add("lam_render_blendshapes_float", "lam_voice", a, blendshapes("float"))
    # GaussianAvatars (FLAME) avatar: its motion, the npz, single frames
    add("ga_motion", "ga", a, motion())
    add("ga_motion_nopipe", "ga", {**a, "pipeline": False}, motion())
    add("ga_motion_npz", "ga", a, motion(ga_motion))
    add("ga_motion_rgba", "ga", a, motion(output="rgba"))
    add("ga_motion_knobs", "ga", {**a, "render_scale": 0.5, "sort_key_bits": 16, "render_target": "float16"},
        motion())
    add("ga_motion_cpu", "ga", {**a, "renderer": "cpu"}, motion())
    add("ga_render_params", "ga", a, params())
    return c


def run_configuration(config: dict, work: Path, record: dict) -> dict:
    from gaussiantalker.runtime import TalkingHead

    bundle = record["files"].get(config["bundle"])
    if bundle is None:
        return {"skipped": f"bundle {config['bundle']!r} is not in {work} (MNN not importable when it was built?)"}
    if config["needs"]:
        import importlib.util

        if importlib.util.find_spec(config["needs"]) is None:
            return {"skipped": f"{config['needs']} is not importable"}
    start = time.perf_counter()
    with TalkingHead(str(work / bundle["file"]), **config["head"]) as head:
        call = config["call"]
        if call.__code__.co_argcount == 2:  # render_params: the FLAME expression size, recorded at build time
            frames = call(head, record["meta"][config["bundle"]]["n_expr"])
        else:
            frames = call(head)
        renderer = getattr(head, "renderer", None)
    seconds = time.perf_counter() - start
    digests = [frame_digest(f) for f in frames]
    return {"bundle": config["bundle"], "bundle_sha256": bundle["sha256"], "renderer": renderer,
            "head": {k: repr(v) for k, v in config["head"].items()}, "frames": digests,
            "digest": hashlib.sha256("".join(d["sha256"] for d in digests).encode()).hexdigest(),
            "seconds": round(seconds, 3)}


def main_render(args) -> int:
    import gaussiantalker.runtime as runtime

    where = str(Path(runtime.__file__).resolve())
    print(f"runtime: {where}", flush=True)
    if args.expect_runtime and not where.startswith(str(Path(args.expect_runtime).resolve()) + os.sep):
        raise SystemExit(f"gaussiantalker.runtime is {where}, not under --expect-runtime {args.expect_runtime}: "
                         "another checkout shadows the one meant (sys.path, .pth files, PYTHONPATH)")
    work = Path(args.work).resolve()
    t0 = time.perf_counter()
    print(f"bundles in {work}", flush=True)
    record = prepare_work(work, Path(args.tests_dir), allow_build=not args.no_build)
    build_seconds = time.perf_counter() - t0
    configs = configurations(work, record)
    if args.only:
        configs = [c for c in configs if any(pattern in c["name"] for pattern in args.only)]
    results, failures = {}, 0
    t1 = time.perf_counter()
    for config in configs:
        try:
            result = run_configuration(config, work, record)
        except Exception as exc:  # noqa: BLE001 - a failing configuration is reported and counted
            failures += 1
            result = {"error": f"{type(exc).__name__}: {exc}", "traceback": traceback.format_exc()}
        results[config["name"]] = result
        if "frames" in result:
            frames = result["frames"]
            print(f"  {config['name']:<34} {len(frames)} x {tuple(frames[0]['shape'])} {frames[0]['dtype']:<4} "
                  f"{result['digest'][:16]}  {result['seconds']:6.2f} s  [{result['renderer']}]", flush=True)
        else:
            why = "SKIPPED: " + result["skipped"] if "skipped" in result else "ERROR: " + result["error"]
            print(f"  {config['name']:<34} {why}", flush=True)
    render_seconds = time.perf_counter() - t1
    out = {"schema": SCHEMA, "environment": environment(), "work": str(work),
           "bundles": {k: v["sha256"] for k, v in record["files"].items()},
           "seconds": {"prepare": round(build_seconds, 1), "render": round(render_seconds, 1)},
           "configurations": results}
    Path(args.out).write_text(json.dumps(out, indent=1, sort_keys=True) + "\n")
    print(f"{len(results)} configurations, {sum(len(r.get('frames', [])) for r in results.values())} frames, "
          f"{failures} errors; prepare {build_seconds:.1f} s, render {render_seconds:.1f} s -> {args.out}")
    return 1 if failures else 0


# -- comparison ----------------------------------------------------------------------------------------------------


def main_compare(a_path: str, b_path: str) -> int:
    a, b = (json.loads(Path(p).read_text()) for p in (a_path, b_path))
    bad = 0
    for key in sorted(set(a["bundles"]) | set(b["bundles"])):
        if a["bundles"].get(key) != b["bundles"].get(key):
            print(f"WARNING: input {key!r} differs between the runs ({a['bundles'].get(key)} vs "
                  f"{b['bundles'].get(key)}): they did not render the same files")
            bad += 1
    env_keys = [k for k in sorted(set(a["environment"]) | set(b["environment"]))
                if k not in ("runtime_module", "gaussiantalker")]
    for key in env_keys:
        if a["environment"].get(key) != b["environment"].get(key):
            loud = key in ("cpu_count", "gl", "onnxruntime", "MNN", "numba", "machine")  # these change the bits
            print(f"{'WARNING' if loud else 'note'}: environment {key} differs: {a['environment'].get(key)!r} vs "
                  f"{b['environment'].get(key)!r}" + (" (digests are only comparable on the same machine and "
                                                       "stack)" if loud else ""))
    print(f"A: {a_path} (runtime {a['environment'].get('runtime_module')})")
    print(f"B: {b_path} (runtime {b['environment'].get('runtime_module')})")
    names = list(a["configurations"]) + [n for n in b["configurations"] if n not in a["configurations"]]
    counts = {"identical": 0, "DIFFERENT": 0, "skipped": 0}
    for name in names:
        ra, rb = a["configurations"].get(name), b["configurations"].get(name)
        if ra is None or rb is None:
            status, detail = "DIFFERENT", f"missing in {'A' if ra is None else 'B'}"
        elif "frames" not in ra or "frames" not in rb:
            sa = ra.get("skipped") or ("ERROR " + ra.get("error", "")) if "frames" not in ra else "rendered"
            sb = rb.get("skipped") or ("ERROR " + rb.get("error", "")) if "frames" not in rb else "rendered"
            if "skipped" in ra and "skipped" in rb:
                status, detail = "skipped", f"both skipped: {ra['skipped']}"
            else:
                status, detail = "DIFFERENT", f"A: {sa[:150]} | B: {sb[:150]}"
        else:
            fa, fb = ra["frames"], rb["frames"]
            differ = sum(x != y for x, y in zip(fa, fb, strict=False)) + abs(len(fa) - len(fb))
            if ra.get("bundle_sha256") != rb.get("bundle_sha256"):
                status, detail = "DIFFERENT", "rendered from different bundle files"
            elif differ:
                shapes = {(tuple(x["shape"]), x["dtype"]) for x in fa} ^ {(tuple(x["shape"]), x["dtype"]) for x in fb}
                status = "DIFFERENT"
                detail = (f"{differ} of {max(len(fa), len(fb))} frames differ"
                          + (f" (shape/dtype {sorted(shapes)})" if shapes else ""))
            else:
                status, detail = "identical", f"{len(fa)} frames"
        counts[status] += 1
        print(f"  {name:<34} {status:<10} {detail}")
    print(f"{counts['identical']} identical, {counts['DIFFERENT']} DIFFERENT, {counts['skipped']} skipped (both)")
    return 1 if counts["DIFFERENT"] or bad else 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--work", help="folder of the bundles (built there if missing, reused if present)")
    parser.add_argument("--out", help="the digests JSON to write")
    parser.add_argument("--no-build", action="store_true", help="refuse to build missing bundles")
    parser.add_argument("--tests-dir", default=DEFAULT_TESTS_DIR,
                        help=f"the baseline's tests/ (helper modules for building; default {DEFAULT_TESTS_DIR})")
    parser.add_argument("--expect-runtime", metavar="DIR",
                        help="abort unless gaussiantalker.runtime is imported from under DIR (e.g. /tmp/base)")
    parser.add_argument("--only", nargs="*", help="render only configurations whose name contains one of these")
    parser.add_argument("--compare", nargs=2, metavar=("A.json", "B.json"), help="compare two digest files")
    args = parser.parse_args(argv)
    if args.compare:
        return main_compare(*args.compare)
    if not (args.work and args.out):
        parser.error("--work and --out are needed (or --compare A B)")
    return main_render(args)


if __name__ == "__main__":
    sys.exit(main())
