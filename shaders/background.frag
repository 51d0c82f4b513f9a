#version 330 core
// Background pass, drawn last with the same "under" blend as the splats: (C, 1 - T) becomes
// (C + T * background, 1), i.e. the contract's final colour C + T * background.

uniform vec3 u_background;

out vec4 frag_color;

void main() {
    frag_color = vec4(u_background, 1.0);
}
