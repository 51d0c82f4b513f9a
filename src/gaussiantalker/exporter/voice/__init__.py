"""The built-in voice drivers: audio -> ARKit-52 weights and audio -> FLAME expression + jaw, small ONNX models the SDK
trains on synthetic speech whose phonemes are known (docs/voice.md): espeak-ng's phoneme events (`espeak`), festival's
and flite's (`festival`, `flite`, their shared segment reading `segments`, ARPAbet names `arpabet`), the sentences and
voices spoken (`corpus`), the viseme table (`visemes`), the targets it gives (`targets`), training streams and
augmentation (`data`, a call's channel `channels`), the network and its hand-built ONNX graph (`model`, `onnx_graph`;
its streaming form is built from that graph by `export/voice_stream.py`), training (`train`), FLAME's expressions
fitted to the viseme shapes (`flame_fit`), the measurements (`evaluate`; every driver's mouth in one currency
`mouths`, the clip families `families`, the gates table `gates`), real human recordings fetched at install
(`real_speech`) and aligned by pocketsphinx (`align`), and where the committed models live (`paths`). Imports `model`
(FLAME's arrays), `imports` (FLAME's lip rings, the audio model checks), `gaussiantalker.sdk`,
`gaussiantalker.runtime` and its own modules; never `demo` or the console scripts."""
