"""`gt-bench`: every benchmark (frames, sweep, compare, composite, backends, video, clip codecs) and their worker,
quality measures and reports. Imports `model`, `export`, `verify`, `demo`, `gaussiantalker.sdk`,
`gaussiantalker.runtime` and its own modules; never the console scripts."""
