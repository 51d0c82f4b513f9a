#version 330 core
// One source for GLSL 3.30 core, 4.10 core and ES 3.00 (OpenGL 3.3/4.1, OpenGL ES 3.0, WebGL 2): the runtime replaces
// the #version line above with each target's header, nothing else (docs/shaders.md).
// Full-screen triangle for the background pass (no vertex buffer: positions come from gl_VertexID). Rasterisation
// only, no contract maths: only main, no torch twin.

void main() {
    vec2 p = vec2(float((gl_VertexID & 1) << 2), float((gl_VertexID & 2) << 1)) - 1.0;
    gl_Position = vec4(p, 0.0, 1.0);
}
