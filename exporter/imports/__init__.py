"""Importers: avatars trained elsewhere become ordinary speaker checkpoints (docs/import.md). Imports `model`,
`export` (the checkpoint file), `gaussiantalker.sdk` and its own modules."""
