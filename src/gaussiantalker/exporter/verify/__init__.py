"""`gt-export --verify`: a bundle's graphs and frames against its torch speaker, and the random inputs it compares
them on. Imports `model`, `export`, `gaussiantalker.sdk`, `gaussiantalker.runtime` and its own modules; never
`demo` or the console scripts."""
