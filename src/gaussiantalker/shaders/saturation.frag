#version 330 core
// One source for GLSL 3.30 core, 4.10 core and ES 3.00 (OpenGL 3.3/4.1, OpenGL ES 3.0, WebGL 2): the runtime replaces
// the #version line above with each target's header, nothing else (docs/shaders.md).
// Saturation mark of the opt-in early stop (RenderSettings.early_stop; docs/numerics.md, "Early stop of saturated
// pixels"): a full-screen pass into a depth-only framebuffer that keeps the fragment, so writes depth, where the
// splats accumulated so far hold 1 - T with T < TRANSMITTANCE_MIN; later splats are depth-tested against it.
// Rasterisation only (it chooses which fragments later splats try), no contract maths: only main, no torch twin.
// #defines injected by the runtime after the header (runtime/splat/programs.py shader_defines), used here:
//   TRANSMITTANCE_MIN (gaussiantalker.sdk.numerics)

uniform sampler2D u_accumulated;

void main() {
    float transmittance = 1.0 - texelFetch(u_accumulated, ivec2(gl_FragCoord.xy), 0).a;
    if (!(transmittance < TRANSMITTANCE_MIN)) {
        discard;
    }
}
