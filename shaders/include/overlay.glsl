// Per-item push constants of the overlay pass (mirrors render::overlay::ItemPush; 96 bytes, within
// the 128 bytes every Vulkan device guarantees).
layout(push_constant) uniform Item {
    mat4 mvp;        // item-local -> clip space of the eye being drawn (view_proj * model)
    vec4 color;      // straight (not premultiplied) RGBA
    vec4 eye_local;  // xyz: the eye's position in item-local units, for the shading
} item;
