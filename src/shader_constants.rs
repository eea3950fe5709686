//! Constants that Rust and the shaders share, written once here. build.rs includes this file and
//! writes each one into the generated GLSL include `constants.glsl`; the Rust modules re-export
//! them where they belong. Plain `const` items only: build.rs compiles this file on its own.

/// V_AO and V_PAO hold AO in [0, 1] as 16-bit unorm: stored q = round(a * UNORM16_MAX), read
/// a = q / UNORM16_MAX (within 0.5 / 65535 = 7.6e-6 of the f32 value; 2 bytes a voxel).
pub const UNORM16_MAX: f32 = 65535.0;
/// The ray caster stops a ray once its opacity reaches this: what lies behind can then change
/// no channel of an 8-bit pixel by half a level (1 - alpha < 0.5 / 255).
pub const OPAQUE_ALPHA: f32 = 1.0 - 0.5 / 255.0;
/// Bricks of 2^BRICK_SHIFT voxels per axis for LAO's exact empty-space skipping.
pub const BRICK_SHIFT: u32 = 2;
/// Workgroup size of the LAO kernel (lao.comp, cao_update.comp): rows of voxels along x. On
/// lavapipe this measured 2-3x faster than 4x4x4 for the same kernel (bench lao, phantom-64).
pub const LAO_GROUP: [u32; 3] = [8, 8, 1];
/// Edge of the occupancy bricks, in voxels.
pub const BRICK: usize = 1 << BRICK_SHIFT;
/// Depth of an empty clip-map interval: `EMPTY_IN > z > EMPTY_OUT` holds for no z.
pub const EMPTY_IN: f32 = 1e30;
pub const EMPTY_OUT: f32 = -1e30;
/// SH visibility marches stop once the transmittance falls below this.
pub const SH_T_MIN: f64 = 1.0 / 1024.0;
/// Y_0 = 1 / (2 sqrt(pi)) = 1 / sqrt(4 pi): the constant SH band, and the bound of every
/// visibility coefficient.
pub const Y0: f64 = 0.282_094_791_773_878_14;
/// Most bins a local histogram has (`--hist-bins`).
pub const HIST_MAX_BINS: u32 = 256;
/// Most dimensions the clustering packs a local histogram into (histogram_assign.comp).
pub const HIST_MAX_PACKED: u32 = 32;
/// The cluster id histogram_assign.comp gives a flat voxel's second hemisphere: the same as its
/// first's (the host resolves it).
pub const SAME_AS_FRONT: u32 = u32::MAX;
/// Bricks of 2^HIST_BRICK_SHIFT voxels per axis for the local histograms' clear bricks
/// (src/ao/histogram.rs clear_bricks).
pub const HIST_BRICK_SHIFT: u32 = 3;
/// V_AO is stored in bricks of 2^AO_BRICK_SHIFT voxels per axis, only those where some voxel's
/// AO can differ from 1 (src/ao/pool.rs).
pub const AO_BRICK_SHIFT: u32 = 3;
/// A brick table's entry for a brick V_AO does not store: every voxel of it has AO 1.
pub const AO_NONE: u32 = u32::MAX;
/// A brick table whose first word is this stands for V_AO stored whole, x fastest (a
/// precompute's V_PAO).
pub const AO_WHOLE: u32 = u32::MAX - 1;
/// Bricks of 2^RAY_BRICK_SHIFT voxels per axis for the ray caster's exact empty-space skipping
/// (src/render/empty_space.rs).
pub const RAY_BRICK_SHIFT: u32 = 3;
/// The ray caster's clip state of a brick (src/clip/bricks.rs): no tool hides any of it; 1 + t:
/// tool t hides all of it; a tool's surface may cross it (each sample tests the maps).
pub const CLIP_BRICK_OPEN: u32 = 0;
pub const CLIP_BRICK_CUT: u32 = 255;
/// At most this many tools clip at once.
pub const MAX_TOOLS: usize = 8;
/// At most this many boxes in a downsampled volume, over its levels (`app::inset`: two at full
/// resolution, one at half; raycast.frag picks a box's images by a three-way branch).
pub const MAX_INSETS: usize = 3;
/// Minor (tube) radius of the unit torus (major radius 1, around local Z).
pub const TORUS_MINOR: f32 = 0.35;
/// `ClipTool.offsets.w`: which built-in shape a tool is, for its exact surface normal on cut
/// faces (raycast.frag); a mesh takes its normal from its clip map.
pub const SHAPE_MESH: u32 = 0;
pub const SHAPE_SPHERE: u32 = 1;
pub const SHAPE_BOX: u32 = 2;
pub const SHAPE_CYLINDER: u32 = 3;
pub const SHAPE_TORUS: u32 = 4;
/// The features the ray caster is specialised on (raycast.frag's FLAGS, constant_id 0): the code
/// of a feature that is off is not compiled in. lavapipe (gallivm) runs both sides of every
/// branch, masked, even where the condition is the same for every pixel, so a feature switched
/// off by a uniform would still cost its reads (docs/design.md, "Shading and sampling").
pub const RAY_PREINTEGRATED: u32 = 1;
pub const RAY_JITTER: u32 = 1 << 1;
pub const RAY_TRICUBIC: u32 = 1 << 2;
pub const RAY_SKIP_EMPTY: u32 = 1 << 3;
pub const RAY_LABELS: u32 = 1 << 4;
pub const RAY_CLIPPING: u32 = 1 << 5;
pub const RAY_GLOW: u32 = 1 << 6;
pub const RAY_ISO: u32 = 1 << 7;
pub const RAY_CLIP_BRICKS: u32 = 1 << 8;
pub const RAY_INSET: u32 = 1 << 9;
/// V_AO modulates the ambient and part of the diffuse term.
pub const RAY_AO: u32 = 1 << 10;
/// The local histograms' colour bleeding, and their scattering (both read E).
pub const RAY_BLEEDING: u32 = 1 << 11;
pub const RAY_SCATTERING: u32 = 1 << 12;
/// SH environment light through the visibility volume.
pub const RAY_SH: u32 = 1 << 13;
/// Variance opacity modulation.
pub const RAY_VARIANCE: u32 = 1 << 14;
/// Diffuse or specular light (the gradient is read).
pub const RAY_LIT: u32 = 1 << 15;
/// The first eye writes its record (colour and surface depths per pixel), which the second
/// eye reads with RAY_REPROJECT (docs/design.md, "The second eye").
pub const RAY_RECORD: u32 = 1 << 16;
pub const RAY_REPROJECT: u32 = 1 << 17;
/// V_AO (and every inset's) is stored in bricks through a table (src/ao/pool.rs).
pub const RAY_AO_BRICKS: u32 = 1 << 18;
/// A first-eye pixel shows an opaque surface where its opacity went from 5 % to opaque within a
/// depth over which the two eyes' parallax stays below this many pixels (deeper, what it
/// composited lies differently behind the surface for the other eye).
pub const REPROJECT_PARALLAX: f32 = 0.5;
/// That depth ends where the opacity reaches this (what comes after adds at most 10 % of the
/// colour), on a ray that ends opaque.
pub const REPROJECT_BACK_ALPHA: f32 = 0.9;
/// The four first-eye pixels a second-eye pixel interpolates lie on one surface where their
/// depths differ by at most this many pixel footprints (more: an edge, or a surface steeper
/// than 63 degrees to the view).
pub const REPROJECT_SLOPE: f32 = 2.0;
/// ... and their colours differ by at most this much per channel (more: detail that
/// interpolation between them would blur, and that the second eye's own rays resolve).
pub const REPROJECT_CONTRAST: f32 = 16.0 / 255.0;
/// The longest search, in first-eye pixels, along the second eye's ray (longer: cast it).
pub const REPROJECT_MAX_MARCH: u32 = 2048;
