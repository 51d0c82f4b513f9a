"""Speaker -> bundle: ONNX graphs and their precision, buffer codecs and presets, the checkpoint file, the Gaussian
budget and scene specialisation (with the speech clips they measure on), MNN conversion and the export driver.
Imports `model`, `gaussiantalker.sdk`, `gaussiantalker.runtime` and its own modules; never `verify`, `demo` or
the console scripts."""
