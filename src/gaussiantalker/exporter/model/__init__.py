"""The torch speaker and its maths: FLAME (its arrays, the npz loader, the teeth, blendshapes and skinning), the
bound Gaussians and their splat maths, the motion translator, the inpainting generator F, the reference rasterizer,
the speaker that ties them together, and the torch side of compositing. The lowest floor of the exporter: it
imports only `gaussiantalker.sdk`, `gaussiantalker.runtime` and its own modules, never onnx, a bundle writer or any
floor above it."""
