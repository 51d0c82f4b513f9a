"""Shared fixtures, each built once per session (deterministic): a small trained speaker and its fp32 bundle (the
quick run's speaker), the 20k-Gaussian demo speaker and its bundle (the full run's; `speaker_export` gives tests
both), with the ONNX protos torch.onnx made for each, and the helpers that export again without torch.onnx:
`replay_onnx_exports` (the same speaker) and `export_rebound` / `rebind_onnx_exports` (another speaker of the same
architecture: the recorded graphs with that speaker's weights)."""

from __future__ import annotations

import contextlib
import dataclasses
import os
from collections.abc import Iterator, Sequence
from pathlib import Path
from types import SimpleNamespace

import pytest


@pytest.fixture(scope="session")
def demo_speaker(small_speaker):
    """The default demo speaker (20k Gaussians) with the small speaker's trained translator. The translator learns
    from synthetic speech alone, whatever the head, so one training serves both; its default 400 steps (~70 s) are
    checked by test_demo_motion's heavy test and measured by `make_demo_speaker.py` (docs/demo-speaker.md)."""
    from gaussiantalker.exporter.demo.demo_speaker import make_demo_speaker

    speaker, metrics = make_demo_speaker(progress=False, train_steps=0)
    speaker.translator.load_state_dict(small_speaker.translator.state_dict())
    speaker.metrics = {**metrics, **small_speaker.metrics}
    return speaker.eval()


@contextlib.contextmanager
def replaying_onnx_exports(protos: Sequence) -> Iterator[list]:
    """Within the block, export_onnx returns `protos` in order instead of running torch.onnx (the rest of an
    export runs for real). Yields the list of protos not handed out yet."""
    import gaussiantalker.exporter.export.onnx_export as onnx_export_module

    queue = list(protos)

    def replay(*args, **kwargs):
        if not queue:
            raise AssertionError("export_onnx called more often than there are recorded protos")
        return queue.pop(0)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(onnx_export_module, "export_onnx", replay)
        yield queue


def _export_recording(speaker, path, **export_kwargs) -> SimpleNamespace:
    """Export `speaker` to `path` (with `export_kwargs`: a scene, a preset...), keeping the ONNX protos torch.onnx
    made (translator, translator_stream, translator_stream_steady, deform, then inpaint where the speaker has
    F) and the ExportResult (`.result`)."""
    import gaussiantalker.exporter.export.onnx_export as onnx_export_module
    from gaussiantalker.exporter.export.bundle_export import export_bundle

    protos = []
    real_export_onnx = onnx_export_module.export_onnx

    def recording(*args, **kwargs):
        protos.append(real_export_onnx(*args, **kwargs))
        return protos[-1]

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(onnx_export_module, "export_onnx", recording)
        result = export_bundle(speaker, path, progress=False, **export_kwargs)
    return SimpleNamespace(path=path, protos=protos, speaker=speaker, result=result)


def _settle_heap() -> None:
    """Collect garbage now, then move every surviving object out of later garbage collections (gc.freeze).

    Called after the collection phase and after each session export: importing torch and running torch.onnx leave
    ~500k long-lived objects (modules, op registries, dynamo caches), and every full collection rescans all of them
    (~0.15 s each: ~2 s per session during the tests, as much again in pytest's final collections). Objects that
    tests create stay in the normal generations, so their garbage (and unraisable exceptions) is seen as before."""
    import gc

    gc.collect()
    gc.freeze()


def pytest_collection_finish(session):
    _settle_heap()


def pytest_collection_modifyitems(config, items):
    """`heavy` cases (minutes each: the demo speaker's defaults end to end) run only with GT_HEAVY=1; CI and the
    full run skip them, their figures come from the commands their docs name (CONTRIBUTING.md)."""
    if os.environ.get("GT_HEAVY"):
        return
    skip = pytest.mark.skip(reason="heavy: run with GT_HEAVY=1 (CONTRIBUTING.md)")
    for item in items:
        if "heavy" in item.keywords:
            item.add_marker(skip)


# -- rebinding recorded graphs to another speaker's weights ------------------------------------------------------
# torch.onnx makes the same graph for two speakers of one architecture (config, sizes, every non-tensor setting
# of the modules); only the initializers hold their weights, each named after the module's parameter or buffer
# (non-persistent buffers included). So a recorded graph whose initializers are replaced, by name, with another
# speaker's tensors is that speaker's export, in ~0.1 s instead of ~5 s. Anything that would make it not so is
# refused loudly. tests/test_rebinding.py (slow) proves the equality against a real torch.onnx export.


class RebindError(AssertionError):
    """A recorded graph cannot stand for this module (another architecture, or a weight without a name)."""


def graph_modules(speaker) -> list:
    """The modules export_bundle turns into ONNX graphs, in export order: translator, its streaming form and that
    form's steady one, deform."""
    from gaussiantalker.exporter.export.deform_graph import DeformationGraph
    from gaussiantalker.exporter.model.translator_stream import MotionTranslatorStream

    return [speaker.translator, MotionTranslatorStream(speaker.translator),
            MotionTranslatorStream(speaker.translator, call_refresh=0), DeformationGraph(speaker)]


def _plain(value) -> bool:
    """Numbers, strings, None, and tuples/lists/dataclasses made only of them (the settings torch.onnx bakes in)."""
    if value is None or isinstance(value, bool | int | float | str):
        return True
    if isinstance(value, tuple | list):
        return all(_plain(v) for v in value)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return all(_plain(getattr(value, f.name)) for f in dataclasses.fields(value))
    return False


def module_settings(module) -> dict:
    """Every plain non-tensor attribute of `module` and its submodules (config, sizes, ids, the FLAME tree...):
    torch.onnx bakes these into the graph's structure and constants, so they must match for a rebind."""
    return {f"{name}.{attr}": value for name, sub in module.named_modules() for attr, value in vars(sub).items()
            if not attr.startswith("_") and attr != "training" and _plain(value)}


def _rebind_onnx(proto, module, recorded_module):
    """A copy of `proto` (torch.onnx's export of `recorded_module`) with every initializer replaced by the tensor
    of the same name in `module` (parameters and buffers, non-persistent ones included).

    Raises RebindError when the two modules' settings differ, when an initializer of at least
    EXTERNALIZE_MIN_BYTES (a weight: it becomes a bundle buffer) has no tensor of that name in `module`, or when a
    name matches with another shape or dtype. Small unmatched initializers are architecture constants (e.g. the
    identity quaternion torch.onnx lifts out of the code) and are kept."""
    import numpy as np
    import onnx
    from onnx import numpy_helper

    from gaussiantalker.exporter.export.onnx_export import EXTERNALIZE_MIN_BYTES

    settings, recorded_settings = module_settings(module), module_settings(recorded_module)
    if settings != recorded_settings:
        differ = [f"{key} {recorded_settings.get(key, '<missing>')!r} -> {settings.get(key, '<missing>')!r}"
                  for key in sorted(settings.keys() | recorded_settings.keys())
                  if settings.get(key, "<missing>") != recorded_settings.get(key, "<missing>")]
        raise RebindError(f"cannot rebind {type(module).__name__}: settings differ from the recorded module's: "
                          + ", ".join(differ[:8]))
    tensors = dict(module.named_parameters()) | dict(module.named_buffers())
    model = onnx.ModelProto()
    model.CopyFrom(proto)
    for initializer in model.graph.initializer:
        old = numpy_helper.to_array(initializer)
        tensor = tensors.get(initializer.name)
        if tensor is None:
            if old.nbytes >= EXTERNALIZE_MIN_BYTES:
                raise RebindError(f"initializer {initializer.name!r} ({old.dtype}{list(old.shape)}, {old.nbytes} "
                                  f"bytes) has no parameter or buffer of that name in {type(module).__name__}")
            continue
        new = np.ascontiguousarray(tensor.detach().cpu().numpy())
        if new.shape != old.shape or new.dtype != old.dtype:
            raise RebindError(f"initializer {initializer.name!r}: recorded {old.dtype}{list(old.shape)}, "
                              f"{type(module).__name__} has {new.dtype}{list(new.shape)}")
        initializer.CopyFrom(numpy_helper.from_array(new, initializer.name))
    return model


@contextlib.contextmanager
def rebinding_onnx_exports(recorded: SimpleNamespace) -> Iterator[list]:
    """Within the block, export_onnx(module, ...) returns the next recorded graph of `recorded` (a `small_export`-
    like namespace) rebound to `module`'s weights instead of running torch.onnx; so any speaker of the recorded
    speaker's architecture exports (gt-export included). The recorded modules are `recorded.modules` where it has
    them, else `graph_modules(recorded.speaker)`. Yields the list of rebound protos handed out so far."""
    import gaussiantalker.exporter.export.onnx_export as onnx_export_module

    modules = getattr(recorded, "modules", None) or graph_modules(recorded.speaker)
    queue = list(zip(recorded.protos, modules, strict=True))
    handed_out = []

    def rebinding(module, *args, **kwargs):
        if not queue:
            raise AssertionError("export_onnx called more often than there are recorded protos")
        proto, recorded_module = queue.pop(0)
        handed_out.append(_rebind_onnx(proto, module, recorded_module))
        return handed_out[-1]

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(onnx_export_module, "export_onnx", rebinding)
        yield handed_out


@contextlib.contextmanager
def rebinding_the_translator(recorded: SimpleNamespace, deform: bool = False) -> Iterator[None]:
    """Within the block, exporting a translator of the recorded speaker's kind, or its streaming forms with the
    recorded settings (refresh, delay), rebinds its recorded graph (as `rebinding_onnx_exports` does); so does the
    deformation graph with `deform`; every other graph (a short stream's) is exported by torch.onnx."""
    import gaussiantalker.exporter.export.onnx_export as onnx_export_module

    real_export_onnx = onnx_export_module.export_onnx
    recorded_modules = graph_modules(recorded.speaker)[:4 if deform else 3]

    def export(module, *args, **kwargs):
        for proto, recorded_module in zip(recorded.protos, recorded_modules, strict=False):
            if type(module) is type(recorded_module) and all(
                    getattr(module, name, None) == getattr(recorded_module, name, None)
                    for name in ("call_refresh", "delay_frames", "refresh_frames", "tail_frames")):
                return _rebind_onnx(proto, module, recorded_module)
        return real_export_onnx(module, *args, **kwargs)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(onnx_export_module, "export_onnx", export)
        yield


def _export_rebound(speaker, path, recorded: SimpleNamespace, **export_kwargs) -> SimpleNamespace:
    """Export `speaker` to `path` with `recorded`'s graphs (a `small_export`-like namespace of a speaker of the
    same architecture) rebound to its weights; buffers, codecs and writing run for real.
    Returns the same kind of namespace (path, protos, speaker)."""
    from gaussiantalker.exporter.export.bundle_export import export_bundle

    with rebinding_onnx_exports(recorded) as protos:
        export_bundle(speaker, path, progress=export_kwargs.pop("progress", False), **export_kwargs)
    assert len(protos) == len(recorded.protos), f"exported {len(protos)} graphs, not {len(recorded.protos)}"
    return SimpleNamespace(path=path, protos=protos, speaker=speaker)


@pytest.fixture(scope="session")
def export_recording():
    """`export_recording(speaker, path)`: a real export (torch.onnx) that keeps its protos, as the session's."""
    return _export_recording


@pytest.fixture(scope="session")
def rebind_onnx():
    """`rebind_onnx(proto, module, recorded_module)`: a recorded graph with `module`'s weights (see above)."""
    return _rebind_onnx


@pytest.fixture(scope="session")
def export_rebound():
    """`export_rebound(speaker, path, recorded)`: `speaker` exported with `recorded`'s graphs (e.g. `small_export`,
    for a speaker of the same architecture) rebound to its weights; no torch.onnx."""
    return _export_rebound


@pytest.fixture(scope="session")
def demo_export(demo_speaker, tmp_path_factory) -> SimpleNamespace:
    """The demo speaker exported as an fp32 bundle (`.path`) and its ONNX protos (`.protos`)."""
    export = _export_recording(demo_speaker, tmp_path_factory.mktemp("bundle") / "demo.gtb")
    _settle_heap()
    return export


@pytest.fixture(scope="session")
def demo_bundle(demo_export):
    """The demo speaker exported as an fp32 bundle."""
    return demo_export.path


@pytest.fixture(scope="session")
def small_speaker():
    """A 2k-Gaussian demo speaker (seed 3), its translator trained as `make_demo_speaker.py` does (the face follows
    the audio, docs/demo-speaker.md) but for 100 steps instead of 400 (measured: held-out jaw/loudness r 0.994,
    20 of 20 coefficients moving, in a quarter of the time): the quick run's speaker (its torch frames are ~4x
    cheaper than the 20k demo speaker's). No time cap (`seconds_budget`): on a busy machine the 150 s default
    could stop training early and make the speaker depend on the machine's load."""
    from gaussiantalker.exporter.demo.demo_speaker import make_demo_speaker
    from gaussiantalker.exporter.demo.train_translator import TrainSettings, train_demo_translator

    speaker, metrics = make_demo_speaker(n_gaussians=2000, seed=3, train_steps=0, progress=False)
    metrics.update(train_demo_translator(speaker.translator, speaker.config.n_expr, seed=3, progress=False,
                                         seconds_budget=float("inf"), settings=TrainSettings(max_steps=100)))
    assert metrics["heldout_jaw_loudness_corr"] > 0.98, metrics  # the audio tests need a jaw that follows speech
    speaker.metrics = metrics
    return speaker.eval()


@pytest.fixture(scope="session")
def small_export(small_speaker, tmp_path_factory) -> SimpleNamespace:
    """`small_speaker` exported once: `.path` the fp32 bundle, `.protos` its two ONNX graphs as torch.onnx made
    them (translator, deform) for tests that export again without paying for torch.onnx."""
    export = _export_recording(small_speaker, tmp_path_factory.mktemp("small") / "small.gtb")
    _settle_heap()
    return export


@pytest.fixture(scope="session")
def lam_voice_bundle(tmp_path_factory):
    """A small synthetic LAM avatar (tests/lam_avatars.py) imported as `gt-import lam` does by default, the built-in
    voice driver attached (docs/voice.md), exported as an fp32 bundle: an ARKit speaker that audio drives at 30 fps."""
    from lam_avatars import write_avatar_zip

    from gaussiantalker.exporter.export.bundle_export import export_bundle
    from gaussiantalker.exporter.imports.sources.lam import import_lam
    from gaussiantalker.exporter.voice.attach import builtin_audio_model

    folder = tmp_path_factory.mktemp("lam_voice")
    speaker = import_lam(write_avatar_zip(folder / "avatar.zip"), progress=False)
    speaker.audio_model = builtin_audio_model(speaker)
    return export_bundle(speaker, folder / "avatar.gtb", progress=False).path


@pytest.fixture(scope="session")
def ga_voice_bundle(tmp_path_factory):
    """A small synthetic GaussianAvatars avatar (tests/gaussian_avatars.py) with the built-in FLAME voice driver
    fitted on its own FLAME, exported as an fp32 bundle: a FLAME speaker that audio drives at 25 fps."""
    from gaussian_avatars import synthetic_flame, write_flame_npz, write_gaussian_avatar

    from gaussiantalker.exporter.export.bundle_export import export_bundle
    from gaussiantalker.exporter.imports.sources.gaussian_avatars import import_gaussian_avatars
    from gaussiantalker.exporter.voice.attach import builtin_audio_model

    folder = tmp_path_factory.mktemp("ga_voice")
    flame_model = synthetic_flame(0)
    write_gaussian_avatar(folder / "ga", flame_model, n_gaussians=20, frames=2)
    speaker = import_gaussian_avatars(folder / "ga", write_flame_npz(folder / "flame.npz", flame_model))
    speaker.audio_model = builtin_audio_model(speaker)
    return export_bundle(speaker, folder / "avatar.gtb", progress=False).path


@pytest.fixture(scope="session")
def inpaint_export() -> SimpleNamespace:
    """A default-config F (seed 0) with random (non-zero) output weights, so the network's path shows in its
    output, and its ONNX proto as the exporter makes it (`.model`, `.proto`): the session's one torch.onnx export
    of F (~25 s); other tests rebind it to their F's weights or use it as it is."""
    import torch

    from gaussiantalker.exporter.export.inpainter_graph import inpainter_onnx
    from gaussiantalker.exporter.model.inpainter import InpainterNet

    torch.manual_seed(0)
    model = InpainterNet()
    with torch.no_grad():
        torch.nn.init.normal_(model.head.weight, std=0.5)
        torch.nn.init.normal_(model.head.bias, std=0.5)
    model.eval()
    return SimpleNamespace(model=model, proto=inpainter_onnx(model))


@pytest.fixture(scope="session")
def clip_export(small_export, inpaint_export, tmp_path_factory) -> SimpleNamespace:
    """The small speaker with a small demo clip and a random F (tests/clip_speaker.py), saved (`.checkpoint`) and
    exported (`.path`, `.protos`: translator, translator_stream, deform, inpaint): the session's recorded graphs
    rebound to its weights, so no torch.onnx runs (the composited frames' parity checks would catch a graph that is
    not F's)."""
    from clip_speaker import make_clip_speaker

    from gaussiantalker.exporter.export.checkpoint import save_checkpoint

    speaker, composer = make_clip_speaker(small_export.speaker)
    folder = tmp_path_factory.mktemp("clip")
    save_checkpoint(speaker, folder / "clip.ckpt")
    recorded = SimpleNamespace(protos=[*small_export.protos, inpaint_export.proto],
                               modules=[*graph_modules(small_export.speaker), inpaint_export.model])
    protos = _export_rebound(speaker, folder / "clip.gtb", recorded).protos
    return SimpleNamespace(speaker=speaker, composer=composer, checkpoint=folder / "clip.ckpt",
                           path=folder / "clip.gtb", folder=folder, protos=protos)


@pytest.fixture(scope="session")
def small_scene_export(small_speaker, tmp_path_factory) -> SimpleNamespace:
    """The small speaker exported for a 128x128 front scene (`.scene`, `.path`, `.result` the ExportResult with its
    specialisation, `.protos` the graphs torch.onnx made for it)."""
    from gaussiantalker.sdk.scene import Scene

    scene = Scene(width=128, height=128)
    export = _export_recording(small_speaker, tmp_path_factory.mktemp("scene") / "small-front.gtb", scene=scene)
    export.scene = scene
    return export


# Reduced bundles of the small speaker that `reduced_export` makes: the presets, and each reduced translator graph
# precision.
# Those marked True keep the fp32 export's graphs (only buffer codecs or the translator's precision change, which
# happen after torch.onnx), so their exports replay the session's recorded graphs; the others prune or truncate
# the Gaussians, which changes the deformation graph (exported again) but not the translator's (rebound).
REDUCED_EXPORTS = {"balanced": True, "compact": False, "fast": False, "mobile": False, "translator-fp16": True,
               "translator-int8": True}


@pytest.fixture(scope="session")
def short_stream_export(small_export, tmp_path_factory) -> Path:
    """`small_export.speaker` exported with its short stream (`short_stream=True`): the recorded graphs rebound, the
    short stream's two traced."""
    from gaussiantalker.exporter.export.bundle_export import export_bundle

    path = tmp_path_factory.mktemp("short") / "short.gtb"
    with rebinding_the_translator(small_export, deform=True):
        export_bundle(small_export.speaker, path, progress=False, short_stream=True)
    return path


@pytest.fixture(scope="session")
def reduced_export(small_export, tmp_path_factory):
    """`reduced_export(name)`: the path of `small_export.speaker` exported as `name` (a preset, or
    "translator-fp16"/"translator-int8"), made on first use and shared by the session's tests."""
    from gaussiantalker.exporter.export.bundle_export import export_bundle
    from gaussiantalker.exporter.export.presets import ExportSettings

    folder = tmp_path_factory.mktemp("reduced")
    paths = {}

    def export(name: str):
        if name not in paths:
            kwargs = ({"settings": ExportSettings(translator_precision=name.split("-")[1])}
                      if name.startswith("translator-") else {"preset": name})
            replay = (replaying_onnx_exports(small_export.protos) if REDUCED_EXPORTS[name]
                      else rebinding_the_translator(small_export))
            with replay:
                export_bundle(small_export.speaker, folder / f"{name}.gtb", progress=False, **kwargs)
            paths[name] = folder / f"{name}.gtb"
        return paths[name]

    return export


@pytest.fixture(scope="session", params=["small", pytest.param("demo", marks=pytest.mark.slow)])
def speaker_export(request) -> SimpleNamespace:
    """Each speaker with its bundle and protos (`.speaker`, `.path`, `.protos`): the small one in the quick run,
    also the 20k-Gaussian demo speaker (the default `make_demo_speaker.py` builds) in the full run."""
    return request.getfixturevalue(f"{request.param}_export")


@pytest.fixture
def replay_onnx_exports():
    """`replay_onnx_exports(protos)`: the next exports (until the test ends) reuse `protos` (in export order)
    instead of running torch.onnx again; the rest of the export (codecs, bundle writing) runs for real."""
    with contextlib.ExitStack() as stack:
        yield lambda protos: stack.enter_context(replaying_onnx_exports(protos))


@pytest.fixture
def rebind_onnx_exports():
    """`rebind_onnx_exports(recorded)`: the next exports (until the test ends) rebind `recorded`'s graphs to the
    modules they are given (`rebinding_onnx_exports`), e.g. for gt-export on another speaker of that architecture."""
    with contextlib.ExitStack() as stack:
        yield lambda recorded: stack.enter_context(rebinding_onnx_exports(recorded))


# -- stability table --------------------------------------------------------------------------------------------
# Stability tests call `stability.record(area, case, behaviour)` with what they observed (not what they expect):
# `GT_STABILITY_TABLE=docs/stability.md python -m pytest -q tests/test_stability_*.py` writes docs/stability.md.

_STABILITY_ROWS: list[tuple[str, str, str, str]] = []


# The page the table is written into: what it is and the command that regenerates it, then the table.
_STABILITY_HEADER = [
    "# Stability at the extremes",
    "",
    "Extreme drives (expression ±10 σ, jaw/neck/global/eyes to ±π and beyond, head onto and behind the camera),",
    "collapsed and coincident geometry, heads at 1e-3..1e3 scale, degenerate and huge Gaussians, odd cameras (focal",
    "1e-3..1e7 px, 1×1 to 4096², 4096×8, principal point far outside), audio of every layout and rate, a 10-minute",
    "file, damaged bundles and checkpoints, interrupted exports, and every reduced bundle: each case either renders",
    "finite frames on which torch and the runtime agree (bounds stated in each test module's docstring) or both cull",
    "the same Gaussians, or raises the SDK's own error naming the problem and the limit; the GL context keeps",
    "rendering normally afterwards.",
    "",
    "The table below is written by the tests themselves: each row is what a test observed, not what it expects.",
    "This whole page is generated; regenerate it with",
    "",
    "    GT_STABILITY_TABLE=docs/stability.md python -m pytest -q tests/test_stability_*.py",
    "",
]


class StabilityRecorder:
    """Collects (area, case, observed behaviour) rows for the stability table of one test."""

    def __init__(self, test_id: str) -> None:
        self.test_id = test_id

    def record(self, area: str, case: str, behaviour: str) -> None:
        _STABILITY_ROWS.append((area, case, behaviour, self.test_id))


@pytest.fixture
def stability(request) -> StabilityRecorder:
    return StabilityRecorder(request.node.nodeid)


def pytest_sessionfinish(session, exitstatus):
    import os
    from pathlib import Path

    target = os.environ.get("GT_STABILITY_TABLE")
    if not target or not _STABILITY_ROWS:
        return
    rows = sorted(set(_STABILITY_ROWS))
    lines = [*_STABILITY_HEADER,
             f"{len(rows)} cases, recorded by the tests ({'all passed' if exitstatus == 0 else 'NOT all passed'}).",
             "", "| area | case | behaviour | test |", "|---|---|---|---|"]
    for area, case, behaviour, test_id in rows:
        cells = (c.replace("|", "\\|") for c in (area, case, behaviour, test_id.split("::")[0].split("/")[-1]))
        lines.append("| " + " | ".join(cells) + " |")
    Path(target).parent.mkdir(parents=True, exist_ok=True)
    Path(target).write_text("\n".join(lines) + "\n")
