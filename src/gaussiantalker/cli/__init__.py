"""The console scripts: `gt-export` (export.py), `gt-import` (imports.py), and the launchers of `gt-bench`
(bench.py) and `gt-web` (web.py), which run the checkout's tools/. May import `gaussiantalker.exporter`,
`gaussiantalker.runtime` and `gaussiantalker.sdk`; nothing of theirs imports it (tests/test_layers.py)."""
