"""`speaker.ckpt`: one torch.save file of plain tensors/numbers/strings/lists/dicts, read with weights_only=True.

A checkpoint from a stranger must never run code, so loading refuses anything the weights-only unpickler
refuses (custom classes, `__reduce__` payloads) and reports which entries are missing or mis-shaped.
"""

from __future__ import annotations

import os
import pickle
from pathlib import Path

import numpy as np
import torch

from gaussiantalker.sdk.camera import Camera
from gaussiantalker.sdk.config import SpeakerConfig
from gaussiantalker.sdk.errors import CameraError, CheckpointError

from .flame import FlameArrays
from .speaker import Speaker

FORMAT = "gaussiantalker-speaker"
VERSION = 1
REQUIRED_KEYS = ("format", "version", "config", "flame", "shape", "parent", "translator", "latent_pose",
                 "gaussians", "camera", "background")


def _flame_to_dict(arrays: FlameArrays) -> dict:
    """FLAME arrays with numpy arrays turned into tensors (the weights-only unpickler refuses numpy objects)."""
    return {k: torch.from_numpy(np.ascontiguousarray(v)) if isinstance(v, np.ndarray) else v
            for k, v in arrays.to_dict().items()}


def _flame_from_dict(data: dict) -> FlameArrays:
    if not isinstance(data, dict):
        raise CheckpointError("checkpoint entry 'flame' must be a dict of arrays")
    return FlameArrays.from_dict({k: v.numpy() if isinstance(v, torch.Tensor) else v for k, v in data.items()})


def save_checkpoint(speaker: Speaker, path: str | os.PathLike) -> Path:
    """Write `speaker` as a weights-only-loadable checkpoint (atomically: temp file + rename)."""
    path = Path(path)
    payload = {
        "format": FORMAT,
        "version": VERSION,
        "config": speaker.config.to_dict(),
        "flame": _flame_to_dict(speaker.flame_arrays),
        "shape": speaker.shape.detach().clone(),
        "parent": speaker.gaussians.parent.detach().clone(),
        "translator": speaker.translator.state_dict(),
        "latent_pose": speaker.latent_pose.state_dict(),
        "gaussians": {k: v for k, v in speaker.gaussians.state_dict().items() if k not in ("parent", "vertex_ids")},
        "camera": speaker.camera.to_dict(),
        "background": list(speaker.background),
        "pose_track": None if speaker.pose_track is None else speaker.pose_track.clone(),
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        torch.save(payload, tmp)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def _unpickler_reason(exc: Exception) -> str:
    """The one informative line of torch's long weights-only error message."""
    lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
    for index, line in enumerate(lines):
        if line.startswith("WeightsUnpickler error:"):
            detail = line.removeprefix("WeightsUnpickler error:").strip()
            return detail or (lines[index + 1] if index + 1 < len(lines) else "unsupported content")
    return lines[0] if lines else type(exc).__name__


def read_checkpoint(path: str | os.PathLike) -> dict:
    """torch.load with weights_only=True; CheckpointError for unsafe, unreadable or incomplete files."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path} does not exist")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        raise CheckpointError(f"refusing to load {path}: the weights-only unpickler rejected it, so it is either "
                              f"not a torch.save file of plain tensors/numbers/strings/lists/dicts or it would "
                              f"run code when unpickled ({_unpickler_reason(exc)})") from exc
    except Exception as exc:  # zip/pickle corruption surfaces as several exception types
        raise CheckpointError(f"cannot read checkpoint {path}: {exc}") from exc
    if not isinstance(payload, dict):
        raise CheckpointError(f"checkpoint {path} holds a {type(payload).__name__}, not a speaker dict")
    missing = [k for k in REQUIRED_KEYS if k not in payload]
    if missing:
        raise CheckpointError(f"checkpoint {path} is missing entries: {', '.join(missing)}")
    if payload["format"] != FORMAT or payload["version"] != VERSION:
        raise CheckpointError(f"checkpoint {path} is {payload['format']!r} version {payload['version']!r}; "
                              f"this SDK reads {FORMAT!r} version {VERSION}")
    return payload


def load_checkpoint(path: str | os.PathLike) -> Speaker:
    """Rebuild the torch Speaker from a checkpoint; every shape is checked (strict state-dict loading)."""
    payload = read_checkpoint(path)
    try:
        config = SpeakerConfig.from_dict(payload["config"])
        camera = Camera.from_dict(payload["camera"])
    except (TypeError, ValueError, CameraError) as exc:
        raise CheckpointError(f"checkpoint {path}: invalid config or camera: {exc}") from exc
    flame = _flame_from_dict(payload["flame"])
    parent = payload["parent"]
    if not isinstance(parent, torch.Tensor) or parent.ndim != 1 or parent.dtype.is_floating_point:
        raise CheckpointError(f"checkpoint {path}: 'parent' must be a 1-D integer tensor of triangle indices")
    if parent.numel() and (int(parent.min()) < 0 or int(parent.max()) >= flame.n_faces):
        raise CheckpointError(f"checkpoint {path}: 'parent' indexes triangles outside [0, {flame.n_faces})")
    if flame.n_expr != config.n_expr or flame.n_shape != config.n_shape:
        raise CheckpointError(f"checkpoint {path}: FLAME model has {flame.n_shape} shape / {flame.n_expr} expression "
                              f"bases but the config says {config.n_shape} / {config.n_expr}")
    try:
        speaker = Speaker(config, flame, payload["shape"], parent, camera, payload["background"],
                          payload.get("pose_track"))
    except (RuntimeError, ValueError, TypeError) as exc:
        raise CheckpointError(f"checkpoint {path}: shape, background or pose track is malformed: {exc}") from exc
    for name, module, state in (("translator", speaker.translator, payload["translator"]),
                                ("latent_pose", speaker.latent_pose, payload["latent_pose"])):
        try:
            module.load_state_dict(state, strict=True)
        except (RuntimeError, TypeError, AttributeError) as exc:
            raise CheckpointError(f"checkpoint {path}: {name} weights do not fit the config: {exc}") from exc
    gaussian_state = dict(payload["gaussians"])
    gaussian_state["parent"] = speaker.gaussians.parent
    gaussian_state["vertex_ids"] = speaker.gaussians.vertex_ids
    try:
        speaker.gaussians.load_state_dict(gaussian_state, strict=True)
    except (RuntimeError, TypeError, AttributeError) as exc:
        raise CheckpointError(f"checkpoint {path}: gaussian parameters do not fit: {exc}") from exc
    return speaker.eval()
