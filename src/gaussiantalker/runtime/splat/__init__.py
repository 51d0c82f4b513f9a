"""Splatters: Gaussians -> pixels on the numerics contract (docs/numerics.md). `common.py` holds the `Splatter` protocol
and what both kinds prepare alike; `gl.py` (with `programs.py`, `gl_context.py`) the OpenGL one; `cpu.py` the CPU tile
splatter; `choice.py` picks one for `renderer="gl" | "cpu" | "auto"`; `depth_sort.py` orders a frame front to back."""
