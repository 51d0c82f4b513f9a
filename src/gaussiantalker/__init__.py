"""GaussianTalker's deployment SDK: `gaussiantalker.exporter` turns a torch speaker into a bundle,
`gaussiantalker.runtime` plays it without torch, and `gaussiantalker.sdk` holds what both share (docs/README.md).

Imports nothing, so `import gaussiantalker.runtime` never pulls in the exporter (or torch).
"""
