"""The exporter: torch speaker -> bundle, in floors that import only downwards (tests/test_layers.py checks it):
`model` (the torch speaker and its maths) <- `export` (graphs, codecs, presets, checkpoints, the bundle) <-
`verify` (the bundle against the torch speaker) <- `demo`, `bench`, `imports` (avatars trained elsewhere) and
`voice` (the built-in audio drivers imported avatars speak with) <- `cli`, `import_cli` and `entry` (the console
scripts).
Every floor may also import `gaussiantalker.sdk` and `gaussiantalker.runtime`."""
