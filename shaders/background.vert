#version 330 core
// Full-screen triangle for the background pass (no vertex buffer: positions come from gl_VertexID). Rasterisation
// only, no contract maths: only main, no torch twin.

void main() {
    vec2 p = vec2(float((gl_VertexID & 1) << 2), float((gl_VertexID & 2) << 1)) - 1.0;
    gl_Position = vec4(p, 0.0, 1.0);
}
