// One entry of LAO's sample table (src/ao/lao.rs LaoSample): sample m of ray k, the same for
// every voxel.
struct LaoSample {
    vec3 frac;    // trilinear weights of the footprint's upper corner
    int offset;   // index of the footprint's lower corner relative to the voxel's own
};
