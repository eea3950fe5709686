#version 460
// Translucent shading of a tool or marker: a headlight term so the shape reads in 3D, darker
// back faces (seen through the front ones), and opacity that grows towards the silhouette so
// the outline stays visible even where the surface is faint.
#extension GL_GOOGLE_include_directive : require
#include "overlay.glsl"

layout(location = 0) in vec3 v_normal;
layout(location = 1) in vec3 v_to_eye;

layout(location = 0) out vec4 out_color;

void main() {
    vec3 n = normalize(v_normal);
    vec3 v = normalize(v_to_eye);
    float facing = abs(dot(n, v));
    float shade = (0.45 + 0.55 * facing) * (gl_FrontFacing ? 1.0 : 0.6);
    float rim = pow(1.0 - facing, 3.0);
    float alpha = clamp(item.color.a * (1.0 + 2.0 * rim), 0.0, 1.0);
    out_color = vec4(item.color.rgb * shade, alpha);
}
