// Shadow-test clipping against the tools' clip-camera maps (src/clip, src/ao/cao.rs ClipToolGpu).
// Define before inclusion: CLIP_SET, CLIP_TOOLS_BINDING, CLIP_MAPS_BINDING, and CLIP_TOOL_COUNT
// (an expression giving the number of tools). Tool modes: 0 = carve (inside removed), 1 = probe
// (only the inside kept).

struct ClipTool {
    mat4 local_from_index;   // volume index space -> tool-local units
    mat4 local_from_world;   // world -> tool-local units
    vec4 map;                // x: extent, y: texels per local unit, z: resolution, w: mode
    uvec4 offsets;           // x: clip map, y: dilation map (xy; zw: the contraction),
                             // z: SH dilation map (vec4 units), w: SHAPE_* (constants.glsl)
    vec4 sh_map;             // the SH dilation map's own x, y, z (it has its own extent)
};

layout(std430, set = CLIP_SET, binding = CLIP_TOOLS_BINDING) readonly buffer ClipTools {
    ClipTool tools[];
};
layout(std430, set = CLIP_SET, binding = CLIP_MAPS_BINDING) readonly buffer ClipMaps {
    vec4 clip_maps[];
};

// The texel that tool-local point `local` projects to in a map of extent m.x, m.y texels per
// local unit and m.z texels a side (a tool's `map` or `sh_map`), or -1 off the map.
int map_texel(vec4 m, vec3 local) {
    ivec2 px = ivec2(floor((local.xy + m.x) * m.y));
    int res = int(m.z);
    if (any(lessThan(px, ivec2(0))) || any(greaterThanEqual(px, ivec2(res)))) return -1;
    return px.y * res + px.x;
}

int tool_texel(uint t, vec3 local) {
    return map_texel(tools[t].map, local);
}

// Whether `z` lies in one of a clip-map texel's two intervals (the shape's inside along z).
bool in_shape(vec4 c, float z) {
    return (z >= c.x && z <= c.y) || (z >= c.z && z <= c.w);
}

// bit 0: inside the tool's shape; bit 1: inside its dilated shape.
uint tool_test(uint t, vec3 local) {
    int texel = tool_texel(t, local);
    if (texel < 0) return 0u;
    vec4 c = clip_maps[tools[t].offsets.x + uint(texel)];
    vec4 d = clip_maps[tools[t].offsets.y + uint(texel)];
    uint r = 0u;
    if (in_shape(c, local.z)) r |= 1u;
    if (local.z >= d.x && local.z <= d.y) r |= 2u;
    return r;
}

// Whether a tool-local point is inside the tool's shape: tool_test's bit 0, one map read.
bool tool_inside(uint t, vec3 local) {
    int texel = tool_texel(t, local);
    return texel >= 0 && in_shape(clip_maps[tools[t].offsets.x + uint(texel)], local.z);
}

// Whether a tool-local point is inside the tool's shape contracted by the dilation radius (z, w
// of its dilation map; src/clip/mod.rs `dilate`): a probe's cut is out of its reach there.
bool tool_contracted(uint t, vec3 local) {
    int texel = tool_texel(t, local);
    if (texel < 0) return false;
    vec4 d = clip_maps[tools[t].offsets.y + uint(texel)];
    return local.z >= d.z && local.z <= d.w;
}

// bit 0: visible after all tools; bit 1: within the reach of any tool's cut. A `spared` point
// (its voxel's structure is protected) stays visible inside a carving tool; a probe still hides
// all outside it (docs/design.md, selective clipping).
uint clip_test_index(vec3 p, bool spared) {
    bool visible = true;
    bool affected = false;
    for (uint t = 0u; t < uint(CLIP_TOOL_COUNT); t++) {
        vec3 local = (tools[t].local_from_index * vec4(p, 1.0)).xyz;
        uint r = tool_test(t, local);
        bool probe = tools[t].map.w > 0.5;
        bool inside = (r & 1u) != 0u;
        if (probe ? !inside : inside && !spared) visible = false;
        // A carve's cut reaches its dilation; a probe cuts everything outside its shape, which
        // reaches all but its contraction (the paper's Sect. 3.4, conditions inverted).
        if (probe ? !tool_contracted(t, local) : (r & 2u) != 0u) affected = true;
    }
    return (visible ? 1u : 0u) | (affected ? 2u : 0u);
}

// Whether the SH visibility at index-space point p can see any tool's cut: inside some tool's
// shape dilated by the SH reach (offsets.z), or any probe tool (it changes everything outside it).
bool sh_affected_index(vec3 p) {
    for (uint t = 0u; t < uint(CLIP_TOOL_COUNT); t++) {
        ClipTool tool = tools[t];
        if (tool.map.w > 0.5) return true;
        vec3 local = (tool.local_from_index * vec4(p, 1.0)).xyz;
        int texel = map_texel(tool.sh_map, local);
        if (texel < 0) continue;
        vec4 d = clip_maps[tool.offsets.z + uint(texel)];
        if (local.z >= d.x && local.z <= d.y) return true;
    }
    return false;
}
