"""`gt-bench`: every benchmark (frames, sweep, compare, composite, backends, video, clip codecs, LAM's web renderer,
live sessions, ...) and their worker, quality measures and reports. Imports the package (`gaussiantalker.exporter`,
`gaussiantalker.runtime`, `gaussiantalker.sdk`), `tools.browser` and its own modules."""
