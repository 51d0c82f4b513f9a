"""What every graph backend checks of a bundle before and after opening its graphs, so damage fails at load.

A speaker bundle must hold the graphs and camera TalkingHead needs (`check_speaker_bundle`); each graph's
protobuf must agree with the buffers the manifest feeds it and want no data from outside the bundle
(`check_initializers`, read with runtime/onnx_wire.py); a session's signature must be the manifest's
(`check_signature`); the speaker's expression width must be the graphs' (`check_expression_width`).
"""

from __future__ import annotations

from typing import Any

from gaussiantalker.sdk.bundle import FLAME_DRIVER, Bundle
from gaussiantalker.sdk.camera import Camera
from gaussiantalker.sdk.codecs import ONNX_DTYPES, ORT_DTYPES
from gaussiantalker.sdk.config import SpeakerConfig
from gaussiantalker.sdk.errors import BundleError, CameraError
from gaussiantalker.sdk.flame_motion import TABLE_POSE_COLUMNS
from gaussiantalker.sdk.rig import ArkitRig

from .onnx_wire import model_tensors

# What a speaker bundle (one whose manifest has a 'speaker' section) must hold for TalkingHead.
SPEAKER_GRAPHS = ("translator", "deform")
POSE_TRACK_WIDTH = 6


def is_speaker_bundle(bundle: Bundle) -> bool:
    """Whether the bundle holds a speaker (a FLAME 'speaker' section or an ARKit 'rig'), not bare graphs."""
    return "speaker" in bundle.manifest or "rig" in bundle.manifest


def _check_track(bundle: Bundle, name: str, width: int, what: str) -> None:
    """Buffer `name`, if present, must be float32 [T >= 1, width]."""
    if bundle.has_buffer(name):
        entry = bundle.manifest["buffers"][name]
        shape = entry["shape"]
        if entry["dtype"] != "float32" or len(shape) != 2 or shape[0] < 1 or shape[1] != width:
            raise BundleError(f"{bundle.path}: buffer {name!r} is {entry['dtype']} {shape}, expected float32 "
                              f"[T >= 1, {width}] ({what})")


def check_arkit_bundle(bundle: Bundle) -> None:
    """An ARKit speaker's bundle: a valid rig, a `deform` graph, a valid camera, and well-shaped tracks."""
    try:
        rig = ArkitRig.from_dict(bundle.manifest["rig"])
    except (TypeError, ValueError) as exc:
        raise BundleError(f"{bundle.path}: manifest 'rig' is invalid: {exc}") from None
    if "deform" not in bundle.manifest["graphs"]:
        raise BundleError(f"{bundle.path}: ARKit speaker bundle lacks the 'deform' graph")
    try:
        Camera.from_dict(bundle.manifest["camera"])
    except (CameraError, TypeError, KeyError) as exc:
        raise BundleError(f"{bundle.path}: manifest 'camera' section is invalid: {exc}") from None
    _check_track(bundle, "pose_track", POSE_TRACK_WIDTH, "rotation, translation per frame")
    _check_track(bundle, "motion_track", len(rig.blendshapes), "ARKit weights per frame")


def _check_width(bundle: Bundle, value_name: str, expected: int, claim: str, unit: str) -> None:
    """The last axis of `value_name` (the `deform` graph's input, the `translator` graph's output) must be
    `expected`, what the manifest's `claim` says; BundleError naming both."""
    for graph, kind in (("deform", "inputs"), ("translator", "outputs")):
        if graph not in bundle.manifest["graphs"]:
            continue
        for value in bundle.graph_info(graph)[kind]:
            width = value["shape"][-1] if value["shape"] else None
            if value["name"] == value_name and isinstance(width, int) and width != expected:
                raise BundleError(f"{bundle.path}: {claim} but graph {graph!r} {kind[:-1]} {value_name!r} has "
                                  f"{width} {unit}")


def check_blendshape_width(bundle: Bundle) -> None:
    """The `deform` graph's 'blendshapes' input, and an audio model's (`translator`) output, must be as wide as
    the rig's blendshape list."""
    count = len(bundle.manifest["rig"]["blendshapes"])
    _check_width(bundle, "blendshapes", count, f"manifest rig names {count} blendshapes", "weights")


def check_speaker_bundle(bundle: Bundle) -> None:
    """A speaker bundle must hold both graphs (a flame-driven scene's only `deform`), a valid camera, and (if any)
    a float32 [T, 6] pose track. An ARKit speaker's: `check_arkit_bundle`."""
    if "rig" in bundle.manifest:
        check_arkit_bundle(bundle)
        return
    scene = bundle.manifest.get("scene")
    flame_driven = bundle.manifest.get("driver") == FLAME_DRIVER or (
        isinstance(scene, dict) and isinstance(scene.get("drive"), dict) and scene["drive"].get("driver") == "flame")
    required = [name for name in SPEAKER_GRAPHS if not (flame_driven and name == "translator")]
    missing = [name for name in required if name not in bundle.manifest["graphs"]]
    if missing:
        raise BundleError(f"{bundle.path}: speaker bundle lacks the {' and '.join(map(repr, missing))} graph"
                          f"{'s' if len(missing) > 1 else ''} (it holds: {', '.join(bundle.graph_names()) or 'none'})")
    for section in ("speaker", "camera"):
        if not isinstance(bundle.manifest[section], dict):
            raise BundleError(f"{bundle.path}: manifest {section!r} section is not a table")
    try:
        Camera.from_dict(bundle.manifest["camera"])
    except CameraError as exc:
        raise BundleError(f"{bundle.path}: manifest 'camera' section is invalid: {exc}") from None
    _check_track(bundle, "pose_track", POSE_TRACK_WIDTH, "rotation, translation per frame")
    n_expr = bundle.manifest["speaker"].get("n_expr", SpeakerConfig.n_expr)
    if isinstance(n_expr, int):
        _check_track(bundle, "motion_track", n_expr + TABLE_POSE_COLUMNS,
                     "expression, FLAME pose and translation per frame")


def check_expression_width(bundle: Bundle) -> None:
    """The speaker config's n_expr must be the graphs' expression width (drives are built from it); each backend
    calls this once its graphs' signatures are known to be the manifest's. An ARKit speaker's: the rig's
    blendshape count (`check_blendshape_width`)."""
    if "rig" in bundle.manifest:
        check_blendshape_width(bundle)
        return
    n_expr = bundle.manifest["speaker"].get("n_expr", SpeakerConfig.n_expr)
    _check_width(bundle, "expression", n_expr, f"manifest speaker n_expr is {n_expr!r}", "coefficients")


def check_initializers(bundle: Bundle, name: str, onnx_bytes: bytes, feeds: dict[str, str]) -> None:
    """Each fed initializer exists with the buffer's dtype and shape; nothing else wants external data."""
    try:
        tensors = list(model_tensors(onnx_bytes))
    except (ValueError, IndexError) as exc:
        raise BundleError(f"{bundle.path}: graph {name!r} is not a valid ONNX model ({exc})") from None
    top_level = {t.name: t for t in tensors if t.top_level}
    for tensor in tensors:
        if tensor.external and not (tensor.top_level and tensor.name in feeds):
            raise BundleError(f"{bundle.path}: graph {name!r} tensor {_short(tensor.name)} wants external data the "
                              f"bundle does not supply (refused: the runtime reads nothing outside the bundle)")
    for init, buffer in feeds.items():
        tensor = top_level.get(init)
        if tensor is None:
            raise BundleError(f"{bundle.path}: graph {name!r} has no initializer {init!r} (the manifest feeds it "
                              f"from buffer {buffer!r})")
        entry = bundle.manifest["buffers"][buffer]
        dtype = ONNX_DTYPES.get(tensor.data_type, f"ONNX type {tensor.data_type}")
        if dtype != entry["dtype"] or tensor.dims != list(entry["shape"]):
            raise BundleError(f"{bundle.path}: graph {name!r} initializer {init!r} is {dtype} {tensor.dims} but "
                              f"buffer {buffer!r} is {entry['dtype']} {entry['shape']}")


def _short(name: str) -> str:
    """A tensor name read from a graph's bytes, quoted as an error quotes it: at most 100 characters."""
    return f"{name[:100]!r}" + ("..." if len(name) > 100 else "")


def check_signature(bundle: Bundle, name: str, info: dict, session: Any) -> None:
    """The manifest's input/output names, ranks, fixed sizes and dtypes must be what the graph really has
    (`session`: an onnxruntime InferenceSession, or anything with its get_inputs/get_outputs)."""
    for kind, declared, actual in (("input", info["inputs"], session.get_inputs()),
                                   ("output", info["outputs"], session.get_outputs())):
        actual_by_name = {a.name: a for a in actual}
        if sorted(d["name"] for d in declared) != sorted(actual_by_name):
            raise BundleError(f"{bundle.path}: graph {name!r} {kind}s are {sorted(actual_by_name)} but the "
                              f"manifest declares {sorted(d['name'] for d in declared)}")
        for d in declared:
            a = actual_by_name[d["name"]]
            fixed_differ = len(a.shape) == len(d["shape"]) and any(
                isinstance(x, int) and isinstance(y, int) and x != y for x, y in zip(a.shape, d["shape"], strict=True))
            if ORT_DTYPES.get(a.type) != d["dtype"] or len(a.shape) != len(d["shape"]) or fixed_differ:
                raise BundleError(f"{bundle.path}: graph {name!r} {kind} {d['name']!r} is {a.type} {a.shape} but "
                                  f"the manifest declares {d['dtype']} {d['shape']}")


__all__ = ["FLAME_DRIVER", "POSE_TRACK_WIDTH", "SPEAKER_GRAPHS", "check_arkit_bundle", "check_blendshape_width",
           "is_speaker_bundle", "check_expression_width", "check_initializers", "check_signature",
           "check_speaker_bundle"]
