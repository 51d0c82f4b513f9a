"""The built-in voice drivers: audio -> ARKit-52 weights and audio -> FLAME expression + jaw, small ONNX models the
SDK trains on espeak-ng speech whose phonemes are known (docs/voice.md): espeak-ng's phoneme events (`espeak`), the
sentences and voices spoken (`corpus`), the viseme table (`visemes`), the targets it gives (`targets`), training
streams and augmentation (`data`), the network and its hand-built ONNX graph (`model`, `onnx_graph`), training
(`train`), FLAME's expressions fitted to the viseme shapes (`flame_fit`), the measurements (`evaluate`) and where
the committed models live (`paths`). Imports `model` (FLAME's arrays), `imports` (FLAME's lip rings, the audio
model checks), `gaussiantalker.sdk`, `gaussiantalker.runtime` and its own modules; never `demo` or the console
scripts."""
