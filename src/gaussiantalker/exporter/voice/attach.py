"""The built-in voice driver attached to an imported speaker (docs/voice.md): the ARKit model for an ARKit speaker,
the FLAME model with its expression map fitted on the speaker's own FLAME for a FLAME speaker. Both go through the
importer's audio-model checks (exporter/imports/audio_model.py), as a user's `--audio-model` does.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import onnx

from gaussiantalker.sdk.errors import CheckpointError
from gaussiantalker.sdk.rig import ARKIT_RIG

from ..export.checkpoint import load_checkpoint, save_checkpoint
from ..imports.audio_model import flame_outputs, load_audio_model
from ..model.arkit_speaker import ArkitSpeaker
from ..model.speaker import Speaker
from .flame_fit import bind_to_flame
from .paths import ARKIT_MODEL, FLAME_MODEL


def builtin_audio_model(speaker: Speaker | ArkitSpeaker) -> bytes:
    """The built-in driver for `speaker`, checked and renamed as an attached audio model (ONNX bytes)."""
    if speaker.rig_kind == ARKIT_RIG:
        return load_audio_model(ARKIT_MODEL)
    bound = bind_to_flame(onnx.load(str(FLAME_MODEL)), speaker.flame_arrays)
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / FLAME_MODEL.name
        onnx.save(bound, str(path))
        return load_audio_model(path, flame_outputs(speaker.config.n_expr))


def attach_builtin_voice(checkpoint: str | os.PathLike, output: str | os.PathLike | None = None,
                         replace: bool = False) -> Path:
    """Attach the built-in driver to an imported speaker's checkpoint (written to `output`, default in place);
    CheckpointError for a speaker with a translator of its own, or an attached model unless `replace`."""
    speaker = load_checkpoint(checkpoint)
    if getattr(speaker, "translator", None) is not None:
        raise CheckpointError(f"checkpoint {checkpoint}: this speaker has its own trained translator; the built-in "
                              "voice driver is for imported avatars")
    if speaker.audio_model is not None and not replace:
        raise CheckpointError(f"checkpoint {checkpoint}: an audio model is attached already (--replace swaps it for "
                              "the built-in one)")
    speaker.audio_model = builtin_audio_model(speaker)
    return save_checkpoint(speaker, output or checkpoint)


__all__ = ["attach_builtin_voice", "builtin_audio_model"]
