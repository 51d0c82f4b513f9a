"""The motion translator as an ONNX graph (the `translator` graph of a bundle, docs/bundle-format.md)."""

from __future__ import annotations

from pathlib import Path

import onnx
import torch

from ..model.translator import MotionTranslator, check_audio_length, count_parameters
from ..model.translator_stream import (
    STREAM_DELAY_FRAMES,
    STREAM_REFRESH_FRAMES,
    STREAM_TAIL_FRAMES,
    MotionTranslatorStream,
)
from . import onnx_export  # the module, not its function: tests swap `onnx_export.export_onnx` for a replay
from .window_slices import window_gathers_to_slices

# Largest audio length the exported graph accepts, in video frames (10 minutes at 25 fps).
MAX_EXPORT_FRAMES = 15000


def translator_onnx(model: MotionTranslator, example_frames: int = 8):
    """The translator as an ONNX model proto with a dynamic audio length of 640 * frames samples.

    Input "audio" [1, 640 * frames] float32; outputs "expression" [1, frames, n_expr], "jaw_pose" [1, frames, 3].
    The batch is fixed at 1 (one utterance per call, as the runtime drives it). Uses the project's quiet
    exporter (onnx_export.export_onnx, optimize=False so the normalisation epsilon survives).
    """
    check_audio_length(example_frames * model.samples_per_frame, model.samples_per_frame)
    generator = torch.Generator().manual_seed(0)
    example = 0.1 * torch.randn(1, example_frames * model.samples_per_frame, generator=generator)
    frames = torch.export.Dim("frames", min=1, max=MAX_EXPORT_FRAMES)
    return onnx_export.export_onnx(model.eval(), (example,), ["audio"], ["expression", "jaw_pose"],
                                   dynamic_shapes={"audio": {1: model.samples_per_frame * frames}})


def export_translator_onnx(model: MotionTranslator, path: str | Path, example_frames: int = 8) -> None:
    """Write `translator_onnx(model)` to a .onnx file; weights above 1.5 GB go next to it (`<name>.data`)."""
    proto = translator_onnx(model, example_frames)
    large = count_parameters(model) * 4 > 1.5e9
    onnx.save_model(proto, str(path), save_as_external_data=large, location=Path(path).name + ".data")


def translator_stream_onnx(model: MotionTranslator, refresh_frames: int = STREAM_REFRESH_FRAMES,
                           tail_frames: int | None = STREAM_TAIL_FRAMES, call_refresh: int | None = None,
                           delay_frames: int = STREAM_DELAY_FRAMES):
    """The translator's streaming form (exporter/model/translator_stream.py) as an ONNX model proto, or None when
    its feature encoder cannot stream on the frame grid (`refresh_frames`, `tail_frames`: the export's, or others
    for a bench; `call_refresh` 0: the steady form, which makes no frame's features again; `delay_frames`: the
    frames a row lags its audio, the lookahead each row sees).

    Inputs "audio" [B, n, 640], "state" [B, S], "keep" [1] float32; outputs "expression" [B, n, n_expr], "jaw_pose"
    [B, n, 3], "state_out" [B, S], "delay_frames" [1] int64. Batch and frames are dynamic (a live server stacks its
    sessions on the batch axis)."""
    try:
        stream = MotionTranslatorStream(model.eval(), delay_frames=delay_frames, refresh_frames=refresh_frames,
                                        tail_frames=tail_frames, call_refresh=call_refresh)
    except ValueError:
        return None
    spf = model.samples_per_frame
    example = (0.1 * torch.randn(2, 3, spf, generator=torch.Generator().manual_seed(0)),
               torch.zeros(2, stream.state_size), torch.tensor([2.0]))
    batch = torch.export.Dim("batch", min=1, max=4096)
    frames = torch.export.Dim("frames", min=1, max=MAX_EXPORT_FRAMES)
    model = onnx_export.export_onnx(stream.eval(), example, ["audio", "state", "keep"],
                                    ["expression", "jaw_pose", "state_out", "delay_frames"],
                                    dynamic_shapes={"audio": {0: batch, 1: frames}, "state": {0: batch},
                                                    "keep": None})
    window_gathers_to_slices(model)  # the state's windows read as Slices, not Gathers (window_slices.py)
    return model
