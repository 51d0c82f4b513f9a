#version 330 core
// One source for GLSL 3.30 core, 4.10 core and ES 3.00 (OpenGL 3.3/4.1, OpenGL ES 3.0, WebGL 2): the runtime replaces
// the #version line above with each target's header, nothing else (docs/shaders.md).
// Background pass, drawn last with the same "under" blend as the splats: (C, 1 - T) becomes
// (C + T * background, 1), the contract's final colour (docs/numerics.md, "Compositing order and early
// termination"). Not a contract step of its own: only main, no torch twin.

uniform vec3 u_background;

out vec4 frag_color;

void main() {
    frag_color = vec4(u_background, 1.0);
}
