#version 460
// Tools and hand markers over the volume: item-local meshes placed by one matrix per item.
#extension GL_GOOGLE_include_directive : require
#include "overlay.glsl"

layout(location = 0) in vec3 position;
layout(location = 1) in vec3 normal;

layout(location = 0) out vec3 v_normal;
layout(location = 1) out vec3 v_to_eye;

void main() {
    gl_Position = item.mvp * vec4(position, 1.0);
    // Shaded in item-local space: exact for rigid poses with a uniform scale (tools, markers).
    v_normal = normal;
    v_to_eye = item.eye_local.xyz - position;
}
