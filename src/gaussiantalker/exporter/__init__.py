"""The exporter: torch speaker -> bundle, in floors that import only downwards (tests/test_layers.py checks it):
`model` (the torch speaker and its maths) <- `export` (graphs, codecs, presets, checkpoints, the bundle) <-
`verify` (the bundle against the torch speaker) <- `demo`, `imports` (avatars trained elsewhere) and `voice` (the
built-in audio drivers imported avatars speak with). The console scripts (`gaussiantalker.cli`) sit above it.
Every floor may also import `gaussiantalker.sdk` and `gaussiantalker.runtime`."""
