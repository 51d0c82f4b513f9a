"""Importers: avatars trained elsewhere become ordinary speaker checkpoints, and FLAME's model pickle becomes the
FLAME npz (docs/import.md). `formats` reads the files (glTF, PLY, zip, FLAME pickle), `sources` has one importer per
project (LAM, GaussianAvatars) built on them, and `audio_model` checks the audio-to-FLAME/ARKit models both attach.
Imports `model`, `export` (the checkpoint file), `gaussiantalker.sdk` and its own modules."""
