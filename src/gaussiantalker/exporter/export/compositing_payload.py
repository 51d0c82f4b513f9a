"""The reference clip and the inpainting generator as checkpoint content (the `reference` and `inpaint` entries
of `speaker.ckpt`, docs/compositing.md), and back, checked."""

from __future__ import annotations

from pathlib import Path

import torch

from gaussiantalker.sdk.errors import CheckpointError
from gaussiantalker.sdk.reference_clip import ClipLayout, EncodedClip, ReferenceClipError

from ..model.inpainter import InpainterConfig, InpainterNet


def reference_payload(clip: EncodedClip | None) -> dict | None:
    """A clip as checkpoint content: its layout and one uint8 tensor per encoded frame and mask."""
    if clip is None:
        return None

    def as_tensors(entries: list[bytes]) -> list[torch.Tensor]:
        return [torch.frombuffer(bytearray(data), dtype=torch.uint8) for data in entries]

    return {"layout": clip.layout.to_dict(), "frames": as_tensors(clip.frames), "masks": as_tensors(clip.masks)}


def _byte_entries(path: Path, name: str, values) -> list[bytes]:
    if not (isinstance(values, list) and all(isinstance(v, torch.Tensor) and v.dtype == torch.uint8
                                             and v.ndim == 1 for v in values)):
        raise CheckpointError(f"checkpoint {path}: 'reference' {name!r} must be a list of 1-D uint8 tensors "
                              f"(one encoded picture each)")
    return [v.numpy().tobytes() for v in values]


def reference_from_payload(path: Path, data, track_frames: int | None) -> EncodedClip | None:
    """The checkpoint's clip, every frame and mask decoded once and checked (CheckpointError naming the problem)."""
    if data is None:
        return None
    if not isinstance(data, dict) or set(data) != {"layout", "frames", "masks"}:
        raise CheckpointError(f"checkpoint {path}: 'reference' must hold exactly 'layout', 'frames' and 'masks'")
    try:
        clip = EncodedClip(ClipLayout.from_dict(data["layout"]), _byte_entries(path, "frames", data["frames"]),
                           _byte_entries(path, "masks", data["masks"]))
        clip.check(track_frames)
    except ReferenceClipError as exc:
        raise CheckpointError(f"checkpoint {path}: {exc}") from None
    return clip


def inpainter_payload(model: InpainterNet | None) -> dict | None:
    """The generator as checkpoint content: its config and state dict."""
    if model is None:
        return None
    return {"config": model.config.to_dict(), "state": model.state_dict()}


def inpainter_from_payload(path: Path, data) -> InpainterNet | None:
    """The checkpoint's inpainting generator (strictly loaded), or None."""
    if data is None:
        return None
    if not isinstance(data, dict) or set(data) != {"config", "state"} or not isinstance(data["state"], dict):
        raise CheckpointError(f"checkpoint {path}: 'inpaint' must hold exactly 'config' and a 'state' dict")
    try:
        model = InpainterNet(InpainterConfig.from_dict(data["config"]))
        model.load_state_dict(data["state"], strict=True)
    except (ValueError, TypeError, RuntimeError) as exc:
        raise CheckpointError(f"checkpoint {path}: inpainting generator does not load: {exc}") from None
    for name, tensor in model.state_dict().items():
        if not torch.isfinite(tensor).all():
            raise CheckpointError(f"checkpoint {path}: inpainting generator weight {name!r} is not finite")
    return model.eval()
