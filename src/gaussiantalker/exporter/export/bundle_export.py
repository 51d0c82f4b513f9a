"""torch Speaker -> `.gtb` bundle: the translator and deformation graphs plus every buffer they need."""

from __future__ import annotations

import difflib
import os
import platform
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import onnx
import torch
from tqdm import tqdm

from gaussiantalker.sdk import __version__ as sdk_version
from gaussiantalker.sdk.bundle import FLAME_DRIVER, STREAM_GRAPH, STREAM_GRAPHS, BundleWriter
from gaussiantalker.sdk.config import POSE_DIM
from gaussiantalker.sdk.errors import BundleError
from gaussiantalker.sdk.files import StagedFile
from gaussiantalker.sdk.numerics import ALPHA_MIN
from gaussiantalker.sdk.progress import progress_bar
from gaussiantalker.sdk.reference_clip import CROP_MARGIN_PX, CROP_MULTIPLE, ReferenceClipError, frame_entry, mask_entry
from gaussiantalker.sdk.scene import Scene

from ..model.arkit_speaker import ArkitSpeaker
from ..model.speaker import Speaker
from ..model.translator_stream import STREAM_DELAYS
from . import onnx_export
from .arkit_graph import ARKIT_DEFORM_INPUTS, ArkitDeformationGraph, arkit_deform_example
from .deform_graph import DeformationGraph
from .graph_precision import convert_precision
from .inpainter_graph import inpainter_onnx
from .mnn_export import add_mnn_graphs, mnn_version
from .onnx_export import add_graph
from .presets import ExportSettings, Preset, get_preset, group_of, parse_reference
from .prune import apply_budget
from .refit import refit_kept
from .spatial_order import in_spatial_order
from .specialise import Specialisation, specialise
from .translator_graph import translator_onnx, translator_stream_onnx
from .voice_stream import stream_model_of

DEFORM_INPUTS = ["expression", "flame_pose", "head_translation", "camera_center"]
DEFORM_OUTPUTS = ["means", "cov3d", "rgb", "opacity"]


@dataclass
class ExportResult:
    """What an export wrote: path, size, and per-graph / per-buffer byte counts."""

    path: Path
    bytes_written: int
    graphs: dict = field(default_factory=dict)
    buffer_bytes: dict = field(default_factory=dict)
    settings: ExportSettings | None = None
    label: str = "fp32"  # the manifest's "precision": fp32, fp16, a preset's name, NAME+custom or custom
    gaussians: int = 0  # Gaussians in the bundle (after scene pruning and a Gaussian budget)
    specialisation: Specialisation | None = None  # what a scene let the export leave out (export/specialise.py)
    mnn: dict = field(default_factory=dict)  # bytes of each graph's .mnn model (`mnn=True`, docs/mnn.md)

    @property
    def reference_bytes(self) -> int:
        """Stored bytes of the reference clip's frames and masks (0: no clip in the bundle)."""
        return sum(nbytes for name, nbytes in self.buffer_bytes.items() if name.startswith("reference/"))

    @property
    def tier(self) -> str:
        """The former name of `label`, kept for callers that read it."""
        return self.label

    def group_bytes(self) -> dict[str, int]:
        """Stored bytes per codec group (exporter/export/presets.py) plus 'other' (pose track, index buffers, ...)."""
        totals: dict[str, int] = {}
        for name, nbytes in self.buffer_bytes.items():
            group = group_of(name)
            totals[group] = totals.get(group, 0) + nbytes
        return totals


def _deform_example(speaker: Speaker) -> tuple[tuple, dict]:
    batch = 2
    args = (torch.zeros(batch, speaker.config.n_expr), torch.zeros(batch, POSE_DIM), torch.zeros(batch, 3),
            torch.zeros(batch, 3))
    dim = torch.export.Dim("batch", min=1, max=4096)
    return args, {name: {0: dim} for name in DEFORM_INPUTS}


def resolve_settings(codec: str | None = None, settings: ExportSettings | None = None,
                     preset: str | Preset | None = None, rig: str = "flame"
                     ) -> tuple[ExportSettings, Preset | None, str]:
    """(settings, preset, label) of an export: explicit `settings` (over a preset's, whose name and runtime
    defaults are kept), a preset's own for a speaker of `rig` ("flame" or "arkit"), every buffer with one `codec`,
    or fp32."""
    if codec is not None and (settings is not None or preset is not None):
        raise BundleError("give codec (every buffer's codec) or settings/preset, not both")
    chosen = get_preset(preset) if isinstance(preset, str) else preset
    if codec is not None:
        settings = ExportSettings.all_buffers(codec)  # an unknown codec fails here, before any graph export
    settings = settings or (chosen.export_for(rig) if chosen is not None else ExportSettings())
    if chosen is None:
        return settings, None, settings.label()
    return settings, chosen, chosen.name if settings == chosen.export_for(rig) else f"{chosen.name}+custom"


def rig_of(speaker: Speaker | ArkitSpeaker) -> str:
    """The kind of rig a speaker has, as presets name it: "arkit" or "flame"."""
    return "arkit" if isinstance(speaker, ArkitSpeaker) else "flame"


def export_bundle(speaker: Speaker, path: str | os.PathLike | StagedFile, *, codec: str | None = None,
                  settings: ExportSettings | None = None, preset: str | Preset | None = None, progress: bool = True,
                  example_frames: int = 8, scene: Scene | Specialisation | None = None, mnn: bool = False,
                  short_stream: bool = False) -> ExportResult:
    """Export `speaker` to one bundle file at `path` (written atomically), or into a file staged by `atomic_path`.

    The speed/accuracy knobs (exporter/export/presets.py, docs/precision.md): `preset` names a preset (its runtime
    defaults are stored in the bundle), `codec` stores every buffer with one codec, `settings` sets each knob. `scene`
    (docs/scene.md) compiles the bundle for one scene, leaving out what it never uses (or an already measured
    `specialise` result for it); the bundle records the scene and its camera. `mnn` also stores every graph as
    an MNN model (docs/mnn.md; needs the `mnn` extra). `short_stream` also exports a trained translator's short
    stream, for live sessions with under 160 ms of lookahead (docs/live.md, "A stream for a short lookahead")."""
    rig = rig_of(speaker)
    settings, chosen, label = resolve_settings(codec, settings, preset, rig)
    runtime, runtime_by_renderer = chosen.stored_runtime(rig) if chosen is not None else (None, {})
    # the buffer codecs the caller asked for (a preset's own may name arrays a small avatar keeps inside its graph)
    own = dict(chosen.export_for(rig).buffer_codecs) if chosen is not None else {}
    asked = tuple(name for name, codec in settings.buffer_codecs if own.get(name) != codec)
    if isinstance(speaker, ArkitSpeaker) and scene is not None:
        raise BundleError("scene specialisation (--scene) is for FLAME speakers; an ARKit speaker's bundle is "
                          "exported without one (docs/import.md)")
    if not isinstance(speaker, ArkitSpeaker) and speaker.translator is None and scene is not None:
        raise BundleError("scene specialisation (--scene) needs the speaker's trained translator; an imported avatar's "
                          "bundle is exported without one (docs/import.md)")
    if short_stream and (isinstance(speaker, ArkitSpeaker) or speaker.translator is None):
        raise BundleError("a short stream (--short-stream) is a trained Motion Translator's; this speaker drives "
                          "through a voice or an attached audio model, whose one stream live sessions run")
    if mnn:
        mnn_version()  # a missing converter fails here, before any graph is exported
    speaker = speaker.eval()
    spec = (specialise(speaker, scene, progress=progress, sh_degree_cap=settings.sh_degree)
            if isinstance(scene, Scene) else scene)
    camera, background = speaker.camera, list(speaker.background)
    if spec is not None:
        speaker, camera = spec.speaker, spec.camera
        background = list(spec.scene.background_color or background)
    if settings.gaussian_budget is not None:
        full = speaker
        speaker = apply_budget(speaker, settings.gaussian_budget, progress=progress)
        if settings.refit_steps and speaker is not full:  # fitted as the CPU splatter will draw the bundle
            alpha_min = chosen.runtime_for("cpu", rig).alpha_min if chosen is not None else ALPHA_MIN
            speaker = refit_kept(full, speaker, settings.refit_steps, alpha_min=alpha_min, progress=progress)
    if settings.spatial_order:
        speaker = in_spatial_order(speaker, midpoints=settings.midpoints)
    writer = BundleWriter(metadata={
        **({"rig": speaker.config.to_dict()} if isinstance(speaker, ArkitSpeaker)
           else {"speaker": speaker.config.to_dict()}),
        **({"source": speaker.source} if speaker.source else {}),
        "camera": camera.to_dict(),
        "background": background,
        "precision": label,
        "export_settings": asdict(settings),
        "runtime_defaults": runtime.to_dict() if chosen is not None else {},
        **({"runtime_defaults_by_renderer": {name: settings.to_dict() for name, settings in
                                             runtime_by_renderer.items()}} if runtime_by_renderer else {}),
        "gaussians": speaker.gaussians.count,
        "exporter": {"sdk": sdk_version, "torch": torch.__version__, "python": platform.python_version()},
        **({} if spec is None else {"scene": spec.scene.to_dict(),
                                    "specialisation": [asdict(r) for r in spec.removals]}),
    })
    writer.deflate = settings.deflate
    # A scene fixes its own camera and background: the reference clip (seen through another camera) is left out;
    # the manifest's `reference` layout is written with the clip's entries (`_add_reference`).
    if spec is None and getattr(speaker, "reference", None) is not None:
        writer.metadata["inpaint"] = {"generator": "learned" if speaker.inpaint is not None else "opencv_fallback",
                                      "crop_margin": CROP_MARGIN_PX, "crop_multiple": CROP_MULTIPLE}
    steps = progress_bar(total=5 if mnn else 4, desc="gt-export", unit="step", disable=not progress)
    result = ExportResult(path.path if isinstance(path, StagedFile) else Path(path), 0, settings=settings, label=label,
                          gaussians=speaker.gaussians.count, specialisation=spec)
    try:
        _export_steps(speaker, writer, path, result, settings, example_frames, steps, spec, mnn, asked,
                      short_stream)
    finally:
        steps.close()
    return result


def _export_steps(speaker: Speaker, writer: BundleWriter, path: str | os.PathLike | StagedFile, result: ExportResult,
                  settings: ExportSettings, example_frames: int, steps: tqdm, spec: Specialisation | None,
                  mnn: bool, asked: tuple[str, ...] = (), short_stream: bool = False) -> None:
    """Both graphs into `writer` (and their MNN models), then one atomic write: nothing reaches `result.path`
    until every step worked. A flame-driven scene has no translator graph."""
    if isinstance(speaker, ArkitSpeaker):
        _export_arkit_steps(speaker, writer, path, result, settings, steps, mnn, asked)
        return
    steps.set_postfix_str("translator graph")
    if speaker.translator is None:  # an imported avatar: its attached audio-to-FLAME model, if any
        _add_audio_model(speaker, writer, result, settings)
        if speaker.audio_model is None:
            writer.metadata["driver"] = FLAME_DRIVER
    elif spec is None or spec.has_translator:
        model = convert_precision(translator_onnx(speaker.translator, example_frames), settings.translator_precision)
        result.graphs["translator"] = add_graph(writer, "translator", model, settings.codec_for)
        streams = list(zip(STREAM_GRAPHS, STREAM_DELAYS, strict=True))
        for (refreshing, steady), delay in streams if short_stream else streams[:1]:
            _add_stream(writer, result, settings, translator_stream_onnx(speaker.translator, delay_frames=delay),
                        refreshing)
            _add_stream(writer, result, settings,
                        translator_stream_onnx(speaker.translator, call_refresh=0, delay_frames=delay), steady)
    steps.update()

    steps.set_postfix_str("deformation graph")
    args, dynamic = _deform_example(speaker)
    scene_options = {} if spec is None else {
        "drive_allowed": spec.drive_allowed, "vertex_subset": True,
        "latent_subspace": None if spec.latent_basis is None else (spec.latent_mean, spec.latent_basis)}
    # A scene's refit already went down to the settings' degree when `specialise` was told it (export_bundle does).
    sh_degree = settings.sh_degree
    if spec is not None:
        sh_degree = spec.sh_degree if sh_degree is None else min(spec.sh_degree, sh_degree)
    graph = DeformationGraph(speaker, sh_degree=sh_degree, blendshape_rank=settings.blendshape_rank,
                             **scene_options)
    model = onnx_export.export_onnx(graph, args, DEFORM_INPUTS, DEFORM_OUTPUTS, dynamic)
    result.graphs["deform"] = add_graph(writer, "deform", model, settings.codec_for)
    steps.update()

    steps.set_postfix_str("reference clip")
    if spec is None:  # a scene's bundle holds no clip (export_bundle)
        _add_reference(speaker, writer, result, settings)
    steps.update()

    buffers = {}
    regions = speaker.flame_arrays.regions
    if regions is not None:  # the semantic pass: each Gaussian's parent-triangle region (docs/compositing.md)
        ids = regions[speaker.gaussians.parent.numpy()]
        names = list(speaker.flame_arrays.region_names)
        writer.metadata["regions"] = names + [f"region_{i}" for i in range(len(names), int(regions.max()) + 1)]
        buffers["gaussian_regions"] = ids.astype(np.uint8 if regions.max() < 256 else np.uint16)
    _write_bundle(writer, path, result, steps, mnn,
                  {**buffers, "pose_track": speaker.pose_track, "motion_track": speaker.motion_track}, asked)


def _write_bundle(writer: BundleWriter, path: str | os.PathLike | StagedFile, result: ExportResult, steps: tqdm,
                  mnn: bool, buffers: dict, asked: tuple[str, ...] = ()) -> None:
    """The last steps of every export: the MNN models (if asked), the speaker's own buffers (None: absent; tensors
    stored as float32), the check that every buffer `asked` a codec of is stored, then one atomic write."""
    if mnn:
        steps.set_postfix_str("MNN graphs")
        result.mnn = add_mnn_graphs(writer)
        steps.update()
    steps.set_postfix_str("writing bundle")
    for name, value in buffers.items():
        if value is not None:
            writer.add_buffer(name, value.numpy().astype(np.float32) if isinstance(value, torch.Tensor) else value)
    check_buffer_codecs(asked, writer.manifest()["buffers"])
    result.bytes_written = writer.write(path)
    result.buffer_bytes = {name: entry["nbytes"] for name, entry in writer.manifest()["buffers"].items()}
    steps.update()


def check_buffer_codecs(asked: Sequence[str], stored: dict) -> None:
    """BundleError naming each buffer in `asked` (given a codec by `ExportSettings.buffer_codecs`) that the bundle
    does not store (a misspelt or another rig's name would otherwise change nothing, silently), with the names it
    does store."""
    missing = [name for name in asked if name not in stored]
    if not missing:
        return
    hints = []
    for name in missing:
        close = difflib.get_close_matches(name, list(stored), n=3, cutoff=0.6)
        hints.append(f"{name!r}" + (f" (did you mean {', '.join(map(repr, close))}?)" if close else ""))
    prefix = missing[0].split("/")[0] + "/"
    alike = sorted(name for name in stored if name.startswith(prefix))
    listed = ", ".join(alike[:24]) + (f", ... ({len(alike) - 24} more)" if len(alike) > 24 else "")
    raise BundleError(f"--buffer-codec names {'a buffer' if len(missing) == 1 else 'buffers'} this bundle does not "
                      f"store: {'; '.join(hints)}. Its buffers under {prefix!r}: {listed or 'none'} "
                      "(docs/precision.md, \"Knobs\")")


def _export_arkit_steps(speaker: ArkitSpeaker, writer: BundleWriter, path: str | os.PathLike | StagedFile,
                        result: ExportResult, settings: ExportSettings, steps: tqdm, mnn: bool,
                        asked: tuple[str, ...] = ()) -> None:
    """An ARKit speaker's deformation graph, its shipped motion and pose tracks, then one atomic write (its bundle
    has no translator graph and no reference clip; docs/import.md)."""
    steps.set_postfix_str("audio model")
    _add_audio_model(speaker, writer, result, settings)
    steps.update()
    steps.set_postfix_str("deformation graph")
    args, dynamic = arkit_deform_example(speaker)
    graph = ArkitDeformationGraph(speaker, sh_degree=settings.sh_degree, midpoints=settings.midpoints)
    model = onnx_export.export_onnx(graph, args, ARKIT_DEFORM_INPUTS, DEFORM_OUTPUTS, dynamic)
    result.graphs["deform"] = add_graph(writer, "deform", model, settings.codec_for)
    steps.update()
    steps.update()  # no reference clip
    _write_bundle(writer, path, result, steps, mnn,
                  {"pose_track": speaker.pose_track, "motion_track": speaker.motion_track}, asked)


def _add_audio_model(speaker: Speaker | ArkitSpeaker, writer: BundleWriter, result: ExportResult,
                     settings: ExportSettings) -> None:
    """An imported speaker's attached audio model (ONNX; exporter/imports/audio_model.py) as its translator graph."""
    if speaker.audio_model is None:
        return
    source = onnx.load_from_string(speaker.audio_model)
    model = convert_precision(source, settings.translator_precision)
    result.graphs["translator"] = add_graph(writer, "translator", model, settings.codec_for)
    _add_stream(writer, result, settings, stream_model_of(source))  # a user's own model has none


def _add_stream(writer: BundleWriter, result: ExportResult, settings: ExportSettings,
                stream: onnx.ModelProto | None, name: str = STREAM_GRAPH) -> None:
    """The translator's streaming graph (or its steady form, `name`), if it has one (live sessions run it:
    docs/live.md, "Streaming translators"), at the translator's precision; its weights are the translator's
    buffers, stored once."""
    if stream is not None:
        result.graphs[name] = add_graph(writer, name, convert_precision(
            stream, settings.translator_precision), settings.codec_for, share=True)


def _add_reference(speaker: Speaker, writer: BundleWriter, result: ExportResult, settings: ExportSettings) -> None:
    """The reference clip's encoded frames and masks (one entry each, decoded once here so a bundle never holds
    a clip that fails mid-video; re-encoded as the `reference` knob says when it names a coding) and the
    inpainting generator's graph, if the speaker has them."""
    clip = speaker.reference
    if clip is None:
        return
    try:
        coding = parse_reference(settings.reference)
        if coding is not None:
            clip = clip.reencoded(coding)
        clip.check(None if speaker.pose_track is None else int(speaker.pose_track.shape[0]))
    except ReferenceClipError as exc:
        raise BundleError(f"cannot export the reference clip: {exc}") from None
    writer.metadata["reference"] = clip.layout.to_dict()
    for index, (frame, mask) in enumerate(zip(clip.frames, clip.masks, strict=True)):
        writer.add_buffer(frame_entry(index), np.frombuffer(frame, dtype=np.uint8))
        writer.add_buffer(mask_entry(index), np.frombuffer(mask, dtype=np.uint8))
    if speaker.inpaint is not None:
        result.graphs["inpaint"] = add_graph(writer, "inpaint", inpainter_onnx(speaker.inpaint.eval()),
                                             settings.codec_for)
