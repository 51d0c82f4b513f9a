"""The checkpoint entries of an ARKit speaker (docs/import.md): the same weights-only torch.save file as a FLAME
speaker's (exporter/export/checkpoint.py), marked "rig": "arkit", holding the blendshape rig, the vertex-bound
Gaussians, camera, background, the shipped motion and where the avatar came from."""

from __future__ import annotations

import math
from pathlib import Path

import torch

from gaussiantalker.sdk.camera import Camera
from gaussiantalker.sdk.errors import CameraError, CheckpointError
from gaussiantalker.sdk.numerics import sh_coeff_count
from gaussiantalker.sdk.rig import ARKIT_RIG, ArkitRig

from ..model.arkit_speaker import ArkitSpeaker
from ..model.blendshape_rig import BlendshapeRig
from ..model.vertex_binding import VertexBoundGaussians

REQUIRED_KEYS = ("config", "sh_degree", "blendshape_rig", "gaussians", "camera", "background")
_GAUSSIAN_KEYS = ("offset", "rotation", "log_scale", "opacity_logit", "sh")


def arkit_payload(speaker: ArkitSpeaker) -> dict:
    """The entries of an ARKit speaker's checkpoint (beside "format" and "version")."""
    g = speaker.gaussians
    return {
        "rig": ARKIT_RIG,
        "config": speaker.config.to_dict(),
        "sh_degree": g.sh_degree,
        "blendshape_rig": {"rest": speaker.rig.rest.clone(), "morphs": speaker.rig.morphs.clone(),
                           "pivot": speaker.rig.pivot.clone(),
                           **({} if speaker.rig.faces is None else {"faces": speaker.rig.faces.clone()})},
        "gaussians": {"vertex": g.vertex.clone(), **{k: getattr(g, k).detach().clone() for k in _GAUSSIAN_KEYS}},
        "camera": speaker.camera.to_dict(),
        "background": list(speaker.background),
        "pose_track": None if speaker.pose_track is None else speaker.pose_track.clone(),
        "motion_track": None if speaker.motion_track is None else speaker.motion_track.clone(),
        "source": speaker.source,
        "audio_model": audio_model_entry(speaker.audio_model),
    }


def audio_model_entry(model: bytes | None) -> torch.Tensor | None:
    """An attached ONNX audio model's bytes as a uint8 tensor (what the weights-only unpickler reads)."""
    return None if model is None else torch.frombuffer(bytearray(model), dtype=torch.uint8)


def audio_model_from(path: Path, payload: dict) -> bytes | None:
    """The attached audio model's bytes from a checkpoint (None: none attached); CheckpointError if malformed."""
    model = payload.get("audio_model")
    if model is None:
        return None
    _tensor(path, "'audio_model'", model, (None,), floating=False)
    if model.dtype != torch.uint8:
        raise CheckpointError(f"checkpoint {path}: 'audio_model' must be the ONNX file's bytes (uint8)")
    return model.numpy().tobytes()


# How deep a plain entry (config, camera, source, ...) may nest: theirs are two or three levels deep.
MAX_PLAIN_DEPTH = 16


def plain_entry(path: Path, label: str, value: object) -> object:
    """`value` if it is plain data (None, bools, numbers, strings, and lists, tuples and dicts of them, at most
    MAX_PLAIN_DEPTH deep), else CheckpointError: a tensor where a number belongs would fail later, deep inside a
    comparison (docs/untrusted-input.md, "Checkpoints")."""
    stack = [(value, 0)]
    while stack:
        item, depth = stack.pop()
        if depth > MAX_PLAIN_DEPTH:
            raise CheckpointError(f"checkpoint {path}: {label} nests over {MAX_PLAIN_DEPTH} levels deep")
        if isinstance(item, dict):
            if not all(isinstance(key, str | int) for key in item):
                raise CheckpointError(f"checkpoint {path}: {label} has a key that is not a string")
            stack += [(v, depth + 1) for v in item.values()]
        elif isinstance(item, list | tuple):
            stack += [(v, depth + 1) for v in item]
        elif not (item is None or isinstance(item, bool | int | float | str)):
            raise CheckpointError(f"checkpoint {path}: {label} holds a {type(item).__name__} where plain numbers, "
                                  "strings, lists and dicts belong")
    return value


def source_from(path: Path, payload: dict) -> dict:
    """Where an imported speaker came from (a plain dict; empty when absent); CheckpointError if not a dict."""
    source = plain_entry(path, "'source'", payload.get("source"))
    if source is None:
        return {}
    if not isinstance(source, dict):
        raise CheckpointError(f"checkpoint {path}: 'source' must be a dict")
    return source


def _tensor(path: Path, label: str, value, shape: tuple, floating: bool = True) -> torch.Tensor:
    """A tensor of the right kind, shape (None: any size on that axis) and finite values, or CheckpointError."""
    if not isinstance(value, torch.Tensor):
        raise CheckpointError(f"checkpoint {path}: {label} must be a tensor, got {type(value).__name__}")
    if value.is_floating_point() != floating or value.is_complex():
        kind = "a floating-point" if floating else "an integer"
        raise CheckpointError(f"checkpoint {path}: {label} has dtype {value.dtype}, expected {kind} tensor")
    if value.ndim != len(shape) or any(want is not None and got != want
                                       for got, want in zip(value.shape, shape, strict=True)):
        want = ", ".join("*" if s is None else str(s) for s in shape)
        raise CheckpointError(f"checkpoint {path}: {label} has shape {list(value.shape)}, expected [{want}]")
    if floating and not bool(torch.isfinite(value).all()):
        raise CheckpointError(f"checkpoint {path}: {label} contains NaN or infinite values")
    return value


def optional_track(path: Path, payload: dict, key: str, width: int) -> torch.Tensor | None:
    """The [T >= 1, width] float track `key` of a checkpoint, or None when absent; CheckpointError if malformed."""
    value = payload.get(key)
    if value is None:
        return None
    track = _tensor(path, f"{key!r}", value, (None, width))
    if track.shape[0] < 1:
        raise CheckpointError(f"checkpoint {path}: {key!r} has no rows")
    return track


def load_arkit_payload(path: Path, payload: dict) -> ArkitSpeaker:
    """Rebuild an ArkitSpeaker from checkpoint entries; every entry's type, dtype and shape is checked."""
    missing = [k for k in REQUIRED_KEYS if k not in payload]
    if missing:
        raise CheckpointError(f"checkpoint {path} (an ARKit speaker) is missing entries: {', '.join(missing)}")
    try:
        config = ArkitRig.from_dict(payload["config"])
        camera = Camera.from_dict(payload["camera"])
    except (TypeError, ValueError, CameraError) as exc:
        raise CheckpointError(f"checkpoint {path}: invalid config or camera: {exc}") from exc
    sh_degree = payload["sh_degree"]
    if not isinstance(sh_degree, int) or not 0 <= sh_degree <= 3:
        raise CheckpointError(f"checkpoint {path}: 'sh_degree' must be an int 0..3, got {sh_degree!r}")
    rig_data, g = payload["blendshape_rig"], payload["gaussians"]
    if not isinstance(rig_data, dict) or not isinstance(g, dict):
        raise CheckpointError(f"checkpoint {path}: 'blendshape_rig' and 'gaussians' must be dicts of tensors")
    rest = _tensor(path, "blendshape_rig 'rest'", rig_data.get("rest"), (None, 3))
    count = rest.shape[0]
    morphs = _tensor(path, "blendshape_rig 'morphs'", rig_data.get("morphs"), (len(config.blendshapes), count, 3))
    pivot = _tensor(path, "blendshape_rig 'pivot'", rig_data.get("pivot"), (3,))
    faces = rig_data.get("faces")  # optional: checkpoints before it lack it
    if faces is not None:
        faces = _tensor(path, "blendshape_rig 'faces'", faces, (None, 3), floating=False)
        if faces.numel() and not 0 <= int(faces.min()) <= int(faces.max()) < count:
            raise CheckpointError(f"checkpoint {path}: blendshape_rig 'faces' indexes vertices outside [0, {count})")
    vertex = _tensor(path, "gaussians 'vertex'", g.get("vertex"), (None,), floating=False)
    n = vertex.shape[0]
    if n and (int(vertex.min()) < 0 or int(vertex.max()) >= count):
        raise CheckpointError(f"checkpoint {path}: gaussians 'vertex' indexes vertices outside [0, {count})")
    shapes = {"offset": (n, 3), "rotation": (n, 4), "log_scale": (n, 3), "opacity_logit": (n,),
              "sh": (n, sh_coeff_count(sh_degree), 3)}
    values = {k: _tensor(path, f"gaussians {k!r}", g.get(k), shape) for k, shape in shapes.items()}
    background = payload["background"]
    if not (isinstance(background, list | tuple) and len(background) == 3
            and all(isinstance(c, int | float) and math.isfinite(c) for c in background)):
        raise CheckpointError(f"checkpoint {path}: 'background' must be 3 finite numbers, got {background!r}")
    gaussians = VertexBoundGaussians(vertex, sh_degree, config.covariance)
    with torch.no_grad():
        for key, value in values.items():
            getattr(gaussians, key).copy_(value)
    speaker = ArkitSpeaker(config, BlendshapeRig(rest, morphs, pivot, faces), gaussians, camera, background,
                           optional_track(path, payload, "pose_track", 6),
                           optional_track(path, payload, "motion_track", len(config.blendshapes)),
                           source_from(path, payload))
    speaker.audio_model = audio_model_from(path, payload)
    return speaker.eval()


__all__ = ["arkit_payload", "audio_model_entry", "audio_model_from", "load_arkit_payload", "optional_track",
           "plain_entry", "source_from"]
