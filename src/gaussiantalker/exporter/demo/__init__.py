"""The demo speaker: a procedural head, its reference clip, translator and inpainter training, and the loudness
targets they train on. Imports `model`, `export`, `verify`, `gaussiantalker.sdk`, `gaussiantalker.runtime` and its
own modules; never the console scripts."""
