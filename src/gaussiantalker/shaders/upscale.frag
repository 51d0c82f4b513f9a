#version 330 core
// One source for GLSL 3.30 core, 4.10 core and ES 3.00 (OpenGL 3.3/4.1, OpenGL ES 3.0, WebGL 2): the runtime replaces
// the #version line above with each target's header, nothing else (docs/shaders.md).
// Render-scale pass (docs/precision.md): the frame drawn at a fraction of the output size is sampled bilinearly
// (the source texture's LINEAR filter) at each output pixel centre. The framebuffer holds premultiplied (C, 1 - T)
// or the final colour, both of which interpolate linearly. Rasterisation only, no contract maths: no torch twin.

uniform sampler2D u_source;
uniform vec2 u_output_size;

out vec4 frag_color;

void main() {
    frag_color = texture(u_source, gl_FragCoord.xy / u_output_size);
}
