"""Tools run from a source checkout, never installed with the package: `bench` (the benchmarks behind `gt-bench`)
and `browser` (headless Chromium, the browser player's harness and generated assets behind `gt-web`). They may
import anything of `gaussiantalker`; nothing in the package imports them (tests/test_layers.py)."""
