"""Graph precision knobs, done with onnxruntime's own tools (quantisation and float16 conversion), never by
rewriting graphs by hand.

* int8: dynamic quantisation of the MatMul weights (per output channel, int8), after onnxruntime's quantisation
  pre-processing (shape inference + its graph optimiser, which folds the weights' Transpose nodes into the
  initializers so the quantiser can see them). Convolutions stay float: measured on the demo translator,
  quantising them too (ConvInteger) made it slower and far less accurate (docs/precision.md, "Knobs"), with the
  raw-audio feature extractor the sensitive part.
* fp16: every float initializer and op in half precision, inputs and outputs kept float32 (`keep_io_types`).
"""

from __future__ import annotations

import contextlib
import io
import tempfile
import warnings
from pathlib import Path

import onnx

from .onnx_export import quiet_logger
from .presets import TRANSLATOR_PRECISIONS


def convert_precision(model: onnx.ModelProto, precision: str) -> onnx.ModelProto:
    """`model` at `precision` (fp32: unchanged)."""
    if precision == "fp32":
        return model
    if precision == "fp16":
        from onnxruntime.transformers.float16 import convert_float_to_float16

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return convert_float_to_float16(onnx.ModelProto.FromString(model.SerializeToString()), keep_io_types=True)
    if precision == "int8":
        return _quantize_int8(model)
    raise ValueError(f"unknown graph precision {precision!r} (allowed: {', '.join(TRANSLATOR_PRECISIONS)})")


def _quantize_int8(model: onnx.ModelProto) -> onnx.ModelProto:
    from onnxruntime.quantization import QuantType, quantize_dynamic
    from onnxruntime.quantization.shape_inference import quant_pre_process

    # The quantisation tools read and write files.
    with tempfile.TemporaryDirectory(prefix="gt-int8-") as tmp, quiet_logger("root"), \
            contextlib.redirect_stdout(io.StringIO()), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        source, prepared, quantised = (Path(tmp) / name for name in ("model.onnx", "prepared.onnx", "int8.onnx"))
        onnx.save(model, source)
        quant_pre_process(str(source), str(prepared), skip_symbolic_shape=True)
        quantize_dynamic(str(prepared), str(quantised), weight_type=QuantType.QInt8, per_channel=True,
                         op_types_to_quantize=["MatMul"])
        return onnx.load(str(quantised))


__all__ = ["convert_precision"]
