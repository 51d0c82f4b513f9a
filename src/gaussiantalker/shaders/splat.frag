#version 330 core
// One source for GLSL 3.30 core, 4.10 core and ES 3.00 (OpenGL 3.3/4.1, OpenGL ES 3.0, WebGL 2): the runtime replaces
// the #version line above with each target's header, nothing else (docs/shaders.md).
// Per-pixel evaluation of one Gaussian, composited front-to-back by the fixed-function "under" blend
// (src factor ONE_MINUS_DST_ALPHA, dst factor ONE): the framebuffer holds (C, 1 - T).
// The maths is the numerics contract (docs/numerics.md). Each function names its torch twin in
// exporter/model/splat_math.py (same name, same arguments); tests/test_mirror_names.py checks it.
// #defines injected by the runtime after the header (runtime/splat/programs.py shader_defines), never re-typed:
//   contract constants, from gaussiantalker.sdk.numerics (the values the torch reference imports), used here:
//     ALPHA_MAX, ALPHA_MIN, COLOR_LIMIT
//   the GL renderer's own rasterisation settings (runtime/splat/programs.py): none used here.

flat in vec2 v_center;
flat in vec3 v_shape;
flat in float v_radius;
flat in vec4 v_rgba;

out vec4 frag_color;

// Torch twin: `splat_color` (exporter/model/splat_math.py).
// Colour as composited: clamped to +-COLOR_LIMIT (far above any real colour) so float32 sums stay finite
// (docs/numerics.md, "Colour clamp").
vec3 splat_color(vec3 rgb) {
    return clamp(rgb, -COLOR_LIMIT, COLOR_LIMIT);
}

// Torch twin: `splat_alpha` (exporter/model/splat_math.py).
// min(ALPHA_MAX, opacity * exp(power)), power = -1/2 d^T cov2d^-1 d evaluated in the vertex shader's alpha_shape
// form (A, k, q) as -1/2 (A (dx - k dy)^2 + q dy^2). Skipped contributions return 0: a positive power (not
// positive definite) and an alpha below ALPHA_MIN, NaN included (docs/numerics.md, "Alpha and the alpha_shape
// form").
float splat_alpha(vec2 d, vec3 shape, float opacity) {
    float t = d.x - shape.y * d.y;
    float power = -0.5 * (shape.x * t * t + shape.z * d.y * d.y);
    if (power > 0.0) {
        return 0.0;
    }
    float alpha = min(ALPHA_MAX, opacity * exp(power));
    return alpha >= ALPHA_MIN ? alpha : 0.0;
}

void main() {
    // gl_FragCoord.xy is the pixel centre (x + 0.5, y + 0.5) in image coordinates (rows are not flipped).
    vec2 d = gl_FragCoord.xy - v_center;
    // Extent (docs/numerics.md, "Extent radius"): only pixel centres with |dx| <= r and |dy| <= r, decided here,
    // exactly, per pixel.
    if (!(abs(d.x) <= v_radius && abs(d.y) <= v_radius)) {
        discard;
    }
    float alpha = splat_alpha(d, v_shape, v_rgba.a);
    if (!(alpha > 0.0)) {  // skipped by splat_alpha
        discard;
    }
    frag_color = vec4(splat_color(v_rgba.rgb) * alpha, alpha);
}
