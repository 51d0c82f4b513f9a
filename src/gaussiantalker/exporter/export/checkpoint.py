"""`speaker.ckpt`: one torch.save file of plain tensors/numbers/strings/lists/dicts, read with weights_only=True.

A checkpoint from a stranger must never run code, so loading refuses anything the weights-only unpickler
refuses (custom classes, `__reduce__` payloads) and reports which entries are missing or mis-shaped.
"""

from __future__ import annotations

import functools
import math
import os
import pickle
import zipfile
from collections.abc import Callable
from dataclasses import fields
from pathlib import Path
from typing import TypeVar

import numpy as np
import torch

from gaussiantalker.sdk.camera import Camera
from gaussiantalker.sdk.config import SpeakerConfig
from gaussiantalker.sdk.errors import CameraError, CheckpointError
from gaussiantalker.sdk.files import atomic_write
from gaussiantalker.sdk.rig import RIGS
from gaussiantalker.sdk.zip_reader import READ_ERRORS, check_member

from ..model.arkit_speaker import ArkitSpeaker
from ..model.flame import FlameArrays
from ..model.speaker import MOTION_POSE_COLUMNS, Speaker
from .arkit_checkpoint import (
    arkit_payload,
    audio_model_entry,
    audio_model_from,
    load_arkit_payload,
    optional_track,
    plain_entry,
    source_from,
)
from .compositing_payload import inpainter_from_payload, inpainter_payload, reference_from_payload, reference_payload

FORMAT = "gaussiantalker-speaker"
VERSION = 1
# The entries every checkpoint has, and (a FLAME speaker, no "rig" entry) the FLAME speaker's own.
COMMON_KEYS = ("format", "version")
REQUIRED_KEYS = ("format", "version", "config", "flame", "shape", "parent", "translator", "latent_pose",
                 "gaussians", "camera", "background")
_FLAME_FLOAT_KEYS = ("v_template", "shapedirs", "exprdirs", "posedirs", "J_regressor", "lbs_weights")
_FLAME_INT_KEYS = ("faces", "teeth_anchors", "regions")
# Entries of plain data (no tensors), checked so before any is compared or converted.
PLAIN_KEYS = ("format", "version", "rig", "config", "camera", "background", "source", "sh_degree")
# The most a checkpoint's records may state uncompressed, together (a 100k-Gaussian avatar's is ~0.2 GB).
MAX_CHECKPOINT_BYTES = 16 << 30
T = TypeVar("T")


def _flame_to_dict(arrays: FlameArrays) -> dict:
    """FLAME arrays with numpy arrays turned into tensors (the weights-only unpickler refuses numpy objects)."""
    return {k: torch.from_numpy(np.ascontiguousarray(v)) if isinstance(v, np.ndarray) else v
            for k, v in arrays.to_dict().items()}


def _flame_from_dict(path: Path, data: object) -> FlameArrays:
    """FLAME arrays from checkpoint tensors: each key is type- and dtype-checked before any conversion."""
    if not isinstance(data, dict):
        raise CheckpointError(f"checkpoint {path}: entry 'flame' must be a dict of arrays")
    for key in _FLAME_FLOAT_KEYS + _FLAME_INT_KEYS:
        if key in data:
            _tensor_entry(path, f"FLAME {key!r}", data[key], floating=key in _FLAME_FLOAT_KEYS)
    for key, kind in (("parents", int), ("region_names", str)):
        value = data.get(key, [])
        if not (isinstance(value, list | tuple) and all(isinstance(v, kind) for v in value)):
            raise CheckpointError(f"checkpoint {path}: FLAME {key!r} must be a list of {kind.__name__}s")
    try:
        return FlameArrays.from_dict({k: v.numpy() if isinstance(v, torch.Tensor) else v for k, v in data.items()})
    except (TypeError, ValueError) as exc:
        raise CheckpointError(f"checkpoint {path}: FLAME model is malformed: {exc}") from exc
    except CheckpointError as exc:  # FlameArrays' own checks, told with the file
        raise CheckpointError(f"checkpoint {path}: {exc}") from None


def _tensor_entry(path: Path, label: str, value: object, floating: bool) -> torch.Tensor:
    """`value` must be a real tensor of a floating-point (else integer) dtype; floating values must be finite."""
    if not isinstance(value, torch.Tensor):
        raise CheckpointError(f"checkpoint {path}: {label} must be a tensor, got {type(value).__name__}")
    integer = not value.is_floating_point() and not value.is_complex() and value.dtype != torch.bool
    if (value.is_floating_point() if floating else integer) is False:
        expected = "a floating-point" if floating else "an integer"
        raise CheckpointError(f"checkpoint {path}: {label} has dtype {value.dtype}, expected {expected} tensor")
    if floating and not bool(torch.isfinite(value).all()):
        raise CheckpointError(f"checkpoint {path}: {label} contains NaN or infinite values")
    return value


def _check_state(path: Path, name: str, module: torch.nn.Module, state: object, skip: tuple[str, ...] = ()) -> dict:
    """A state dict of tensors whose dtypes match the module's (shapes are checked by strict loading)."""
    if not isinstance(state, dict):
        raise CheckpointError(f"checkpoint {path}: {name!r} must be a dict of tensors, got {type(state).__name__}")
    own = module.state_dict()
    for key, value in state.items():
        if key not in skip:
            floating = key not in own or own[key].is_floating_point()
            _tensor_entry(path, f"{name} entry {key!r}", value, floating=floating)
    return dict(state)


def _check_config(path: Path, config: SpeakerConfig) -> None:
    """Sizes and rates must be positive ints (fps 0 would only fail later, dividing by zero in the exporter)."""
    not_sizes = ("translator", "binding", "expression_names")
    sizes = {f.name: getattr(config, f.name) for f in fields(config) if f.name not in not_sizes}
    sizes.update({f"translator.{f.name}": getattr(config.translator, f.name) for f in fields(config.translator)
                  if f.name != "conv_strides"})
    for key, value in sizes.items():
        low = 0 if key in ("speaker_id", "sh_degree") else 1
        if not isinstance(value, int) or isinstance(value, bool) or value < low:
            raise CheckpointError(f"checkpoint {path}: config {key} must be an int >= {low}, got {value!r}")
    try:
        config.check_timing()
    except ValueError as exc:
        raise CheckpointError(f"checkpoint {path}: {exc}") from None


def _check_extras(path: Path, payload: dict) -> None:
    """shape, background and pose track: right kinds of values before the Speaker is built from them."""
    _tensor_entry(path, "'shape'", payload["shape"], floating=True)
    background = payload["background"]
    if not (isinstance(background, list | tuple) and len(background) == 3
            and all(isinstance(c, int | float) and math.isfinite(c) for c in background)):
        raise CheckpointError(f"checkpoint {path}: 'background' must be 3 finite numbers, got {background!r}")
    track = payload.get("pose_track")
    if track is not None:
        _tensor_entry(path, "'pose_track'", track, floating=True)
        if track.ndim != 2 or track.shape[0] < 1 or track.shape[1] != 6:
            raise CheckpointError(f"checkpoint {path}: 'pose_track' has shape {list(track.shape)}, "
                                  f"expected [T >= 1, 6]")


def save_checkpoint(speaker: Speaker | ArkitSpeaker, path: str | os.PathLike) -> Path:
    """Write `speaker` as a weights-only-loadable checkpoint (atomically: temp file + rename)."""
    path = Path(path)
    if isinstance(speaker, ArkitSpeaker):
        with atomic_write(path) as handle:
            torch.save({"format": FORMAT, "version": VERSION, **arkit_payload(speaker)}, handle)
        return path
    payload = {
        "format": FORMAT,
        "version": VERSION,
        "config": speaker.config.to_dict(),
        "flame": _flame_to_dict(speaker.flame_arrays),
        "shape": speaker.shape.detach().clone(),
        "parent": speaker.gaussians.parent.detach().clone(),
        # None: no trained translator (an imported avatar; it may carry an attached "audio_model" instead).
        "translator": None if speaker.translator is None else speaker.translator.state_dict(),
        "latent_pose": speaker.latent_pose.state_dict(),
        "gaussians": {k: v for k, v in speaker.gaussians.state_dict().items() if k not in ("parent", "vertex_ids")},
        "camera": speaker.camera.to_dict(),
        "background": list(speaker.background),
        "pose_track": None if speaker.pose_track is None else speaker.pose_track.clone(),
        "reference": reference_payload(speaker.reference),
        "inpaint": inpainter_payload(speaker.inpaint),
        "motion_track": None if speaker.motion_track is None else speaker.motion_track.clone(),
        "audio_model": audio_model_entry(speaker.audio_model),
        "source": speaker.source,
    }
    with atomic_write(path) as handle:
        torch.save(payload, handle)
    return path


def _unpickler_reason(exc: Exception) -> str:
    """The one informative line of torch's long weights-only error message."""
    lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
    for index, line in enumerate(lines):
        if line.startswith("WeightsUnpickler error:"):
            detail = line.removeprefix("WeightsUnpickler error:").strip()
            return detail or (lines[index + 1] if index + 1 < len(lines) else "unsupported content")
    return lines[0] if lines else type(exc).__name__


def _check_archive(path: Path) -> None:
    """A torch.save zip's members checked before torch reads them (docs/untrusted-input.md, "Checkpoints"): torch
    sizes each record by the uncompressed size the zip states, so a member stating more than its compressed bytes
    can hold (a bomb or a lying header), an encrypted one or one of an unknown method is refused here, by name."""
    if not zipfile.is_zipfile(path):
        return  # not a zip: torch.load reads (and refuses) it
    budget = MAX_CHECKPOINT_BYTES
    try:
        with zipfile.ZipFile(path) as archive:
            for info in archive.infolist():
                check_member(info, f"checkpoint {path}: record {info.filename[:80]}", CheckpointError, budget)
                budget -= info.file_size
    except READ_ERRORS as exc:
        raise CheckpointError(f"cannot read checkpoint {path}: truncated or not a torch.save file "
                              f"({' '.join(str(exc).split())[:120]})") from None


# Longest error message: a mis-shaped entry's message may quote a tensor or torch's list of every mismatch.
MAX_MESSAGE = 400


def _one_line_errors(function: Callable[[str | os.PathLike], T]) -> Callable[[str | os.PathLike], T]:
    """`function` with its CheckpointErrors told in one line of at most MAX_MESSAGE characters."""
    @functools.wraps(function)
    def wrapped(path: str | os.PathLike) -> T:
        try:
            return function(path)
        except CheckpointError as exc:
            text = " ".join(str(exc).split())
            if text == str(exc) and len(text) <= MAX_MESSAGE:
                raise
            raise CheckpointError(text[:MAX_MESSAGE] + ("..." if len(text) > MAX_MESSAGE else "")) \
                from exc.__cause__
    return wrapped


@_one_line_errors
def read_checkpoint(path: str | os.PathLike) -> dict:
    """torch.load with weights_only=True; CheckpointError for unsafe, unreadable or incomplete files."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path} does not exist")
    if path.stat().st_size == 0:
        raise CheckpointError(f"checkpoint {path} is empty (0 bytes)")
    _check_archive(path)
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        raise CheckpointError(f"refusing to load {path}: the weights-only unpickler rejected it, so it is either "
                              f"not a torch.save file of plain tensors/numbers/strings/lists/dicts or it would "
                              f"run code when unpickled ({_unpickler_reason(exc)})") from exc
    except Exception as exc:  # zip/pickle corruption surfaces as several exception types
        detail = next((line.strip() for line in str(exc).splitlines() if line.strip()), type(exc).__name__)
        raise CheckpointError(f"cannot read checkpoint {path}: truncated or not a torch.save file ({detail})") from exc
    if not isinstance(payload, dict):
        raise CheckpointError(f"checkpoint {path} holds a {type(payload).__name__}, not a speaker dict")
    for key in PLAIN_KEYS:
        plain_entry(path, repr(key), payload.get(key))
    rig = payload.get("rig", "flame")
    if rig not in RIGS:
        raise CheckpointError(f"checkpoint {path} has rig {rig!r}; this SDK reads {', '.join(RIGS)}")
    missing = [k for k in (REQUIRED_KEYS if rig == "flame" else COMMON_KEYS) if k not in payload]
    if missing:
        raise CheckpointError(f"checkpoint {path} is missing entries: {', '.join(missing)}")
    if payload["format"] != FORMAT or payload["version"] != VERSION:
        raise CheckpointError(f"checkpoint {path} is {payload['format']!r} version {payload['version']!r}; "
                              f"this SDK reads {FORMAT!r} version {VERSION}")
    return payload


@_one_line_errors
def load_checkpoint(path: str | os.PathLike) -> Speaker | ArkitSpeaker:
    """Rebuild the torch speaker (a FLAME Speaker, or an ArkitSpeaker for "rig": "arkit") from a checkpoint;
    every entry's type, dtype and shape is checked. A checkpoint is the user's file (docs/untrusted-input.md,
    "Checkpoints"): every refusal is one CheckpointError of one line naming it."""
    return _load_checkpoint(Path(path))


def _load_checkpoint(path: Path) -> Speaker | ArkitSpeaker:
    """load_checkpoint's work (its messages may quote tensors over several lines)."""
    payload = read_checkpoint(path)
    if payload.get("rig") == "arkit":
        return load_arkit_payload(path, payload)
    try:
        config = SpeakerConfig.from_dict(payload["config"])
        camera = Camera.from_dict(payload["camera"])
    except (TypeError, ValueError, CameraError) as exc:
        raise CheckpointError(f"checkpoint {path}: invalid config or camera: {exc}") from exc
    _check_config(path, config)
    flame = _flame_from_dict(path, payload["flame"])
    parent = payload["parent"]
    if not isinstance(parent, torch.Tensor) or parent.ndim != 1 or parent.dtype.is_floating_point:
        raise CheckpointError(f"checkpoint {path}: 'parent' must be a 1-D integer tensor of triangle indices")
    if parent.numel() and (int(parent.min()) < 0 or int(parent.max()) >= flame.n_faces):
        raise CheckpointError(f"checkpoint {path}: 'parent' indexes triangles outside [0, {flame.n_faces})")
    if flame.n_expr != config.n_expr or flame.n_shape != config.n_shape:
        raise CheckpointError(f"checkpoint {path}: FLAME model has {flame.n_shape} shape / {flame.n_expr} expression "
                              f"bases but the config says {config.n_shape} / {config.n_expr}")
    _check_extras(path, payload)
    motion = optional_track(path, payload, "motion_track", config.n_expr + MOTION_POSE_COLUMNS)
    try:
        speaker = Speaker(config, flame, payload["shape"], parent, camera, payload["background"],
                          payload.get("pose_track"), translator=payload["translator"] is not None,
                          motion_track=motion)
    except (RuntimeError, ValueError, TypeError) as exc:
        raise CheckpointError(f"checkpoint {path}: config, shape or pose track do not fit together: {exc}") from exc
    _load_states(path, speaker, payload)
    speaker.audio_model = audio_model_from(path, payload)
    speaker.source = source_from(path, payload)
    track = payload.get("pose_track")
    speaker.reference = reference_from_payload(path, payload.get("reference"),
                                               None if track is None else int(track.shape[0]))
    speaker.inpaint = inpainter_from_payload(path, payload.get("inpaint"))
    return speaker.eval()


def _load_states(path: Path, speaker: Speaker, payload: dict) -> None:
    """Strict state-dict loading of translator, latent-pose MLP and Gaussians, after type/dtype checks."""
    derived = {"parent": speaker.gaussians.parent, "vertex_ids": speaker.gaussians.vertex_ids}
    modules = (("translator", speaker.translator, ()), ("latent_pose", speaker.latent_pose, ()),
               ("gaussians", speaker.gaussians, tuple(derived)))
    for name, module, skip in modules:
        if module is None:  # no trained translator
            continue
        state = _check_state(path, name, module, payload[name], skip)
        if name == "gaussians":
            state.update(derived)
        try:
            module.load_state_dict(state, strict=True)
        except (RuntimeError, TypeError, AttributeError) as exc:
            what = "gaussian parameters do not fit" if name == "gaussians" else f"{name} weights do not fit the config"
            raise CheckpointError(f"checkpoint {path}: {what}: {exc}") from exc
