"""One importer per project whose avatars become speaker checkpoints (docs/import.md): LAM (`lam`) and
GaussianAvatars (`gaussian_avatars`, with its FLAME variant in `gaussian_avatars_flame`). They read files through
`formats`."""
