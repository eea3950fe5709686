#version 460
// Stereo ray caster: front-to-back compositing through the volume with early termination.
// Colour = C_tf * (k * AO + diffuse * |n.l| + w * E_sh), where E_sh = sum_k V_k L_k is the
// environment light seen through the SH visibility volume (Ritschel), optionally times AO, and
// with the local-histogram method C_tf bleeds towards the neighbourhood's colour E.
// Opacity is corrected per mm; depth is written where
// the ray enters visible material, so later geometry (tools, hands) is depth-correct.
#extension GL_GOOGLE_include_directive : require
#include "frame.glsl"

layout(set = 0, binding = 1) uniform sampler3D scalars;
layout(set = 0, binding = 2) uniform sampler3D ambient;
layout(set = 0, binding = 3) uniform sampler1D tf_lut;
// SH visibility, coefficients 4g..4g+3 in texture g, snorm8 of V_k / Y_0 (src/ao/sh.rs).
layout(set = 0, binding = 6) uniform sampler3D sh0;
layout(set = 0, binding = 7) uniform sampler3D sh1;
layout(set = 0, binding = 8) uniform sampler3D sh2;
layout(set = 0, binding = 9) uniform sampler3D sh3;
// var_s of variance opacity modulation (data units squared); read when lighting.w = 1/V_max > 0.
layout(set = 0, binding = 10) uniform sampler3D variance;
// The local-histogram method's bleeding colour E (rgb); read when bleeding.x = W > 0.
layout(set = 0, binding = 11) uniform sampler3D bleeding;

#define CLIP_SET 0
#define CLIP_TOOLS_BINDING 4
#define CLIP_MAPS_BINDING 5
#define CLIP_TOOL_COUNT frame.viewport.z
#include "clip.glsl"

// Which eye (layer of the stereo target) this draw renders.
layout(push_constant) uniform Eye { uint index; } eye;

layout(location = 0) out vec4 out_color;

const float OPAQUE = 0.99;
const float DEPTH_ALPHA = 0.05;

vec4 classify(vec3 t) {
    float s = texture(scalars, t).r;
    return texture(tf_lut, s * frame.value_map.y + frame.value_map.x);
}

// Gradient of the scalar field in mm (central differences, one texel apart).
vec3 gradient_mm(vec3 t) {
    vec3 texel = 1.0 / vec3(textureSize(scalars, 0));
    vec3 mm = frame.extent_mm.xyz * texel;
    float gx = texture(scalars, t + vec3(texel.x, 0, 0)).r - texture(scalars, t - vec3(texel.x, 0, 0)).r;
    float gy = texture(scalars, t + vec3(0, texel.y, 0)).r - texture(scalars, t - vec3(0, texel.y, 0)).r;
    float gz = texture(scalars, t + vec3(0, 0, texel.z)).r - texture(scalars, t - vec3(0, 0, texel.z)).r;
    return vec3(gx, gy, gz) / (2.0 * mm);
}

vec3 sh_dot(vec4 v, int first) {
    return v.x * frame.sh_light[first].rgb + v.y * frame.sh_light[first + 1].rgb
         + v.z * frame.sh_light[first + 2].rgb + v.w * frame.sh_light[first + 3].rgb;
}

// The environment light reaching point t through the volume (Y_0 is folded into sh_light).
vec3 sh_emission(vec3 t) {
    vec3 e = sh_dot(texture(sh0, t), 0);
    if (frame.lighting.y > 4.5) {
        e += sh_dot(texture(sh1, t), 4) + sh_dot(texture(sh2, t), 8) + sh_dot(texture(sh3, t), 12);
    }
    return max(e, vec3(0.0));
}

// Deterministic per-pixel offset in [0,1) that breaks up wood-grain artefacts.
float pixel_jitter(vec2 p) {
    return fract(52.9829189 * fract(dot(p, vec2(0.06711056, 0.00583715))));
}

void main() {
    uint v = eye.index;
    vec2 ndc = gl_FragCoord.xy / frame.viewport.xy * 2.0 - 1.0;
    vec4 near_w = frame.inv_view_proj[v] * vec4(ndc, 0.0, 1.0);
    vec4 far_w = frame.inv_view_proj[v] * vec4(ndc, 1.0, 1.0);
    vec3 a_w = near_w.xyz / near_w.w;
    vec3 b_w = far_w.xyz / far_w.w;
    vec3 o = (frame.tex_from_world * vec4(a_w, 1.0)).xyz;
    vec3 d = (frame.tex_from_world * vec4(b_w, 1.0)).xyz - o;

    // Ray / unit-box intersection in texture space, t in [0,1] along near->far.
    vec3 inv = 1.0 / d;
    vec3 t0 = (vec3(0.0) - o) * inv;
    vec3 t1 = (vec3(1.0) - o) * inv;
    float tn = max(max(min(t0.x, t1.x), min(t0.y, t1.y)), max(min(t0.z, t1.z), 0.0));
    float tf = min(min(max(t0.x, t1.x), max(t0.y, t1.y)), min(max(t0.z, t1.z), 1.0));

    vec3 color = vec3(0.0);
    float alpha = 0.0;
    float depth = 1.0;
    if (tn < tf) {
        float step_mm = frame.extent_mm.w;
        vec3 d_mm = d * frame.extent_mm.xyz;
        float dt = step_mm / length(d_mm);
        vec3 light = -normalize(d_mm);
        float t = tn + dt * pixel_jitter(gl_FragCoord.xy);
        for (int i = 0; i < 8192 && t < tf; i++, t += dt) {
            vec3 p = o + t * d;
            // Shadow-test clipping: the same maps the AO update used.
            if (frame.viewport.z > 0.0 && clipped_world(a_w + t * (b_w - a_w))) continue;
            vec4 c = classify(p);
            // Variance opacity modulation: homogeneous tissue fades, boundaries stay.
            if (frame.lighting.w > 0.0) c.a *= min(texture(variance, p).r * frame.lighting.w, 1.0);
            if (c.a > 0.0) {
                float a = 1.0 - pow(1.0 - min(c.a, 0.9999), step_mm);
                float occl = frame.background.a > 0.5 ? texture(ambient, p).r : 1.0;
                // Colour bleeding (Ropinski et al.): towards the neighbourhood's colour E, the
                // more the neighbourhood occludes (O_env = 1 - A).
                if (frame.bleeding.x > 0.0) {
                    c.rgb = mix(c.rgb, texture(bleeding, p).rgb, frame.bleeding.x * (1.0 - occl));
                }
                vec3 shade = vec3(frame.value_map.z * occl);
                if (frame.value_map.w > 0.0) {
                    vec3 g = gradient_mm(p);
                    float gl = length(g);
                    if (gl > 1e-3) shade += frame.value_map.w * abs(dot(g / gl, light));
                }
                if (frame.lighting.x > 0.0) {
                    float ao_factor = frame.lighting.z > 0.5 ? occl : 1.0;
                    shade += frame.lighting.x * ao_factor * sh_emission(p);
                }
                color += (1.0 - alpha) * a * c.rgb * shade;
                alpha += (1.0 - alpha) * a;
                if (depth == 1.0 && alpha >= DEPTH_ALPHA) {
                    vec4 clip = frame.view_proj[v] * vec4(a_w + t * (b_w - a_w), 1.0);
                    depth = clamp(clip.z / clip.w, 0.0, 1.0);
                }
                if (alpha >= OPAQUE) break;
            }
        }
    }
    out_color = vec4(color + (1.0 - alpha) * frame.background.rgb, alpha);
    gl_FragDepth = depth;
}
