"""Prove a bundle reproduces its torch speaker: every graph output, then the rendered frames of a driven clip, from
the bundle's camera and from novel views around the head.

Tolerances (why these numbers):
* graphs: max |onnx - torch| <= GRAPH_RTOL * max(1, max |torch|). Both sides compute in float32 with different
  kernels (MLAS vs. MKL/oneDNN), so a few ulps per op, accumulated over ~100 ops, stay well below 1e-4 relative.
* frames: PSNR >= 60 dB on float frames and >= 50 dB on the final 8-bit frames (the SDK's parity bounds). What remains
  is float reassociation, the GL path's missing early termination (< 1e-2 residual transmittance, usually < 1e-3)
  and rare depth-order flips of near-equal depths.
* novel views: the same frame bounds, on frames from the bundle's camera swung around the head (VIEW_ORBITS),
  where a face shows what its own camera does not; reported but not judged for a bundle with a Gaussian budget,
  whose Gaussians were chosen by what its own camera sees.
* reduced exports (quantised codecs, truncations, a Gaussian budget; exporter/export/presets.py): their error is the
  point, so graph errors are reported but the frames decide: every frame's 8-bit PSNR over the head region (pixels
  the torch frame covers with alpha > 1/255) must reach the label's bound, the bound its preset was measured to keep
  (docs/precision.md), or HEAD_PSNR_FLOOR_DB for a custom combination of knobs.
* composited frames (a speaker with a reference clip, docs/compositing.md): the runtime's composite of a driven
  clip against the torch render composited with the torch F, into the same decoded reference pictures, at the
  frame bounds above (outside the mask both are the reference picture exactly); the `inpaint` graph against the
  torch F on random crops and the clip's own crops, to GRAPH_RTOL. A clip re-encoded by the `reference` knob is
  what both sides composite into, so its codec's cost is not judged here (`gt-bench clip-crf` measures it).
* MNN graphs (`gt-export --mnn`, docs/mnn.md): each MNN graph against the onnxruntime graph on the same inputs,
  max |mnn - onnxruntime| <= MNN_RTOL * max |onnxruntime| per output (both run the same decoded float32 weights,
  so only kernel rounding differs: docs/mnn.md, "Accuracy", has the demo speaker's errors), plus the MNN
  backend's graphs and frames against torch at the label's bounds above.
* a scene's bundle (docs/scene.md): its deformation graph leaves out drives outside the scene by design, so it
  is judged by its frames of a driven clip inside the scene, at the scene's camera: SCENE_MIN_PSNR_DB on float and
  8-bit frames (or the label's bound, if lower).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from gaussiantalker.runtime.composite import crop_box
from gaussiantalker.runtime.head import TalkingHead
from gaussiantalker.sdk.bundle import STREAM_GRAPH, STREAM_GRAPHS
from gaussiantalker.sdk.drive import track_row
from gaussiantalker.sdk.image import max_abs_error, psnr_db, to_uint8
from gaussiantalker.sdk.progress import progress_bar

from ..export.probes import driven_clip, motion_clip, plays_audio, speech_clip
from ..export.spatial_order import spatial_order
from ..export.speech import synth_speech
from ..model.arkit_speaker import ArkitSpeaker
from ..model.speaker import Speaker
from ..model.translator_stream import STREAM_DELAYS, MotionTranslatorStream
from .compositing import composite_reference
from .random_inputs import random_blendshape_drives, random_crops, random_drives

GRAPH_RTOL = 1e-4
# Head-region bound of a custom (non-preset) reduced export: below the lowest any preset is built to keep (fast, 35).
HEAD_PSNR_FLOOR_DB = 30.0
# A pixel belongs to the head region when the torch frame's coverage 1 - T exceeds this (the contract's ALPHA_MIN).
HEAD_COVERAGE = 1.0 / 255.0
# Crop sizes (height, width) the inpaint graph is compared on.
INPAINT_CROP_SIZES = ((64, 64), (96, 160), (208, 128))
# MNN vs onnxruntime graph outputs, relative to each output's largest magnitude (fp32 graphs): only kernel rounding
# differs. Measured on the covariances, whose entries are sums of terms that cancel: ~2e-6 with the earlier,
# small-splat demo head, 1.1e-5 with the opaque one's larger splats (2k test speaker, docs/mnn.md "Accuracy").
MNN_RTOL = 3e-5
# Novel views of `verify_views`: (yaw, pitch) in degrees of the bundle's camera swung around the head's centre.
VIEW_ORBITS = ((-35.0, 0.0), (35.0, 0.0), (0.0, 20.0))
# Frame bound of a scene-specialised bundle against the torch speaker (what the scene tests hold it to).
SCENE_MIN_PSNR_DB = 50.0


@dataclass(frozen=True)
class Tolerances:
    """Pass/fail bounds of a verification (see the module docstring for why)."""

    graph_rtol: float | None = GRAPH_RTOL  # None: graph errors are reported, not a pass criterion
    min_psnr_float_db: float = 60.0
    min_psnr_uint8_db: float = 50.0
    min_head_psnr_db: float | None = None  # 8-bit PSNR over the head region, for reduced exports

    @classmethod
    def for_settings(cls, settings, preset=None) -> Tolerances:
        """Bounds of an export's settings (exporter/export/presets.py): fp32 and fp16 as `for_codec`; a reduced export
        is held to its preset's head-region bound, or HEAD_PSNR_FLOOR_DB when the knobs are a custom mix. The
        reference clip's setting plays no part (`ExportSettings.head_settings`)."""
        settings = settings.head_settings()
        label = settings.label()
        if label in ("fp32", "fp16"):
            return cls.for_codec("raw" if label == "fp32" else "fp16")
        same = preset is not None and any(settings == export.head_settings() for export in preset.exports())
        bound = preset.min_head_psnr_db if same else None
        bound = HEAD_PSNR_FLOOR_DB if bound is None else bound
        return cls(graph_rtol=None, min_psnr_float_db=bound, min_psnr_uint8_db=bound, min_head_psnr_db=bound)

    def for_scene(self) -> Tolerances:
        """These bounds for a scene's bundle: graphs reported, frames held to SCENE_MIN_PSNR_DB (or lower bounds)."""
        return Tolerances(graph_rtol=None, min_psnr_float_db=min(self.min_psnr_float_db, SCENE_MIN_PSNR_DB),
                          min_psnr_uint8_db=min(self.min_psnr_uint8_db, SCENE_MIN_PSNR_DB),
                          min_head_psnr_db=self.min_head_psnr_db)

    @classmethod
    def for_codec(cls, codec: str) -> Tolerances:
        """Default bounds of every buffer stored with `codec` (raw or fp16), against the fp32 torch speaker.

        fp16 buffers round every weight to 11 significant bits (relative 4.9e-4); through the blendshape and
        LBS sums that gives graph errors and frame PSNRs measured on the demo speaker in docs/export.md ("Parity
        with the torch speaker"), so the fp16 label is held to 2e-3 relative on graphs. Frames: 40 dB float and
        8-bit, because on an opaque head the ~1e-4 m position error swaps the depth order of a few near-coincident
        opaque splats, which changes those pixels by up to ~56 levels (2k test speaker: 45.8-46.4 dB minimum,
        depending on the translator's training run).
        """
        if codec == "fp16":
            return cls(graph_rtol=2e-3, min_psnr_float_db=40.0, min_psnr_uint8_db=40.0)
        return cls()


def _compare(reference: np.ndarray, test: np.ndarray, floor: float = 1.0) -> dict:
    """Max abs error, and relative to max(floor, max |reference|); whether `test` is finite."""
    reference, test = np.asarray(reference, np.float64), np.asarray(test, np.float64)
    err = max_abs_error(reference, test)
    scale = max(floor, float(np.max(np.abs(reference), initial=0.0)))
    finite = bool(np.all(np.isfinite(test)))
    return {"max_abs_err": err, "max_rel_err": err / scale, "finite": finite}


def _merge(stats: list[dict], tolerance: float | None) -> dict:
    worst = {"max_abs_err": max(s["max_abs_err"] for s in stats), "max_rel_err": max(s["max_rel_err"] for s in stats),
             "finite": all(s["finite"] for s in stats), "cases": len(stats), "tolerance_rel": tolerance}
    worst["passed"] = worst["finite"] and (tolerance is None or worst["max_rel_err"] <= tolerance)
    return worst


def verify_translator(speaker: Speaker, head: TalkingHead, frame_counts=(25, 33), seed: int = 0,
                      tolerance: float | None = GRAPH_RTOL) -> dict:
    """Translator graph vs torch on speech-like clips of several lengths (not only the exported one)."""
    if not plays_audio(speaker):
        if speaker.audio_model is None:
            return {"compared": False, "passed": True, "note": "an imported speaker without an audio model"}
        return _verify_audio_model(speaker, head, frame_counts, seed, tolerance)
    if not head.driver.has_translator:
        return {"compared": False, "passed": True, "note": "a flame-driven scene's bundle has no translator graph"}
    stats = []
    for i, frames in enumerate(frame_counts):
        audio = speech_clip(speaker, frames, seed + i)
        with torch.no_grad():
            expression, jaw = speaker.translate(torch.from_numpy(audio)[None])
        out = head.frame_renderer.graphs.run("translator", {"audio": audio[None]})
        stats.append(_compare(expression.numpy(), out["expression"]))
        stats.append(_compare(jaw.numpy(), out["jaw_pose"]))
    return _merge(stats, tolerance)


def verify_translator_stream(speaker: Speaker, head: TalkingHead, frames: int = 40, seed: int = 2,
                             tolerance: float | None = GRAPH_RTOL, steady: bool = False, short: bool = False
                             ) -> dict | None:
    """The streaming translator graph vs its torch module (None where the bundle has none or the speaker has no
    torch translator: the built-in voice's stream is built from its windowed graph, tests/test_voice_stream.py),
    fed a speech-like clip in uneven calls, some with a provisional frame after them. `steady`: its steady form
    instead (None where the bundle has none), every other call, on the state the two graphs share. `short`: the
    short stream's graphs (`--short-stream`) against its module."""
    pair, delay = STREAM_GRAPHS[int(short)], STREAM_DELAYS[int(short)]
    graph = pair[1] if steady else pair[0]
    if graph not in head.bundle.manifest["graphs"] or not plays_audio(speaker):
        return None
    modules = {True: MotionTranslatorStream(speaker.translator, delay_frames=delay).eval(),
               False: MotionTranslatorStream(speaker.translator, delay_frames=delay, call_refresh=0).eval()}
    module = modules[True]
    spf = speaker.config.samples_per_frame
    audio = speech_clip(speaker, frames, seed).reshape(frames, spf)
    state = np.zeros((1, module.state_size), np.float32)
    stats, position, sizes = [], 0, (1, 3, 2, 5)
    while position < frames:
        keep = min(sizes[len(stats) % len(sizes)], frames - position)
        chunk = np.concatenate([audio[position:position + keep], np.zeros((len(stats) % 2, spf), np.float32)])
        refresh = not steady or len(stats) % 2 == 1
        out = head.driver.run_stream(chunk[None], state, keep, refresh, graphs=pair)
        with torch.no_grad():
            expected = modules[refresh](torch.from_numpy(chunk[None]), torch.from_numpy(state),
                                        torch.tensor([float(keep)]))
        stats += [_compare(value.numpy(), out[name]) for name, value in
                  zip(("expression", "jaw_pose", "state_out"), expected[:3], strict=True)]
        state, position = out["state_out"], position + keep
    return _merge(stats, tolerance)


def _verify_audio_model(speaker: Speaker | ArkitSpeaker, head: TalkingHead, frame_counts, seed: int,
                        tolerance: float | None) -> dict:
    """An attached audio model has no torch twin: the bundle's `translator` graph against the attached model
    itself (onnxruntime on both), on speech-like clips of several lengths."""
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.log_severity_level = 3
    original = ort.InferenceSession(speaker.audio_model, options, providers=["CPUExecutionProvider"])
    stats = []
    for i, frames in enumerate(frame_counts):
        samples = int(round(frames * speaker.config.sample_rate / speaker.config.fps))
        audio = synth_speech(samples / speaker.config.sample_rate, seed=seed + i)[:samples][None]
        names = [value.name for value in original.get_outputs()]
        actual = head.frame_renderer.graphs.run("translator", {"audio": audio})
        stats.extend(_compare(expected, actual[name])
                     for name, expected in zip(names, original.run(names, {"audio": audio}), strict=True))
    return _merge(stats, tolerance)


def verify_deformation(speaker: Speaker, head: TalkingHead, count: int = 6, seed: int = 0,
                       tolerance: float | None = GRAPH_RTOL) -> dict:
    """Deformation graph vs torch on a neutral drive and random drives (expression, jaw, neck, eyes, head pose).
    A bundle with a Gaussian budget holds fewer Gaussians: its graph is not compared (the frames are)."""
    kept = head.bundle.manifest.get("gaussians")
    if "scene" in head.bundle.manifest:
        return {"compared": False, "passed": True, "note": "specialised for a scene (drives outside it are left "
                "out by design): judged by its frames inside the scene"}
    if kept != speaker.gaussians.count:
        return {"compared": False, "passed": True, "note": f"the bundle keeps {kept} of the speaker's "
                f"{speaker.gaussians.count} Gaussians (a Gaussian budget): judged by its frames"}
    stats = []
    center = head.camera.center.astype(np.float32)[None]
    order = _bundle_order(speaker, head.bundle.manifest.get("export_settings") or {})
    for drive in _random_drives(speaker, count, seed):
        inputs = {**drive.graph_inputs(), "camera_center": center}
        with torch.no_grad():
            reference = speaker.deform_drive(drive, torch.from_numpy(center))
        out = head.frame_renderer.graphs.run("deform", inputs)
        for ref, name in zip(reference, ("means", "cov3d", "rgb", "opacity"), strict=True):
            ref = ref.numpy()
            if order is not None:  # per-Gaussian rows: [B, N, C], or [N] for the opacity
                ref = ref[order] if ref.ndim == 1 else ref[..., order, :]
            stats.append(_compare(ref, out[name]))
    return _merge(stats, tolerance)


def _bundle_order(speaker: Speaker | ArkitSpeaker, settings: dict) -> np.ndarray | None:
    """The speaker's Gaussians in the bundle's order: its spatial order where the export took one (the same
    deterministic walk; exporter/export/spatial_order.py), else None (the speaker's own)."""
    if not settings.get("spatial_order"):
        return None
    return spatial_order(speaker, midpoints=bool(settings.get("midpoints")))


def _random_drives(speaker: Speaker | ArkitSpeaker, count: int, seed: int) -> list:
    """Random drives of the speaker's rig (neutral first)."""
    if isinstance(speaker, ArkitSpeaker):
        return random_blendshape_drives(speaker.config.blendshapes, count, seed)
    return random_drives(speaker.config.n_expr, count, seed)


def _clip_drives(speaker: Speaker | ArkitSpeaker, head: TalkingHead, frames: int, seed: int) -> tuple[list, list]:
    """(torch drives, runtime drives) of a driven clip: speech through each side's translator for a FLAME
    speaker (the torch drives on both sides for a bundle without one), its motion for an ARKit speaker."""
    if not plays_audio(speaker):
        drives = motion_clip(speaker, frames, seed)
        return drives, drives
    audio, torch_drives = driven_clip(speaker, frames, seed)
    # A flame-driven scene's bundle has no translator: it is driven with the torch translator's FLAME parameters.
    runtime_drives = (list(head.drives(audio, speaker.config.sample_rate))
                      if head.driver.has_translator else torch_drives)
    return torch_drives, runtime_drives


def verify_inpainter(speaker: Speaker, head: TalkingHead, seed: int = 0, tolerance: float | None = GRAPH_RTOL) -> dict:
    """The `inpaint` graph vs the torch F: random crops of three sizes, then the clip's first frame's own crop."""
    if "inpaint" not in head.bundle.manifest["graphs"]:
        note = ("no inpainting generator: the OpenCV fallback composites" if head.reference is not None
                else "no reference clip")
        return {"compared": False, "passed": True, "note": note}
    crops = random_crops(seed, INPAINT_CROP_SIZES)
    mask = head.reference.mask(0)
    box = crop_box(mask)
    picture = head.reference.frame(0)[box.rows, box.columns].astype(np.float32) / 255
    inside = mask[box.rows, box.columns]
    crops.append((np.ascontiguousarray(((1 - inside[..., None]) * picture).transpose(2, 0, 1)[None]),
                  inside[None, None], np.zeros_like(inside)[None, None]))
    stats = []
    for image, m, coverage in crops:
        if image.shape[2] % 16 or image.shape[3] % 16:  # a crop at the image border (padded at run time)
            continue
        with torch.no_grad():
            reference = speaker.inpaint(*(torch.from_numpy(np.ascontiguousarray(a)) for a in (image, m, coverage)))
        out = head.frame_renderer.graphs.run("inpaint", {"image": image, "mask": m, "coverage": coverage})
        stats.append(_compare(reference.numpy(), out["inpainted"]))
    return _merge(stats, tolerance)


def verify_composited(speaker: Speaker, head: TalkingHead, frames: int = 12, seed: int = 1,
                      tolerances: Tolerances = Tolerances(), progress: bool = False) -> dict:
    """Composited frames of a driven clip: the runtime's vs the torch render composited with the torch F (or the
    same OpenCV fallback) into the same reference pictures."""
    audio, torch_drives = driven_clip(speaker, frames, seed)
    runtime_frames = head.frames(audio, speaker.config.sample_rate)
    background = torch.zeros(3)
    results = []
    for index, test in enumerate(progress_bar(runtime_frames, total=frames, desc="verify composited", unit="frame",
                                      disable=not progress)):
        image, trans = speaker.render(torch_drives[index], head.camera, background, transmittance=True)
        premultiplied = np.dstack([image.numpy(), 1.0 - trans.numpy()]).astype(np.float32)
        row = track_row(len(head.reference), index)
        reference = composite_reference(premultiplied, head.reference.frame(row), head.reference.mask(row),
                                        speaker.inpaint)
        results.append({"index": index, "psnr_db": psnr_db(reference, test),
                        "max_pixel_error": int(np.abs(reference.astype(np.int16) - test.astype(np.int16)).max())})
    min8 = min(r["psnr_db"] for r in results)
    return {"frames": results, "min_psnr_db": min8, "max_pixel_error": max(r["max_pixel_error"] for r in results),
            "resolution": [head.camera.width, head.camera.height],
            "generator": head.bundle.manifest.get("inpaint", {}).get("generator"),
            "passed": min8 >= tolerances.min_psnr_uint8_db}


def verify_frames(speaker: Speaker, head: TalkingHead, frames: int = 25, seed: int = 1,
                  tolerances: Tolerances = Tolerances(), progress: bool = False) -> dict:
    """Driven frames: torch (translator -> deform -> reference rasterizer; an ARKit speaker: its motion -> deform
    -> rasterizer) vs the runtime, end to end."""
    torch_drives, runtime_drives = _clip_drives(speaker, head, frames, seed)
    results = [_frame_result(speaker, head, torch_drives[index], runtime_drives[index], index)
               for index in progress_bar(range(frames), desc="verify frames", unit="frame", disable=not progress)]
    return _frames_report(results, tolerances)


def verify_views(speaker: Speaker | ArkitSpeaker, head: TalkingHead, views: int = len(VIEW_ORBITS), seed: int = 2,
                 tolerances: Tolerances = Tolerances()) -> dict:
    """Frames from novel cameras: the bundle's camera swung around the head's centre (the first `views` of
    VIEW_ORBITS; verify_bundle asks for as many as it renders frames, at most all three), one drive of
    a driven clip each, torch vs runtime as in `verify_frames` (a scene's bundle has one camera: not compared; a
    Gaussian budget's bundle: reported, not judged, as its Gaussians were chosen for its own camera)."""
    if head.frame_renderer.scene is not None:
        return {"compared": False, "passed": True, "note": "a scene's bundle is for its own camera"}
    orbits = VIEW_ORBITS[:max(1, views)]
    torch_drives, runtime_drives = _clip_drives(speaker, head, len(orbits), seed)
    camera = head.camera
    pruned = head.bundle.manifest.get("gaussians") != speaker.gaussians.count
    with torch.no_grad():
        centre = speaker.deform_drive(torch_drives[0], torch.from_numpy(camera.center.astype(np.float32))[None])[0]
    target = centre[0].median(dim=0).values.double().numpy()
    results = []
    try:
        for index, (yaw, pitch) in enumerate(orbits):
            head.camera = camera.orbited(yaw, pitch, target)  # the same head, seen from elsewhere
            results.append({**_frame_result(speaker, head, torch_drives[index], runtime_drives[index], index),
                            "yaw_deg": yaw, "pitch_deg": pitch})
    finally:
        head.camera = camera
    report = _frames_report(results, tolerances)
    if pruned:  # a Gaussian budget keeps what the bundle's own camera sees: reported, not judged, elsewhere
        report.update(judged=False, passed=True,
                      note=f"the bundle keeps {head.bundle.manifest.get('gaussians')} of the speaker's "
                           f"{speaker.gaussians.count} Gaussians, chosen for its own camera: reported only")
    return report


def _frame_result(speaker: Speaker | ArkitSpeaker, head: TalkingHead, torch_drive, runtime_drive, index: int
                  ) -> dict:
    """One frame at the head's camera: torch reference vs runtime, 8-bit / float / head-region PSNR and errors."""
    reference, trans = speaker.render(torch_drive, head.camera, head.frame_renderer.background, transmittance=True)
    reference, head_region = reference.numpy(), (1.0 - trans.numpy()) > HEAD_COVERAGE
    test = head.render(runtime_drive, output="float")
    ref8, test8 = to_uint8(reference), to_uint8(test)
    return {
        "index": index,
        "psnr_db": psnr_db(ref8, test8),
        "head_psnr_db": psnr_db(ref8[head_region], test8[head_region]) if head_region.any() else float("inf"),
        "psnr_float_db": psnr_db(reference, test),
        "max_pixel_error": int(np.abs(ref8.astype(np.int16) - test8.astype(np.int16)).max()),
        "max_float_error": max_abs_error(reference, test),
        "finite": bool(np.all(np.isfinite(test))),
    }


def _frames_report(results: list[dict], tolerances: Tolerances) -> dict:
    """Worst values of per-frame results and whether they pass `tolerances`."""
    min8 = min(r["psnr_db"] for r in results)
    minf = min(r["psnr_float_db"] for r in results)
    min_head = min(r["head_psnr_db"] for r in results)
    passed = (all(r["finite"] for r in results) and min8 >= tolerances.min_psnr_uint8_db
              and minf >= tolerances.min_psnr_float_db
              and (tolerances.min_head_psnr_db is None or min_head >= tolerances.min_head_psnr_db))
    return {"frames": results, "min_psnr_db": min8, "min_psnr_float_db": minf, "min_head_psnr_db": min_head,
            "max_pixel_error": max(r["max_pixel_error"] for r in results), "passed": passed}


def _agreement_cases(speaker: Speaker, head: TalkingHead, seed: int = 0) -> list[tuple[str, dict]]:
    """(graph, inputs) pairs the two backends are compared on: speech clips, random drives, random crops."""
    cases: list[tuple[str, dict]] = []
    if head.driver.has_translator and plays_audio(speaker):
        for i, frames in enumerate((25, 33)):
            cases.append(("translator", {"audio": np.ascontiguousarray(speech_clip(speaker, frames, seed + i)[None],
                                                                       np.float32)}))
        for stream in head.driver.stream_specs if STREAM_GRAPH in head.bundle.manifest["graphs"] else ():
            rest = np.stack([stream.rest_state] * 2)  # two sessions from rest, uneven calls
            spf = speaker.config.samples_per_frame
            for frames, keep in ((3, 2), (1, 1)):
                audio = speech_clip(speaker, 2 * frames, seed + frames).reshape(2, frames, spf)
                for graph in stream.graphs or STREAM_GRAPHS[0]:
                    if graph in head.bundle.manifest["graphs"]:
                        cases.append((graph, {"audio": audio, "state": rest, "keep": np.array([keep], np.float32)}))
    center = head.camera.center.astype(np.float32)[None]
    for drive in _random_drives(speaker, 4, seed):
        cases.append(("deform", {**drive.graph_inputs(), "camera_center": center}))
    if "inpaint" in head.bundle.manifest["graphs"]:
        for image, mask, coverage in random_crops(seed, INPAINT_CROP_SIZES[:2]):
            cases.append(("inpaint", {"image": image, "mask": mask, "coverage": coverage}))
    return cases


def verify_backend_agreement(reference: TalkingHead, test: TalkingHead, cases: list[tuple[str, dict]],
                             tolerance: float = MNN_RTOL) -> dict[str, dict]:
    """Per graph: the worst max |test - reference| / max |reference| over every output and case."""
    stats: dict[str, list[dict]] = {}
    for graph, inputs in cases:
        expected = reference.frame_renderer.graphs.run(graph, inputs)
        actual = test.frame_renderer.graphs.run(graph, inputs)
        stats.setdefault(graph, []).extend(_compare(value, actual[name], floor=1e-30)
                                           for name, value in expected.items())
    return {graph: _merge(graph_stats, tolerance) for graph, graph_stats in stats.items()}


def verify_mnn(speaker: Speaker, head: TalkingHead, bundle_path, frames: int = 25, seed: int = 1,
               tolerances: Tolerances = Tolerances()) -> dict:
    """The bundle's MNN graphs against its onnxruntime graphs (`head`): graph outputs to MNN_RTOL, and the frames
    of a driven clip rendered from each backend's drives at the frame bounds."""
    with TalkingHead(bundle_path, resolution=(head.camera.width, head.camera.height), composite=False,
                     backend="mnn") as mnn_head:
        graphs = verify_backend_agreement(head, mnn_head, _agreement_cases(speaker, head))
        if head.driver.has_translator and plays_audio(speaker):
            audio, _ = driven_clip(speaker, frames, seed)
            pairs = zip(head.frames(audio, speaker.config.sample_rate),
                        mnn_head.frames(audio, speaker.config.sample_rate), strict=True)
        else:  # an ARKit speaker's motion, or a flame-driven scene's torch-translator drives
            _, drives = _clip_drives(speaker, head, frames, seed)
            pairs = ((head.render(drive), mnn_head.render(drive)) for drive in drives)
        results = [{"psnr_db": psnr_db(reference, test),
                    "max_pixel_error": int(np.abs(reference.astype(np.int16) - test.astype(np.int16)).max())}
                   for reference, test in pairs]
    min8 = min(r["psnr_db"] for r in results)
    passed = min8 >= tolerances.min_psnr_uint8_db and all(g["passed"] for g in graphs.values())
    return {"converter": head.bundle.manifest["mnn"].get("converter"), "graphs": graphs, "frames": len(results),
            "min_psnr_db": min8, "max_pixel_error": max(r["max_pixel_error"] for r in results), "passed": passed}


def verify_bundle(speaker: Speaker, bundle_path, *, frames: int = 25, resolution: tuple[int, int] | None = (256, 256),
                  tolerances: Tolerances = Tolerances(), progress: bool = True) -> dict:
    """The full report `gt-export --verify` prints and `--report` writes as JSON (`resolution` None: the bundle's
    camera, which for a scene's bundle is the scene's)."""
    with TalkingHead(bundle_path, resolution=resolution, composite=False) as head:
        resolution = (head.camera.width, head.camera.height)
        head.bundle.verify_all()
        graphs = {"translator": verify_translator(speaker, head, tolerance=tolerances.graph_rtol),
                  "deform": verify_deformation(speaker, head, tolerance=tolerances.graph_rtol)}
        for short, pair in enumerate(STREAM_GRAPHS):
            for graph, steady in zip(pair, (False, True), strict=True):
                stream = verify_translator_stream(speaker, head, tolerance=tolerances.graph_rtol, steady=steady,
                                                  short=bool(short))
                if stream is not None:
                    graphs[graph] = stream
        frame_report = verify_frames(speaker, head, frames, tolerances=tolerances, progress=progress)
        views = verify_views(speaker, head, views=min(frames, len(VIEW_ORBITS)), tolerances=tolerances)
        composited = None
        if head.reference is not None:
            width, height = head.reference.layout.size
            # Half the clip's size, rounded to even sides: the torch rasterizer's cost, not the contract, sets it.
            with TalkingHead(bundle_path, resolution=(width // 4 * 2, height // 4 * 2)) as clip_head:
                graphs["inpaint"] = verify_inpainter(speaker, clip_head, tolerance=tolerances.graph_rtol)
                composited = verify_composited(speaker, clip_head, tolerances=tolerances, progress=progress)
        mnn = verify_mnn(speaker, head, bundle_path, frames, tolerances=tolerances) if "mnn" in head.bundle.manifest \
            else None
    report = {
        "bundle": str(bundle_path),
        "resolution": list(resolution),
        "tier": head.bundle.manifest.get("precision"),
        "tolerances": tolerances.__dict__,
        "graphs": graphs,
        **frame_report,
        "views": views,
    }
    if composited is not None:
        report["composited"] = composited
    if mnn is not None:
        report["mnn"] = mnn
    report["passed"] = (frame_report["passed"] and views["passed"] and all(g["passed"] for g in graphs.values())
                        and (composited is None or composited["passed"]) and (mnn is None or mnn["passed"]))
    return report


def format_report(report: dict) -> str:
    """A short human-readable table of a verification report."""
    mnn = report.get("mnn")
    names = [*report["graphs"], *(f"mnn {name}" for name in (mnn["graphs"] if mnn is not None else ()))]
    width = max(12, *(len(name) + 1 for name in names))  # the graph names' column
    lines = [f"{'graph':<{width}}{'max abs err':>14}{'max rel err':>14}{'tol (rel)':>12}  ok"]
    for name, g in report["graphs"].items():
        if not g.get("compared", True):
            lines.append(f"{name:<{width}}  not compared: {g['note']}")
            continue
        tolerance = "report" if g["tolerance_rel"] is None else f"{g['tolerance_rel']:.0e}"
        lines.append(f"{name:<{width}}{g['max_abs_err']:>14.3e}{g['max_rel_err']:>14.3e}{tolerance:>12}  "
                     f"{'yes' if g['passed'] else 'NO'}")
    psnrs = [f["psnr_db"] for f in report["frames"]]
    finite = [p for p in psnrs if math.isfinite(p)]
    w, h = report["resolution"]
    lines.append(f"frames: {len(psnrs)} at {w}x{h}; 8-bit PSNR min {report['min_psnr_db']:.2f} dB"
                 f" (median {np.median(finite) if finite else float('inf'):.2f}), float PSNR min "
                 f"{report['min_psnr_float_db']:.2f} dB, head-region 8-bit PSNR min {report['min_head_psnr_db']:.2f}"
                 f" dB, max pixel error {report['max_pixel_error']} levels")
    views = report.get("views")
    if views is not None and views.get("compared", True):
        lines.append(f"novel views: {len(views['frames'])} cameras around the head; 8-bit PSNR min "
                     f"{views['min_psnr_db']:.2f} dB, head-region min {views['min_head_psnr_db']:.2f} dB, max pixel "
                     f"error {views['max_pixel_error']} levels "
                     f"{views['note'] if 'note' in views else 'ok' if views['passed'] else 'NO'}")
    composited = report.get("composited")
    if composited is not None:
        w, h = composited["resolution"]
        lines.append(f"composited: {len(composited['frames'])} frames at {w}x{h} ({composited['generator']} F); "
                     f"8-bit PSNR min {composited['min_psnr_db']:.2f} dB, max pixel error "
                     f"{composited['max_pixel_error']} levels {'ok' if composited['passed'] else 'NO'}")
    if mnn is not None:
        for name, g in mnn["graphs"].items():
            lines.append(f"{'mnn ' + name:<{width}}{g['max_abs_err']:>14.3e}{g['max_rel_err']:>14.3e}"
                         f"{g['tolerance_rel']:>12.0e}  {'yes' if g['passed'] else 'NO'}  (vs onnxruntime)")
        lines.append(f"mnn frames: {mnn['frames']} vs onnxruntime's, 8-bit PSNR min {mnn['min_psnr_db']:.2f} dB, "
                     f"max pixel error {mnn['max_pixel_error']} levels ({mnn['converter']}) "
                     f"{'ok' if mnn['passed'] else 'NO'}")
    bounds = report["tolerances"]
    head_bound = "" if bounds["min_head_psnr_db"] is None else f", head region >= {bounds['min_head_psnr_db']} dB"
    lines.append(f"verification {'PASSED' if report['passed'] else 'FAILED'} for tier {report.get('tier')} (8-bit >= "
                 f"{bounds['min_psnr_uint8_db']} dB, float >= {bounds['min_psnr_float_db']} dB{head_bound})")
    return "\n".join(lines)
