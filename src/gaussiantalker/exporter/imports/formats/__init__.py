"""Readers of the file formats avatars trained elsewhere come in: glTF binaries (`gltf`), Gaussian-splat PLY
(`gaussian_ply`), avatar zips (`avatar_zip`) and FLAME's model pickle (`flame_pkl`), each refusing a damaged or
hostile file with one clear error (docs/untrusted-input.md)."""
