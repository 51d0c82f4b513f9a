"""Importers: avatars trained elsewhere become ordinary speaker checkpoints, and FLAME's model pickle becomes the
FLAME npz (docs/import.md). Imports `model`, `export` (the checkpoint file), `gaussiantalker.sdk` and its own
modules."""
