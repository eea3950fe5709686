//! The stereo ray caster: both eyes, one draw each in one command buffer, into a two-layer
//! colour + depth target (one layer per eye), sampling the scalar volume, the transfer function and the shared AO volume.

pub mod blue_noise;
pub mod compare;
pub mod empty_space;
pub mod overlay;
pub mod png_out;
pub mod preintegration;
pub mod text;

use crate::gpu::{pipeline, Buffer, Gpu, GpuError, Image, ImageDesc, Result};
use crate::shader_constants::{
    MAX_INSETS, MAX_TOOLS, RAY_AO, RAY_AO_BRICKS, RAY_BLEEDING, RAY_CLIPPING, RAY_CLIP_BRICKS,
    RAY_GLOW, RAY_INSET, RAY_ISO, RAY_JITTER, RAY_LABELS, RAY_LIT, RAY_PREINTEGRATED, RAY_RECORD,
    RAY_REPROJECT, RAY_SCATTERING, RAY_SH, RAY_SKIP_EMPTY, RAY_TRICUBIC, RAY_VARIANCE,
};
use crate::space::View;
use crate::volume::transfer::TransferFunction;
use crate::volume::Volume;
use ash::vk;
use glam::{Mat4, Vec3};
use gpu_allocator::MemoryLocation;
pub use overlay::{
    colors, joint_overlay, markup_overlay, scene_overlay, OverlayItem, OverlayMesh, OverlayRenderer,
};

pub const COLOR_FORMAT: vk::Format = vk::Format::R8G8B8A8_UNORM;
pub const DEPTH_FORMAT: vk::Format = vk::Format::D32_SFLOAT;
const LUT_SIZE: u32 = 4096;

/// The shading modes of the CAO paper: AO alone, Phong alone, and Phong with the AO.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Shading {
    /// C = AO * C_tf: the paper's "CAO" pictures, flat but honest about occlusion.
    Ao,
    /// Blinn-Phong from the gradient with a headlight, no AO.
    Phong,
    /// Blinn-Phong whose ambient term and a share of the diffuse one the AO multiplies.
    #[default]
    PhongAo,
}

impl std::str::FromStr for Shading {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s {
            "ao" => Ok(Shading::Ao),
            "phong" => Ok(Shading::Phong),
            "phong+ao" => Ok(Shading::PhongAo),
            _ => Err(format!("'{s}': expected ao, phong or phong+ao")),
        }
    }
}

impl Shading {
    /// The ray caster's settings for this mode: (ambient, diffuse, specular) weights and
    /// whether the AO modulates them.
    pub fn apply(self, s: &mut RenderSettings) {
        let (ka, kd, ks) = match self {
            Shading::Ao => (1.0, 0.0, 0.0),
            Shading::Phong | Shading::PhongAo => (PHONG[0], PHONG[1], PHONG[2]),
        };
        s.ambient = ka;
        s.diffuse = kd;
        s.specular = ks;
        s.use_ao = self != Shading::Phong;
    }
}

/// Blinn-Phong's ambient, diffuse and specular weights and shininess: a surface facing the
/// headlight, unoccluded, comes out at 0.3 + 0.75 of its TF colour plus a soft white highlight.
pub const PHONG: [f32; 4] = [0.3, 0.75, 0.2, 24.0];
/// The default anisotropy g of the local-histogram method's scattering: forward scattering,
/// as in soft tissue (Henyey-Greenstein fits of tissue give g of 0.8-0.95 at visible
/// wavelengths; a milder g keeps a volume lit from the front visible).
pub const DEFAULT_ANISOTROPY: f32 = 0.3;
/// The share of the diffuse term that the AO multiplies (the rest lights crevices directly).
pub const AO_DIFFUSE_SHARE: f32 = 0.5;
/// Default ray step as a fraction of the smallest voxel spacing.
pub const STEP_PER_SPACING: f32 = 0.5;
/// `render --reference`: the step is this many times finer than the default.
pub const REFERENCE_REFINEMENT: f32 = 16.0;
/// The cut-face layer behind a tool's surface, in voxels of the largest spacing: thick enough
/// that an opaque TF reaches full opacity inside it.
const CUT_LAYER_VOXELS: f32 = 2.0;
/// `--cut-tint`'s weight: the cut face's colour moves this far towards the tint.
pub const CUT_TINT_WEIGHT: f32 = 0.35;

/// Shading knobs of the ray caster.
#[derive(Clone, Copy, Debug)]
pub struct RenderSettings {
    /// Sampling step along the ray in mm; 0 = [`STEP_PER_SPACING`] of the smallest spacing.
    pub step_mm: f32,
    /// Weight of the ambient term (the AO multiplies it).
    pub ambient: f32,
    /// Weight of the gradient (headlight) diffuse term; 0 turns it off.
    pub diffuse: f32,
    /// Weight of the headlight's specular highlight.
    pub specular: f32,
    pub use_ao: bool,
    /// The tool's surface normal lights the cut face (else the data's meaningless gradient).
    pub cut_lighting: bool,
    /// Cut faces tinted towards this colour ([`CUT_TINT_WEIGHT`]), if any.
    pub cut_tint: Option<[f32; 3]>,
    /// Pre-integrated transfer function over each step (else point samples).
    pub preintegrated: bool,
    /// Blue-noise jitter of each ray's start.
    pub jitter: bool,
    /// Cubic B-spline reconstruction of the scalars (else trilinear).
    pub tricubic: bool,
    /// Jump over samples in empty bricks ([`empty_space`]): the same image, faster.
    pub skip_empty: bool,
    /// Test the tools' clip maps only in bricks a tool's surface may cross
    /// ([`crate::clip::bricks`]): the same image, faster.
    pub clip_bricks: bool,
    pub background: [f32; 3],
    /// Weight of the SH environment light (used when the frame has an SH volume bound).
    pub sh_weight: f32,
    /// Multiply the SH light by the AO (the exact local occlusion CAO keeps up to date).
    pub sh_times_ao: bool,
    /// Variance opacity modulation's V_max (data units squared); 0 = off. Takes effect where
    /// the textures hold a variance volume ([`VolumeTextures::set_variance`]).
    pub variance_max: f32,
    /// The local-histogram method's bleeding weight W: the TF colour moves towards the
    /// bleeding colour E by W * O_env. Takes effect where the frame has a bleeding volume
    /// ([`FrameViews::bleeding`]); 0 = off.
    pub bleeding: f32,
    /// The local-histogram method's scattering weight: the bleeding colour E scattered towards
    /// the eye by the Henyey-Greenstein phase function between the light and the view
    /// direction (docs/design.md, "Local-histogram AO"); 0 = off. Takes effect where the frame
    /// has a bleeding volume.
    pub scattering: f32,
    /// The phase function's anisotropy g in (-1, 1): > 0 scatters forwards (tissue glows
    /// when lit from behind), 0 evenly.
    pub anisotropy: f32,
    /// The direction towards the light in the world (head-tracking space: +y up), if the
    /// light is fixed there; None: a headlight at the head, midway between the eyes.
    pub light_from: Option<[f32; 3]>,
    /// A transparent background (`render --background transparent`): black, alpha 0 where a
    /// ray misses, premultiplied colour; the PNGs get straight alpha.
    pub transparent: bool,
    /// The safety margins' glow, emitted per mm at full intensity ([`GLOW_COLOUR`]); takes
    /// effect where the textures hold a glow volume ([`VolumeTextures::set_glow`]); 0 = off.
    pub glow: f32,
    /// Render the first-hit isosurface of this data value (`--iso`) instead of compositing:
    /// opaque, in the TF's colour there, shaded and lit by the AO like any sample.
    pub iso: Option<f32>,
    /// Fewer rays away from each eye's centre ([`Foveation`]); None casts every pixel.
    pub foveation: Option<Foveation>,
    /// The second eye reuses the first's pixels where they show an opaque surface it sees too,
    /// or where the first eye saw nothing along its whole ray (`--reproject`; docs/design.md,
    /// "The second eye"), casting its own rays elsewhere; foveated, in the coarse pass (the
    /// full-rate centre casts both eyes). Not with glow, scattering
    /// or a light fixed in the world, nor on a device whose fragment shaders cannot store.
    pub reproject: bool,
}

/// Foveated ray casting: within `radius` (a fraction of the eye image's half-diagonal) of its
/// centre every pixel casts its ray, as without foveation, bit for bit; beyond it one ray per
/// block of `factor` x `factor` pixels, cast first into a coarse image, and the pixels there
/// interpolate it (colour and depth, bilinear).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Foveation {
    pub radius: f32,
    pub factor: u32,
}

impl Default for Foveation {
    /// A quarter of the half-diagonal at full rate (a tenth of a square image's pixels), a
    /// ninth of the rays beyond: `bench frame` measured 2.4x less ray casting than
    /// unfoveated at 49 dB on the phantom, and 34 dB on the CT head at 512 x 512 per eye.
    fn default() -> Self {
        Foveation {
            radius: 0.25,
            factor: 3,
        }
    }
}

impl std::str::FromStr for Foveation {
    type Err = String;
    /// `RADIUS[,FACTOR]`: RADIUS in (0, 1], FACTOR 2 to 8.
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        let mut parts = s.split(',');
        let radius: f32 = parts
            .next()
            .and_then(|r| r.trim().parse().ok())
            .filter(|r| *r > 0.0 && *r <= 1.0)
            .ok_or_else(|| format!("'{s}': the radius must be a fraction in (0, 1]"))?;
        let factor = match parts.next() {
            Some(f) => f
                .trim()
                .parse()
                .ok()
                .filter(|f| (2..=8).contains(f))
                .ok_or_else(|| format!("'{s}': the factor must be 2 to 8"))?,
            None => Foveation::default().factor,
        };
        if parts.next().is_some() {
            return Err(format!("'{s}': expected RADIUS[,FACTOR]"));
        }
        Ok(Foveation { radius, factor })
    }
}

/// The pixel a foveated eye keeps its full rate around (as gl_FragCoord, in an image of `size`
/// pixels): where the point the eyes fixate (world, [`fixation`]) lies in its image, else its
/// lens centre, the point straight ahead (the image's centre where the field of view is
/// symmetric, as the window's is; a headset's eyes look through off-centre lenses). A point
/// beside or behind the eye falls back to the lens centre; one beyond the image is held at its
/// border.
pub fn fovea_centre(view: &View, fixated: Option<Vec3>, (w, h): (u32, u32)) -> [f32; 2] {
    let f = &view.fov;
    let [l, r, u, d] = [f.angle_left, f.angle_right, f.angle_up, f.angle_down].map(f32::tan);
    // The direction's tangents in the eye's frame (-Z ahead, +Y up); 0, 0 straight ahead.
    let (tx, ty) = fixated
        .map(|p| view.pose.orientation.inverse() * (p - view.pose.position))
        .filter(|e| e.z < -1e-3 * e.length())
        .map_or((0.0, 0.0), |e| (e.x / -e.z, e.y / -e.z));
    let (w, h) = (w as f32, h as f32);
    [
        (w * (tx - l) / (r - l)).clamp(0.0, w),
        (h * (u - ty) / (u - d)).clamp(0.0, h),
    ]
}

/// The point a tracked gaze (a pose looking along its -Z, from between the eyes) fixates: on its
/// ray at the depth of `centre` (the volume's), so that each eye's fovea lies where that point
/// is in its own image, the eyes' parallax included (a direction alone would put both eyes'
/// foveae ipd / 2 apart at the volume, tens of pixels in a headset).
pub fn fixation(gaze: &crate::space::Pose, centre: Vec3) -> Vec3 {
    let dir = gaze.orientation * Vec3::NEG_Z;
    gaze.position + dir * (centre - gaze.position).dot(dir).max(crate::space::NEAR)
}

/// The colour a safety margin glows in: the amber a tool inside a margin is drawn in.
pub const GLOW_COLOUR: [f32; 3] = [1.0, 0.62, 0.1];

/// The default glow: about a third of full emission over 10 mm of a full-intensity zone.
pub const DEFAULT_GLOW: f32 = 0.04;

impl Default for RenderSettings {
    fn default() -> Self {
        let mut s = RenderSettings {
            step_mm: 0.0,
            ambient: 0.0,
            diffuse: 0.0,
            specular: 0.0,
            use_ao: true,
            cut_lighting: true,
            cut_tint: None,
            preintegrated: true,
            jitter: true,
            tricubic: false,
            skip_empty: true,
            clip_bricks: true,
            background: [0.06, 0.07, 0.09],
            sh_weight: 1.0,
            sh_times_ao: false,
            variance_max: 0.0,
            bleeding: crate::ao::DEFAULT_BLEEDING,
            scattering: 0.0,
            anisotropy: DEFAULT_ANISOTROPY,
            light_from: None,
            transparent: false,
            glow: DEFAULT_GLOW,
            iso: None,
            foveation: None,
            reproject: false,
        };
        Shading::default().apply(&mut s);
        s
    }
}

impl RenderSettings {
    /// The step in mm for a volume of this spacing.
    pub fn step_for(&self, spacing: [f64; 3]) -> f32 {
        if self.step_mm > 0.0 {
            self.step_mm
        } else {
            STEP_PER_SPACING * spacing.iter().cloned().fold(f64::MAX, f64::min) as f32
        }
    }

    /// `render --reference`: the same view integrated [`REFERENCE_REFINEMENT`] times finer,
    /// with point samples and no jitter, to measure the default against.
    pub fn reference(self, spacing: [f64; 3]) -> RenderSettings {
        RenderSettings {
            step_mm: self.step_for(spacing) / REFERENCE_REFINEMENT,
            preintegrated: false,
            jitter: false,
            ..self
        }
    }
}

/// The volume as the ray caster samples it: scalars (full precision, R32F) and the transfer
/// function's lookup table (the AO it reads from the method's V_AO itself, [`FrameViews::ao`]).
pub struct VolumeTextures {
    pub scalars: Image,
    pub lut: Image,
    /// The pre-integrated TF ([`preintegration`]) for the step in `preint_step`, and where in
    /// each step its light comes from (R32F, 0 front .. 1 back).
    preint: Image,
    preint_at: Image,
    /// The shown TF's lookup table (the pre-integration's input) and the step (mm) the
    /// pre-integrated table was built for (0: not yet).
    tf_lut: std::cell::RefCell<Vec<[f32; 4]>>,
    preint_step: std::cell::Cell<f32>,
    /// The pre-integrated table's opacities (for the empty bricks).
    preint_alpha: std::cell::RefCell<Vec<f32>>,
    /// The value range of every ray-casting brick, and which bricks are empty
    /// ([`empty_space`], R8: 1 = empty) for the TF, pre-integration and step in `skip_for`.
    ranges: empty_space::BrickRanges,
    pub skip: Image,
    skip_for: std::cell::Cell<Option<(u64, bool, f32)>>,
    /// Empty bricks (for `skip_for`) and all bricks.
    empty: std::cell::Cell<(usize, usize)>,
    /// Bumped by every new transfer function.
    tf_version: std::cell::Cell<u64>,
    /// var_s of variance opacity modulation (R32F, data units squared), when it is on.
    pub variance: Option<Image>,
    /// The safety margins' glow (R8 unorm per voxel, [`crate::volume::distance::glow`]), when a
    /// structure has one.
    pub glow: Option<Image>,
    /// The label map's structure id per voxel (R8 unorm, id / 255; 1 voxel of 0 without labels),
    /// and per id its colour and opacity a_l and whether it is protected (frame.glsl).
    pub structures: Image,
    structure_table: Box<[[f32; 4]; 256]>,
    protect: [[u32; 4]; 2],
    labelled: bool,
    pub dims: [usize; 3],
    pub spacing: [f64; 3],
    /// The spacing the default ray step and the cut layer follow: the volume's, or the
    /// full-resolution one's where a downsampled volume has a full-resolution inset
    /// ([`VolumeTextures::show_as`]).
    pub step_spacing: [f64; 3],
    pub value_range: (f32, f32),
    /// The scalar image holds (value - lo) / span: `(lo, span)` ([`scalar_storage`]).
    scalar_map: (f32, f32),
}

/// How the scalar image stores the voxels: integers in their own width (8 or 16 bits, unorm),
/// exactly, at a quarter or half of f32's memory; floats as R32F. Returns the image format, its
/// texels, and `(lo, span)` with value = texel * span + lo.
fn scalar_storage(voxels: &crate::volume::Voxels) -> (vk::Format, Vec<u8>, (f32, f32)) {
    use crate::volume::Voxels;
    match voxels {
        Voxels::U8(v) => (vk::Format::R8_UNORM, v.clone(), (0.0, 255.0)),
        Voxels::U16(v) => (
            vk::Format::R16_UNORM,
            bytemuck::cast_slice(v).to_vec(),
            (0.0, 65535.0),
        ),
        Voxels::I16(v) => (
            vk::Format::R16_UNORM,
            v.iter()
                .flat_map(|&x| ((x as i32 + 32768) as u16).to_ne_bytes())
                .collect(),
            (-32768.0, 65535.0),
        ),
        Voxels::F32(v) => (
            vk::Format::R32_SFLOAT,
            bytemuck::cast_slice(v).to_vec(),
            (0.0, 1.0),
        ),
    }
}

/// The label map's ids as an R8 unorm volume (a single 0 voxel without labels), its structures'
/// colour and opacity per id, and the protected ids' bits, as the ray caster reads them.
#[allow(clippy::type_complexity)]
fn structure_image(
    gpu: &Gpu,
    vol: &Volume,
) -> Result<(Image, Box<[[f32; 4]; 256]>, [[u32; 4]; 2])> {
    let mut table = Box::new([[0.0f32; 4]; 256]);
    let mut protect = [[0u32; 4]; 2];
    let (dims, ids): ([usize; 3], &[u8]) = match vol.labels.as_deref() {
        Some(l) => {
            for (k, st) in l.structures.iter().enumerate() {
                let [r, g, b] = st.colour;
                table[k + 1] = [r, g, b, st.opacity];
            }
            let bits = l.protected_bits();
            protect = [
                [bits[0], bits[1], bits[2], bits[3]],
                [bits[4], bits[5], bits[6], bits[7]],
            ];
            (vol.dims, &l.ids)
        }
        None => ([1, 1, 1], &[0]),
    };
    Ok((id_image(gpu, dims, ids)?, table, protect))
}

/// The margins' glow (one byte per voxel of a grid of `dims`) as the R8 unorm volume the ray
/// caster reads.
pub fn glow_image(gpu: &Gpu, dims: [usize; 3], glow: &[u8]) -> Result<Image> {
    filled_volume_image(gpu, dims, (vk::Format::R8_UNORM, "glow"), glow)
}

/// var_s (one value per voxel of a grid of `dims`) as the R32F volume the ray caster reads.
pub fn variance_image(gpu: &Gpu, dims: [usize; 3], var: &[f32]) -> Result<Image> {
    let format = (vk::Format::R32_SFLOAT, "variance");
    filled_volume_image(gpu, dims, format, bytemuck::cast_slice(var))
}

/// Structure ids (one byte per voxel of a grid of `dims`) as the R8 unorm volume the ray caster
/// reads (id / 255).
pub fn id_image(gpu: &Gpu, dims: [usize; 3], ids: &[u8]) -> Result<Image> {
    filled_volume_image(gpu, dims, (vk::Format::R8_UNORM, "structures"), ids)
}

/// A sampled volume image of `dims` in `format` (named), holding `texels` (x fastest).
fn filled_volume_image(
    gpu: &Gpu,
    dims: [usize; 3],
    (format, name): (vk::Format, &str),
    texels: &[u8],
) -> Result<Image> {
    let img = volume_image(gpu, dims, format, name)?;
    img.upload(texels, vk::ImageLayout::SHADER_READ_ONLY_OPTIMAL)?;
    Ok(img)
}

/// What a GPU can hold of a volume (see [`check_volume_fits`]).
#[derive(Clone, Copy, Debug)]
pub struct VolumeLimits {
    /// Largest side of a 3D image (`maxImageDimension3D`).
    pub max_image_dimension_3d: u64,
    /// Largest single buffer: the smaller of `maxMemoryAllocationSize` and `maxBufferSize`.
    /// (`maxStorageBufferRange` does not limit a volume: the volume passes reach their buffers
    /// by device address.)
    pub max_buffer_bytes: u64,
    /// Size of the largest device-local heap.
    pub device_local_bytes: u64,
}

impl VolumeLimits {
    pub fn of(gpu: &Gpu) -> VolumeLimits {
        VolumeLimits {
            max_image_dimension_3d: gpu.limits.max_image_dimension3_d as u64,
            max_buffer_bytes: gpu.max_buffer_bytes(),
            device_local_bytes: gpu.device_local_heap_bytes(),
        }
    }
}

/// GPU bytes per voxel a volume is checked against: the scalar image at its largest (4 bytes
/// for f32 data; an integer scalar takes 2 or 1), and O_c and V_AO (2 each, `ao::stored`; the
/// filters hold O_c in f32, LAO only over the slices its tools reach; O and V_PAO stay on the
/// host), before the method's own volumes.
pub const GPU_BYTES_PER_VOXEL: u64 = 4 + 2 * crate::ao::stored::BYTES_PER_VOXEL;

/// The shaders index a volume's voxels with 32-bit signed integers.
pub const MAX_VOXELS: u64 = (1 << 31) - 1;

/// Whether a volume of `dims` voxels fits `limits` (3D image side, one f32 buffer per voxel
/// within the largest buffer, 32-bit voxel indices, [`GPU_BYTES_PER_VOXEL`] per voxel within the
/// device-local heap). The refusal names the volume, its dims, the limit, and the smallest
/// `--downsample N` that fits.
pub fn check_volume_fits(
    name: &str,
    dims: [usize; 3],
    limits: &VolumeLimits,
    device: &str,
) -> std::result::Result<(), String> {
    let problem = |d: [u64; 3]| -> Option<String> {
        let voxels = d[0] * d[1] * d[2];
        let side = d.iter().copied().max().unwrap_or(0);
        if side > limits.max_image_dimension_3d {
            Some(format!(
                "a side of {side} voxels exceeds the 3D image limit of {} per axis",
                limits.max_image_dimension_3d
            ))
        } else if voxels > MAX_VOXELS {
            Some(format!(
                "{voxels} voxels exceed the {MAX_VOXELS} a shader can index"
            ))
        } else if voxels * 4 > limits.max_buffer_bytes {
            Some(format!(
                "{} bytes per f32 volume exceed the largest buffer the device allocates ({} bytes)",
                voxels * 4,
                limits.max_buffer_bytes
            ))
        } else if voxels * GPU_BYTES_PER_VOXEL > limits.device_local_bytes {
            Some(format!(
                "it needs about {} MiB of GPU memory ({GPU_BYTES_PER_VOXEL} bytes per voxel), \
                 more than the {} MiB device-local heap",
                (voxels * GPU_BYTES_PER_VOXEL) >> 20,
                limits.device_local_bytes >> 20
            ))
        } else {
            None
        }
    };
    let d = dims.map(|d| d as u64);
    let Some(why) = problem(d) else {
        return Ok(());
    };
    let fits = (2..=64u64).find(|&n| problem(d.map(|x| x.div_ceil(n))).is_none());
    Err(format!(
        "volume {name} ({} x {} x {}) does not fit the GPU ({device}): {why}; {}",
        d[0],
        d[1],
        d[2],
        match fits {
            Some(n) => format!("try --downsample {n}"),
            None => "not even --downsample 64 makes it fit".to_string(),
        }
    ))
}

/// [`check_volume_fits`] on `gpu`'s limits, as a GPU error.
pub fn check_volume_fits_gpu(gpu: &Gpu, vol: &Volume) -> Result<()> {
    check_volume_fits(
        &vol.name,
        vol.dims,
        &VolumeLimits::of(gpu),
        &gpu.device_name,
    )
    .map_err(GpuError::Other)
}

fn check_linear_filter(gpu: &Gpu, format: vk::Format) -> Result<()> {
    // SAFETY: `physical` was enumerated from `instance`; both live as long as `gpu`.
    let props = unsafe {
        gpu.instance
            .get_physical_device_format_properties(gpu.physical, format)
    };
    if !props
        .optimal_tiling_features
        .contains(vk::FormatFeatureFlags::SAMPLED_IMAGE_FILTER_LINEAR)
    {
        return Err(GpuError::Other(format!(
            "{}: {format:?} cannot be filtered linearly",
            gpu.device_name
        )));
    }
    Ok(())
}

/// A sampled 3D image of `dims` voxels in `format`, within the device's 3D image limit.
fn volume_image(gpu: &Gpu, dims: [usize; 3], format: vk::Format, name: &str) -> Result<Image> {
    let max = gpu.limits.max_image_dimension3_d as usize;
    if dims.iter().any(|&d| d > max) {
        return Err(GpuError::Other(format!(
            "volume {dims:?} exceeds the device's 3D image limit of {max} per axis"
        )));
    }
    Image::new(
        gpu,
        ImageDesc {
            image_type: vk::ImageType::TYPE_3D,
            view_type: vk::ImageViewType::TYPE_3D,
            format,
            extent: vk::Extent3D {
                width: dims[0] as u32,
                height: dims[1] as u32,
                depth: dims[2] as u32,
            },
            layers: 1,
            usage: vk::ImageUsageFlags::SAMPLED | vk::ImageUsageFlags::TRANSFER_DST,
            aspect: vk::ImageAspectFlags::COLOR,
        },
        name,
    )
}

/// The scalars of `vol` as the ray caster samples them (integers in their own width, floats as
/// R32F), and `(lo, span)`: value = texel * span + lo.
pub fn scalar_image(gpu: &Gpu, vol: &Volume) -> Result<(Image, (f32, f32))> {
    let (format, stored, scalar_map) = scalar_storage(&vol.voxels);
    check_linear_filter(gpu, format)?;
    let scalars = volume_image(gpu, vol.dims, format, "scalars")?;
    scalars.upload(&stored, vk::ImageLayout::SHADER_READ_ONLY_OPTIMAL)?;
    Ok((scalars, scalar_map))
}

impl VolumeTextures {
    /// Uploads the scalars and the transfer function.
    pub fn new(gpu: &Gpu, vol: &Volume, tf: &TransferFunction) -> Result<VolumeTextures> {
        check_volume_fits_gpu(gpu, vol)?;
        check_linear_filter(gpu, vk::Format::R32_SFLOAT)?;
        check_linear_filter(gpu, vk::Format::R32G32B32A32_SFLOAT)?;
        let (scalars, scalar_map) = scalar_image(gpu, vol)?;
        let ranges = empty_space::BrickRanges::of_samples(vol.dims, |i| vol.voxels.get(i));
        let [bx, by, bz] = ranges.bricks.map(|b| b as u32);
        let skip = Image::new(
            gpu,
            ImageDesc {
                image_type: vk::ImageType::TYPE_3D,
                view_type: vk::ImageViewType::TYPE_3D,
                format: vk::Format::R8_UNORM,
                extent: vk::Extent3D {
                    width: bx,
                    height: by,
                    depth: bz,
                },
                layers: 1,
                usage: vk::ImageUsageFlags::SAMPLED | vk::ImageUsageFlags::TRANSFER_DST,
                aspect: vk::ImageAspectFlags::COLOR,
            },
            "empty-bricks",
        )?;
        // Nothing empty until [`VolumeTextures::prepare`] says otherwise.
        skip.upload(
            &vec![0u8; ranges.ranges.len()],
            vk::ImageLayout::SHADER_READ_ONLY_OPTIMAL,
        )?;
        let lut = Image::new(
            gpu,
            ImageDesc {
                image_type: vk::ImageType::TYPE_1D,
                view_type: vk::ImageViewType::TYPE_1D,
                format: vk::Format::R32G32B32A32_SFLOAT,
                extent: vk::Extent3D {
                    width: LUT_SIZE,
                    height: 1,
                    depth: 1,
                },
                layers: 1,
                usage: vk::ImageUsageFlags::SAMPLED | vk::ImageUsageFlags::TRANSFER_DST,
                aspect: vk::ImageAspectFlags::COLOR,
            },
            "tf-lut",
        )?;
        let n = preintegration::SIZE as u32;
        let preint = Image::new(
            gpu,
            ImageDesc {
                image_type: vk::ImageType::TYPE_2D,
                view_type: vk::ImageViewType::TYPE_2D,
                format: vk::Format::R32G32B32A32_SFLOAT,
                extent: vk::Extent3D {
                    width: n,
                    height: n,
                    depth: 1,
                },
                layers: 1,
                usage: vk::ImageUsageFlags::SAMPLED | vk::ImageUsageFlags::TRANSFER_DST,
                aspect: vk::ImageAspectFlags::COLOR,
            },
            "tf-preintegrated",
        )?;
        let preint_at = Image::new(
            gpu,
            ImageDesc {
                image_type: vk::ImageType::TYPE_2D,
                view_type: vk::ImageViewType::TYPE_2D,
                format: vk::Format::R32_SFLOAT,
                extent: vk::Extent3D {
                    width: n,
                    height: n,
                    depth: 1,
                },
                layers: 1,
                usage: vk::ImageUsageFlags::SAMPLED | vk::ImageUsageFlags::TRANSFER_DST,
                aspect: vk::ImageAspectFlags::COLOR,
            },
            "tf-preintegrated-at",
        )?;
        // Bound (unread) while point sampling; filled by [`VolumeTextures::prepare`].
        preint.upload(
            &vec![0u8; (n * n * 16) as usize],
            vk::ImageLayout::SHADER_READ_ONLY_OPTIMAL,
        )?;
        preint_at.upload(
            &vec![0u8; (n * n * 4) as usize],
            vk::ImageLayout::SHADER_READ_ONLY_OPTIMAL,
        )?;
        let (structures, structure_table, protect) = structure_image(gpu, vol)?;
        let t = VolumeTextures {
            labelled: vol.labels.is_some(),
            structures,
            structure_table,
            protect,
            scalars,
            lut,
            preint,
            preint_at,
            tf_lut: Default::default(),
            preint_step: Default::default(),
            preint_alpha: Default::default(),
            ranges,
            skip,
            skip_for: Default::default(),
            empty: Default::default(),
            tf_version: Default::default(),
            variance: None,
            glow: None,
            dims: vol.dims,
            spacing: vol.spacing,
            value_range: vol.value_range(),
            step_spacing: vol.spacing,
            scalar_map,
        };
        t.set_transfer_function(tf)?;
        Ok(t)
    }

    /// Uploads var_s (one value per voxel, x fastest) for variance opacity modulation; None
    /// turns it off.
    pub fn set_variance(&mut self, gpu: &Gpu, variance: Option<&[f32]>) -> Result<()> {
        self.variance = variance
            .map(|v| variance_image(gpu, self.dims, v))
            .transpose()?;
        Ok(())
    }

    /// Uploads the safety margins' glow (one byte per voxel, [`crate::volume::distance::glow`]);
    /// None turns it off.
    pub fn set_glow(&mut self, gpu: &Gpu, glow: Option<&[u8]>) -> Result<()> {
        self.glow = glow.map(|g| glow_image(gpu, self.dims, g)).transpose()?;
        Ok(())
    }

    /// Samples as `vol` would be sampled (its value range for the lookup tables, its spacing for
    /// the step and the cut layer), showing `tf`. With the full-resolution volume this one was
    /// downsampled from, a full-resolution inset and the rest of the volume share one sample
    /// lattice and one classification; with this volume itself, it samples as itself again.
    pub fn show_as(&mut self, vol: &Volume, tf: &TransferFunction) -> Result<()> {
        self.value_range = vol.value_range();
        self.step_spacing = vol.spacing;
        self.preint_step.set(0.0);
        self.set_transfer_function(tf)
    }

    pub fn set_transfer_function(&self, tf: &TransferFunction) -> Result<()> {
        let lut = tf.lut(self.value_range, LUT_SIZE as usize);
        self.lut.upload(
            bytemuck::cast_slice(&lut),
            vk::ImageLayout::SHADER_READ_ONLY_OPTIMAL,
        )?;
        *self.tf_lut.borrow_mut() = lut;
        self.tf_version.set(self.tf_version.get() + 1);
        match self.preint_step.get() {
            0.0 => Ok(()),
            step => self.upload_preintegrated(step),
        }
    }

    /// Shows each structure (by index) with opacity a_l from the next frame on.
    /// Which structures the tools leave standing (by structure index), from the next frame on.
    pub fn set_protected(&mut self, protected: &[bool]) {
        let bits = crate::volume::labels::protected_bits(protected);
        self.protect = [
            [bits[0], bits[1], bits[2], bits[3]],
            [bits[4], bits[5], bits[6], bits[7]],
        ];
    }

    pub fn set_structure_opacities(&mut self, opacities: &[f32]) {
        for (entry, &a) in self.structure_table[1..].iter_mut().zip(opacities) {
            entry[3] = a;
        }
    }

    /// Makes the pre-integrated table fit `settings`' step (built once per TF and step; call
    /// before recording a frame that uses it).
    pub fn prepare(&self, settings: &RenderSettings) -> Result<()> {
        let step = settings.step_for(self.step_spacing);
        if settings.preintegrated && self.preint_step.get() != step {
            self.upload_preintegrated(step)?;
        }
        // The empty bricks of what the shader will look up, when it skips (by default).
        let key = self.skip_key(settings);
        if settings.skip_empty && self.skip_for.get() != Some(key) {
            let table = if settings.preintegrated {
                let n = preintegration::SIZE;
                let alpha = self.preint_alpha.borrow();
                empty_space::Transparency::preintegrated(&alpha, n, self.lut_map(n))
            } else {
                let alpha: Vec<f32> = self.tf_lut.borrow().iter().map(|c| c[3]).collect();
                empty_space::Transparency::lut(&alpha, self.lut_map(LUT_SIZE as usize))
            };
            let flags = self.ranges.empty_flags(&table);
            self.skip
                .upload(&flags, vk::ImageLayout::SHADER_READ_ONLY_OPTIMAL)?;
            self.skip_for.set(Some(key));
            let empty = flags.iter().filter(|&&f| f != 0).count();
            self.empty.set((empty, flags.len()));
        }
        Ok(())
    }

    /// What the empty bricks depend on: the TF, and the pre-integration step if any.
    fn skip_key(&self, settings: &RenderSettings) -> (u64, bool, f32) {
        let step = settings.step_for(self.step_spacing);
        (
            self.tf_version.get(),
            settings.preintegrated,
            if settings.preintegrated { step } else { 0.0 },
        )
    }

    /// Whether the empty bricks were made for `settings` ([`VolumeTextures::prepare`]); the
    /// ray caster skips nothing otherwise.
    fn skip_ready(&self, settings: &RenderSettings) -> bool {
        self.skip_for.get() == Some(self.skip_key(settings))
    }

    /// Bricks the ray caster skips for the settings last [`VolumeTextures::prepare`]d with
    /// skipping on, and all bricks.
    pub fn empty_bricks(&self) -> (usize, usize) {
        self.empty.get()
    }

    fn upload_preintegrated(&self, step: f32) -> Result<()> {
        let (table, at) = preintegration::tables(&self.tf_lut.borrow(), step, preintegration::SIZE);
        self.preint.upload(
            bytemuck::cast_slice(&table),
            vk::ImageLayout::SHADER_READ_ONLY_OPTIMAL,
        )?;
        self.preint_at.upload(
            bytemuck::cast_slice(&at),
            vk::ImageLayout::SHADER_READ_ONLY_OPTIMAL,
        )?;
        *self.preint_alpha.borrow_mut() = table.iter().map(|c| c[3]).collect();
        self.preint_step.set(step);
        Ok(())
    }

    /// Coordinate in a lookup table of `n` texels over the value range = texel * scale +
    /// offset (the scalar image's texel, [`scalar_storage`]), hitting the first and last texel
    /// centres at the ends of the range.
    fn lut_map(&self, n: usize) -> (f32, f32) {
        let (lo, hi) = self.value_range;
        let n = n as f32;
        let scale = (n - 1.0) / (n * (hi - lo).max(1e-6));
        let (s_lo, span) = self.scalar_map;
        (0.5 / n + (s_lo - lo) * scale, scale * span)
    }

    fn extent_mm(&self) -> Vec3 {
        Vec3::new(
            (self.dims[0] as f64 * self.spacing[0]) as f32,
            (self.dims[1] as f64 * self.spacing[1]) as f32,
            (self.dims[2] as f64 * self.spacing[2]) as f32,
        )
    }
}

/// A two-layer colour + depth render target (layer 0 = left eye, 1 = right eye).
pub struct StereoTarget {
    pub color: Image,
    pub depth: Image,
    pub width: u32,
    pub height: u32,
    /// The part of each layer a frame draws, from the top-left corner: all of it, or less under
    /// a render scale below 1 ([`StereoTarget::set_render_scale`]).
    drawn: (u32, u32),
}

impl StereoTarget {
    pub fn new(gpu: &Gpu, width: u32, height: u32) -> Result<StereoTarget> {
        let desc = |format, usage, aspect| ImageDesc {
            image_type: vk::ImageType::TYPE_2D,
            view_type: vk::ImageViewType::TYPE_2D_ARRAY,
            format,
            extent: vk::Extent3D {
                width,
                height,
                depth: 1,
            },
            layers: 2,
            // Sampled: a foveated frame's coarse target is read by its full pass.
            usage: usage | vk::ImageUsageFlags::TRANSFER_SRC | vk::ImageUsageFlags::SAMPLED,
            aspect,
        };
        Ok(StereoTarget {
            color: Image::new(
                gpu,
                desc(
                    COLOR_FORMAT,
                    vk::ImageUsageFlags::COLOR_ATTACHMENT,
                    vk::ImageAspectFlags::COLOR,
                ),
                "stereo-color",
            )?,
            depth: Image::new(
                gpu,
                desc(
                    DEPTH_FORMAT,
                    vk::ImageUsageFlags::DEPTH_STENCIL_ATTACHMENT,
                    vk::ImageAspectFlags::DEPTH,
                ),
                "stereo-depth",
            )?,
            width,
            height,
            drawn: (width, height),
        })
    }

    /// The size each eye is drawn at: the image's, or its render-scaled part.
    pub fn drawn(&self) -> (u32, u32) {
        self.drawn
    }

    /// Frames from now on draw each eye into the top-left `scale` (in (0, 1]) of its image, per
    /// axis: the same view, fewer pixels, which the headset's compositor (the layer's image
    /// rectangle) or the window's blit enlarges. Each drawn pixel is the one a target of the
    /// drawn size would hold, bit for bit.
    pub fn set_render_scale(&mut self, scale: f64) {
        let part = |n: u32| ((n as f64 * scale.clamp(0.0, 1.0)).round() as u32).clamp(1, n);
        self.drawn = (part(self.width), part(self.height));
    }

    /// Records the start of a frame's drawing: both images, whatever they held, to attachments.
    pub fn cmd_begin(&self, cmd: vk::CommandBuffer) {
        self.color.transition(
            cmd,
            vk::ImageLayout::UNDEFINED,
            vk::ImageLayout::COLOR_ATTACHMENT_OPTIMAL,
        );
        self.depth.transition(
            cmd,
            vk::ImageLayout::UNDEFINED,
            vk::ImageLayout::DEPTH_ATTACHMENT_OPTIMAL,
        );
    }

    /// Records the end of a frame's drawing: both images from attachments (as
    /// [`Renderer::record`] and [`OverlayRenderer::record`] leave them) to TRANSFER_SRC_OPTIMAL,
    /// ready to copy. Separate from the passes so that any number of them can draw in between.
    pub fn cmd_finish(&self, cmd: vk::CommandBuffer) {
        self.color.transition(
            cmd,
            vk::ImageLayout::COLOR_ATTACHMENT_OPTIMAL,
            vk::ImageLayout::TRANSFER_SRC_OPTIMAL,
        );
        self.depth.transition(
            cmd,
            vk::ImageLayout::DEPTH_ATTACHMENT_OPTIMAL,
            vk::ImageLayout::TRANSFER_SRC_OPTIMAL,
        );
    }

    /// Copies both layers back (call after a frame recorded by [`Renderer::record`], any
    /// overlay and [`StereoTarget::cmd_finish`] finished).
    pub fn read_back(&self, gpu: &Gpu) -> Result<StereoImage> {
        let bufs = self.readback_buffers(gpu)?;
        gpu.submit_and_wait(|cmd| self.cmd_read_back(gpu, cmd, &bufs))?;
        self.image_from(&bufs, self.drawn)
    }

    /// Bytes of [`StereoTarget::readback_buffers`].
    pub fn readback_bytes(&self) -> u64 {
        2 * self.layer_bytes()
    }

    /// Bytes of the colour (or the depth) of both layers.
    fn layer_bytes(&self) -> u64 {
        (self.width * self.height * 2) as u64 * 4
    }

    /// Host-visible buffers for the colour and depth of both layers.
    pub fn readback_buffers(&self, gpu: &Gpu) -> Result<[Buffer; 2]> {
        let bytes = self.layer_bytes();
        let usage = vk::BufferUsageFlags::TRANSFER_DST;
        Ok([
            Buffer::new(
                gpu,
                bytes,
                usage,
                MemoryLocation::GpuToCpu,
                "color-readback",
            )?,
            Buffer::new(
                gpu,
                bytes,
                usage,
                MemoryLocation::GpuToCpu,
                "depth-readback",
            )?,
        ])
    }

    /// Records the copy of both layers (in TRANSFER_SRC_OPTIMAL, after
    /// [`StereoTarget::cmd_finish`]) into `bufs`, made visible to the host.
    pub fn cmd_read_back(&self, gpu: &Gpu, cmd: vk::CommandBuffer, bufs: &[Buffer; 2]) {
        self.color.cmd_copy_to(cmd, &bufs[0]);
        self.depth.cmd_copy_to(cmd, &bufs[1]);
        gpu.memory_barrier(
            cmd,
            (
                vk::PipelineStageFlags2::ALL_TRANSFER,
                vk::AccessFlags2::TRANSFER_WRITE,
            ),
            (vk::PipelineStageFlags2::HOST, vk::AccessFlags2::HOST_READ),
        );
    }

    /// Both eyes from buffers filled by [`StereoTarget::cmd_read_back`], once it executed: the
    /// part of `drawn` size each eye was drawn in (the whole image at render scale 1).
    pub fn image_from(&self, bufs: &[Buffer; 2], drawn: (u32, u32)) -> Result<StereoImage> {
        let (w, h) = (self.width as usize, self.height as usize);
        let (dw, dh) = (drawn.0 as usize, drawn.1 as usize);
        let crop = |layer: &[u8], texel: usize| -> Vec<u8> {
            (0..dh)
                .flat_map(|y| &layer[y * w * texel..(y * w + dw) * texel])
                .copied()
                .collect()
        };
        let per = w * h;
        let c = bufs[0].mapped()?;
        let d = bufs[1].mapped()?;
        let depth = |layer: &[u8]| -> Vec<f32> {
            crop(layer, 4)
                .chunks_exact(4)
                .map(|b| f32::from_ne_bytes([b[0], b[1], b[2], b[3]]))
                .collect()
        };
        Ok(StereoImage {
            width: drawn.0,
            height: drawn.1,
            rgba: [crop(&c[..per * 4], 4), crop(&c[per * 4..], 4)],
            depth: [depth(&d[..per * 4]), depth(&d[per * 4..])],
        })
    }
}

/// The frame slot [`Renderer::record_eyes`] records in (below [`MAX_FRAMES_IN_FLIGHT`]; the
/// caller knows no submitted frame still reads its uniform buffer), and `after_eye(cmd, eye)`,
/// called after each eye's pass (for its timestamp).
pub struct EyeSlot<'a> {
    pub slot: usize,
    pub after_eye: &'a mut dyn FnMut(vk::CommandBuffer, usize),
}

/// Both eyes on the host: RGBA8 (alpha = accumulated opacity) and depth in \[0,1], rows top-down.
#[derive(Clone, Debug, PartialEq)]
pub struct StereoImage {
    pub width: u32,
    pub height: u32,
    pub rgba: [Vec<u8>; 2],
    pub depth: [Vec<f32>; 2],
}

pub use crate::gpu::MAX_FRAMES_IN_FLIGHT;

/// raycast.frag's bindings of each inset box's scalars, structure ids, var_s and glow: a
/// binding each, not arrays, since a sample's box is not uniform across a draw (one index for
/// a group of lanes would read another box's images).
const INSET_BINDINGS: [[u32; 4]; MAX_INSETS] =
    [[21, 22, 23, 24], [25, 26, 27, 28], [29, 30, 31, 32]];

/// std140 mirror of shaders/include/frame.glsl.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct FrameUniforms {
    inv_view_proj: [[f32; 16]; 2],
    view_proj: [[f32; 16]; 2],
    tex_from_world: [f32; 16],
    extent_mm: [f32; 4],
    value_map: [f32; 4],
    background: [f32; 4],
    viewport: [f32; 4],
    phong: [f32; 4],
    surface: [f32; 4],
    cut_tint: [f32; 4],
    jitter: [f32; 4],
    lighting: [f32; 4],
    bleeding: [f32; 4],
    glow: [f32; 4],
    sh_light: [[f32; 4]; 16],
    tool_reach: [[i32; 4]; 2 * MAX_TOOLS],
    structures: [[f32; 4]; 256],
    protect: [[u32; 4]; 2],
    light: [f32; 4],
    ao_words: [u32; 4],
    inset_lo: [[f32; 4]; MAX_INSETS],
    inset_hi: [[f32; 4]; MAX_INSETS],
    inset_scale: [[f32; 4]; MAX_INSETS],
    inset_offset: [[f32; 4]; MAX_INSETS],
    inset_words: [[u32; 4]; MAX_INSETS],
    ao_tables: [[u32; 4]; AO_TABLE_VECS],
}
/// uvec4s of the brick tables' addresses: V_AO's, then each inset box's, two to a uvec4.
const AO_TABLE_VECS: usize = (MAX_INSETS + 2) / 2;
crate::gpu::glsl_layout!(FrameUniforms, 5440,
    inv_view_proj: 0, view_proj: 128, tex_from_world: 256, extent_mm: 320, value_map: 336,
    background: 352, viewport: 368, phong: 384, surface: 400, cut_tint: 416, jitter: 432,
    lighting: 448, bleeding: 464, glow: 480, sh_light: 496, tool_reach: 752, structures: 1008,
    protect: 5104, light: 5136, ao_words: 5152, inset_lo: 5168, inset_hi: 5216,
    inset_scale: 5264, inset_offset: 5312, inset_words: 5360,
    ao_tables: 5408);

/// The ray caster's descriptor writes: the uniforms, the clip tools, maps and brick states
/// (bindings 0, 4, 5, 20), then the sampled images by binding.
fn descriptor_writes<'a>(
    [ubo, tools, maps, bricks]: [&'a [vk::DescriptorBufferInfo]; 4],
    views: &[(u32, vk::ImageView)],
    infos: &'a [[vk::DescriptorImageInfo; 1]],
) -> Vec<vk::WriteDescriptorSet<'a>> {
    let buffer = |binding: u32, kind, info| {
        vk::WriteDescriptorSet::default()
            .dst_binding(binding)
            .descriptor_type(kind)
            .buffer_info(info)
    };
    let mut w = vec![
        buffer(0, vk::DescriptorType::UNIFORM_BUFFER, ubo),
        buffer(4, vk::DescriptorType::STORAGE_BUFFER, tools),
        buffer(5, vk::DescriptorType::STORAGE_BUFFER, maps),
        buffer(20, vk::DescriptorType::STORAGE_BUFFER, bricks),
    ];
    w.extend(views.iter().zip(infos).map(|((binding, _), info)| {
        vk::WriteDescriptorSet::default()
            .dst_binding(*binding)
            .descriptor_type(vk::DescriptorType::COMBINED_IMAGE_SAMPLER)
            .image_info(info)
    }));
    w
}

/// raycast.frag's push constants: the eye and its pass (see [`Foveation`]).
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct EyePush {
    index: u32,
    /// 0: every pixel; 1: a foveated eye's coarse pass; 2: its full pass.
    pass: u32,
    /// Pixels of the eye per coarse pixel.
    scale: f32,
    /// Where the full rate ends, in pixels from the eye's centre.
    radius: f32,
    /// The first eye's record's address (written with RAY_RECORD, read with RAY_REPROJECT).
    record: [u32; 2],
    /// The foveation's centre, in pixels ([`fovea_centre`]).
    centre: [f32; 2],
}

/// Bytes per pixel of the first eye's record (raycast.frag's EyeRecord): its colour and the
/// view depths where its ray reached 5 % and 90 % opacity.
const RECORD_TEXEL_BYTES: u64 = 16;

pub struct Renderer {
    gpu: Gpu,
    /// The ray caster specialised per combination of flags (RAY_*; the shader's constant_id
    /// 0), made on first use: code for a feature that is off is not there at all. On lavapipe
    /// that matters twice: its SIMD runs every branch, taken or not, and every loop iteration
    /// of an invocation, taken or not, counts against one budget of 65,535 (docs/design.md).
    pipelines: std::cell::RefCell<std::collections::HashMap<u32, vk::Pipeline>>,
    layout: vk::PipelineLayout,
    set_layout: vk::DescriptorSetLayout,
    sampler: vk::Sampler,
    /// Nearest texel: for the coarse depth (D32 has no linear filtering, and a silhouette's
    /// depth must not be blended).
    nearest: vk::Sampler,
    /// One uniform buffer per frame slot ([`Renderer::record_eyes`]), so that a frame can be
    /// recorded while the previous slot's frame still reads its own.
    uniforms: Vec<Buffer>,
    no_clip: Buffer,
    blue_noise: Image,
    /// Per frame slot, a foveated frame's coarse target (made for the size it was last used at).
    coarse: Vec<Option<StereoTarget>>,
    /// Bound in place of the coarse images where a pass does not read them.
    no_coarse: Image,
    /// Per frame slot, the first eye's record for a reprojected second eye (made for the size
    /// it was last used at).
    records: Vec<Option<Buffer>>,
}

/// What one stereo frame looks at: both views, the volume's model matrix (`world_from_tex`)
/// and the tools that clip it.
#[derive(Clone, Copy)]
pub struct FrameViews<'a> {
    pub views: &'a [View; 2],
    pub model: Mat4,
    pub clip: Option<ClipBinding<'a>>,
    /// The SH visibility volume and the environment light, when the frame is lit by it.
    pub sh: Option<ShBinding<'a>>,
    /// V_AO, the method's 16-bit words ([`crate::ao::stored`]), which the ray caster reads by
    /// address, filtering them itself; None: no AO (as `use_ao = false`).
    pub ao: Option<AoWords<'a>>,
    /// The local-histogram method's bleeding colour E (RGBA8 words), read as V_AO is; None: no
    /// bleeding or scattering.
    pub bleeding: Option<&'a Buffer>,
    /// Parts of the volume at full resolution (at most [`MAX_INSETS`]), where the rest is shown
    /// downsampled.
    pub insets: &'a [InsetBinding<'a>],
    /// The point the eyes fixate (world, [`fixation`]), which a foveated frame centres on;
    /// None: each eye's lens centre ([`fovea_centre`]).
    pub gaze: Option<Vec3>,
}

impl<'a> FrameViews<'a> {
    /// Both `views` of the volume at `model`, unclipped and unlit: no tools, no SH, no AO, no
    /// insets, no gaze (set the fields that apply).
    pub fn new(views: &'a [View; 2], model: Mat4) -> FrameViews<'a> {
        FrameViews {
            views,
            model,
            clip: None,
            sh: None,
            ao: None,
            bleeding: None,
            insets: &[],
            gaze: None,
        }
    }
}

/// V_AO as the ray caster reads it: its 16-bit words, stored whole (x fastest) or in bricks
/// through a table ([`crate::ao::pool`]).
#[derive(Clone, Copy)]
pub struct AoWords<'a> {
    pub words: &'a Buffer,
    pub table: Option<&'a Buffer>,
}

impl<'a> From<&'a Buffer> for AoWords<'a> {
    /// A V_AO stored whole (a precompute's V_PAO).
    fn from(words: &'a Buffer) -> AoWords<'a> {
        AoWords { words, table: None }
    }
}

impl<'a> From<&'a crate::ao::pool::AoPool> for AoWords<'a> {
    /// A CAO state's V_AO, in bricks (or whole).
    fn from(pool: &'a crate::ao::pool::AoPool) -> AoWords<'a> {
        AoWords {
            words: &pool.words,
            table: (!pool.whole()).then_some(&pool.table),
        }
    }
}

/// The addresses of `ao`'s words and table (0 where absent), as uvec2 halves.
fn ao_addresses(ao: Option<AoWords>) -> ([u32; 2], [u32; 2]) {
    let split = |a: u64| [a as u32, (a >> 32) as u32];
    (
        split(ao.map_or(0, |a| a.words.address)),
        split(ao.and_then(|a| a.table).map_or(0, |t| t.address)),
    )
}

/// One full-resolution box of a downsampled volume's inset ([`crate::app::inset`]): its
/// scalars and V_AO, and where it lies in the shown volume's texture coordinates.
#[derive(Clone, Copy)]
pub struct InsetBinding<'a> {
    /// Its scalars, stored as the shown volume's are ([`scalar_image`]).
    pub scalars: &'a Image,
    /// Its V_AO (16-bit words), read as [`FrameViews::ao`] is (stored as that one is).
    pub ao: AoWords<'a>,
    /// Its bleeding colour E, read as [`FrameViews::bleeding`] is, where its method has one.
    pub bleeding: Option<&'a Buffer>,
    /// Its structure ids ([`id_image`]), where the volume has labels.
    pub structures: Option<&'a Image>,
    /// Its var_s at full resolution ([`variance_image`]), where variance modulation is on.
    pub variance: Option<&'a Image>,
    /// Its safety margins' glow ([`glow_image`]), where structures have margins.
    pub glow: Option<&'a Image>,
    /// The box \[lo, hi) of the shown volume's texture coordinates it replaces.
    pub lo: Vec3,
    pub hi: Vec3,
    /// Its texture coordinates are the shown volume's times `scale` plus `offset`.
    pub scale: Vec3,
    pub offset: Vec3,
}

/// An SH visibility volume ([`crate::ao::sh::ShVolume::images`]) and the environment light
/// projected into the volume's data frame ([`crate::light`]), per colour channel.
#[derive(Clone, Copy)]
pub struct ShBinding<'a> {
    pub images: &'a [Image],
    pub light: &'a [[f32; 16]; 3],
}

/// The tools that clip the rendered volume: CAO's tool table and clip maps (see
/// shaders/include/clip.glsl), so the views cut exactly where the AO was cut.
#[derive(Clone, Copy)]
pub struct ClipBinding<'a> {
    pub tools: &'a Buffer,
    pub maps: &'a Buffer,
    /// Per brick of the ray caster's grid, packed: which tool hides all of it, if any, or
    /// whether a tool cuts it ([`crate::clip::bricks`]).
    pub bricks: &'a Buffer,
    pub count: u32,
    /// Per tool, an index-space box holding every point it hides (the whole volume for a
    /// probe): no empty-space skipping inside ([`crate::ao::cao::Cao::reach_boxes`]).
    pub reach: &'a [crate::ao::voxel_box::VoxelBox],
}

impl Renderer {
    /// The ray caster specialised for `flags`.
    fn pipeline(&self, flags: u32) -> Result<vk::Pipeline> {
        if let Some(&p) = self.pipelines.borrow().get(&flags) {
            return Ok(p);
        }
        // One draw per eye rather than multiview: lavapipe (Mesa 22.3) renders only the first
        // layer of a multiview pass with dynamic rendering. The ray caster writes every pixel's
        // depth itself (gl_FragDepth), so the test always passes.
        let desc = pipeline::GraphicsDesc {
            vs: include_bytes!(concat!(env!("OUT_DIR"), "/raycast.vert.spv")),
            fs: include_bytes!(concat!(env!("OUT_DIR"), "/raycast.frag.spv")),
            layout: self.layout,
            vertex_bindings: &[],
            vertex_attributes: &[],
            color_format: COLOR_FORMAT,
            depth_format: DEPTH_FORMAT,
            blend: pipeline::opaque(),
            fs_constants: &[flags],
        };
        let variant = (
            pipeline::raster(vk::CullModeFlags::NONE),
            pipeline::depth(vk::CompareOp::ALWAYS, true),
        );
        let p = pipeline::graphics_pipelines(&self.gpu, &desc, &[variant])?[0];
        self.pipelines.borrow_mut().insert(flags, p);
        Ok(p)
    }

    pub fn new(gpu: &Gpu) -> Result<Renderer> {
        // The buffers and images first: they free themselves when a later step fails (a GPU
        // memory budget can refuse them), where the raw handles below would be left behind.
        let uniforms = (0..MAX_FRAMES_IN_FLIGHT)
            .map(|_| {
                Buffer::new(
                    gpu,
                    std::mem::size_of::<FrameUniforms>() as u64,
                    vk::BufferUsageFlags::UNIFORM_BUFFER,
                    MemoryLocation::CpuToGpu,
                    "frame-uniforms",
                )
            })
            .collect::<Result<Vec<_>>>()?;
        // Bound in place of the clip buffers when no tool clips (the shader reads none).
        let no_clip = Buffer::new(
            gpu,
            16,
            vk::BufferUsageFlags::STORAGE_BUFFER,
            MemoryLocation::GpuOnly,
            "no-clip",
        )?;
        let side = blue_noise::SIZE as u32;
        let blue_noise = Image::new(
            gpu,
            ImageDesc {
                image_type: vk::ImageType::TYPE_2D,
                view_type: vk::ImageViewType::TYPE_2D,
                format: vk::Format::R32_SFLOAT,
                extent: vk::Extent3D {
                    width: side,
                    height: side,
                    depth: 1,
                },
                layers: 1,
                usage: vk::ImageUsageFlags::SAMPLED | vk::ImageUsageFlags::TRANSFER_DST,
                aspect: vk::ImageAspectFlags::COLOR,
            },
            "blue-noise",
        )?;
        blue_noise.upload(
            bytemuck::cast_slice(blue_noise::tile()),
            vk::ImageLayout::SHADER_READ_ONLY_OPTIMAL,
        )?;
        let no_coarse = Image::new(
            gpu,
            ImageDesc {
                image_type: vk::ImageType::TYPE_2D,
                view_type: vk::ImageViewType::TYPE_2D_ARRAY,
                format: COLOR_FORMAT,
                extent: vk::Extent3D {
                    width: 1,
                    height: 1,
                    depth: 1,
                },
                layers: 2,
                usage: vk::ImageUsageFlags::SAMPLED | vk::ImageUsageFlags::TRANSFER_DST,
                aspect: vk::ImageAspectFlags::COLOR,
            },
            "no-coarse",
        )?;
        no_coarse.upload(&[0u8; 8], vk::ImageLayout::SHADER_READ_ONLY_OPTIMAL)?;
        // SAFETY: each create call borrows locals (bindings, push range, sampler info) that outlive
        // it; the set layout, layout and samplers go to the returned Renderer, whose Drop destroys
        // them.
        unsafe {
            let d = &gpu.device;
            let sampled = Some(vk::DescriptorType::COMBINED_IMAGE_SAMPLER);
            let storage = Some(vk::DescriptorType::STORAGE_BUFFER);
            // No bindings 2 and 11: the ray caster reads V_AO and E by address (FrameViews).
            let mut bindings = [sampled; 1 + INSET_BINDINGS[MAX_INSETS - 1][3] as usize];
            bindings[0] = Some(vk::DescriptorType::UNIFORM_BUFFER);
            for b in [4, 5, 20] {
                bindings[b] = storage;
            }
            bindings[2] = None;
            bindings[11] = None;
            let set_layout =
                crate::gpu::sparse_set_layout(gpu, &bindings, vk::ShaderStageFlags::FRAGMENT)?;
            let eye_push = [vk::PushConstantRange::default()
                .stage_flags(vk::ShaderStageFlags::FRAGMENT)
                .size(std::mem::size_of::<EyePush>() as u32)];
            let layout = d.create_pipeline_layout(
                &vk::PipelineLayoutCreateInfo::default()
                    .set_layouts(&[set_layout])
                    .push_constant_ranges(&eye_push),
                None,
            )?;
            // One draw per eye rather than multiview: lavapipe (Mesa 22.3) renders only the first
            // layer of a multiview pass with dynamic rendering. The ray caster writes every pixel's
            // depth itself (gl_FragDepth), so the test always passes.
            let pipelines = Default::default();
            let clamped = |filter| {
                d.create_sampler(
                    &vk::SamplerCreateInfo::default()
                        .mag_filter(filter)
                        .min_filter(filter)
                        .mipmap_mode(vk::SamplerMipmapMode::NEAREST)
                        .address_mode_u(vk::SamplerAddressMode::CLAMP_TO_EDGE)
                        .address_mode_v(vk::SamplerAddressMode::CLAMP_TO_EDGE)
                        .address_mode_w(vk::SamplerAddressMode::CLAMP_TO_EDGE)
                        .max_lod(0.0),
                    None,
                )
            };
            let sampler = clamped(vk::Filter::LINEAR)?;
            let nearest = clamped(vk::Filter::NEAREST)?;
            Ok(Renderer {
                gpu: gpu.clone(),
                pipelines,
                layout,
                set_layout,
                sampler,
                nearest,
                uniforms,
                no_clip,
                blue_noise,
                coarse: (0..MAX_FRAMES_IN_FLIGHT).map(|_| None).collect(),
                no_coarse,
                records: (0..MAX_FRAMES_IN_FLIGHT).map(|_| None).collect(),
            })
        }
    }

    /// Records the stereo ray cast of `views` into `target`, leaving both images attachments
    /// (COLOR_ATTACHMENT_OPTIMAL, DEPTH_ATTACHMENT_OPTIMAL) so that later passes (the
    /// [`OverlayRenderer`]) can draw over the volume, depth-tested against it; end the frame with
    /// [`StereoTarget::cmd_finish`]. The uniform buffer of slot 0 is rewritten: one frame in
    /// flight at a time.
    pub fn record(
        &mut self,
        cmd: vk::CommandBuffer,
        target: &StereoTarget,
        tex: &VolumeTextures,
        frame: &FrameViews,
        settings: &RenderSettings,
    ) -> Result<()> {
        let slot = EyeSlot {
            slot: 0,
            after_eye: &mut |_, _| {},
        };
        self.record_eyes(cmd, slot, target, tex, frame, settings)
    }

    /// [`Renderer::record`] with the uniform buffer of frame slot `slot.slot`, calling
    /// `slot.after_eye` after each eye's pass ([`EyeSlot`]).
    pub fn record_eyes(
        &mut self,
        cmd: vk::CommandBuffer,
        slot: EyeSlot<'_>,
        target: &StereoTarget,
        tex: &VolumeTextures,
        frame: &FrameViews,
        settings: &RenderSettings,
    ) -> Result<()> {
        let EyeSlot { slot, after_eye } = slot;
        if slot >= self.uniforms.len() {
            return Err(GpuError::Other(format!(
                "frame slot {slot}: at most {MAX_FRAMES_IN_FLIGHT} frames in flight"
            )));
        }
        let (views, world_from_tex, clip) = (frame.views, frame.model, frame.clip);
        let ext = tex.extent_mm();
        let step = settings.step_for(tex.step_spacing);
        let preintegrated = settings.preintegrated && tex.preint_step.get() == step;
        if settings.preintegrated && !preintegrated {
            return Err(GpuError::Other(format!(
                "the pre-integrated TF is for a step of {} mm, not {step} mm: call \
                 VolumeTextures::prepare before recording",
                tex.preint_step.get()
            )));
        }
        let (offset, scale) = tex.lut_map(LUT_SIZE as usize);
        let (pre_offset, pre_scale) = tex.lut_map(preintegration::SIZE);
        let max_spacing = tex.step_spacing.iter().cloned().fold(0.0, f64::max) as f32;
        let (lo, hi) = tex.value_range;
        let glow = tex.glow.is_some() && settings.glow > 0.0;
        let iso = settings.iso.is_some();
        let flags = [
            // An isosurface is found on point samples, and skipping knows the TF, not the iso.
            (preintegrated && !iso, RAY_PREINTEGRATED),
            (settings.jitter, RAY_JITTER),
            (settings.tricubic, RAY_TRICUBIC),
            // The glow lies in empty space: no skipping where it shines.
            (
                settings.skip_empty && tex.skip_ready(settings) && !glow && !iso,
                RAY_SKIP_EMPTY,
            ),
            (iso, RAY_ISO),
            (tex.labelled, RAY_LABELS),
            (clip.is_some_and(|c| c.count > 0), RAY_CLIPPING),
            (glow, RAY_GLOW),
            (settings.clip_bricks, RAY_CLIP_BRICKS),
            (!frame.insets.is_empty(), RAY_INSET),
            (settings.use_ao && frame.ao.is_some(), RAY_AO),
            (
                settings.use_ao
                    && frame.ao.is_some()
                    && std::iter::once(frame.ao)
                        .chain(frame.insets.iter().map(|i| Some(i.ao)))
                        .any(|a| a.is_some_and(|a| a.table.is_some())),
                RAY_AO_BRICKS,
            ),
            (
                frame.bleeding.is_some() && settings.bleeding > 0.0,
                RAY_BLEEDING,
            ),
            (
                frame.bleeding.is_some() && settings.scattering > 0.0,
                RAY_SCATTERING,
            ),
            (frame.sh.is_some() && settings.sh_weight > 0.0, RAY_SH),
            (
                tex.variance.is_some() && settings.variance_max > 0.0,
                RAY_VARIANCE,
            ),
            (settings.diffuse > 0.0 || settings.specular > 0.0, RAY_LIT),
        ]
        .iter()
        .filter(|f| f.0)
        .fold(0, |acc, f| acc | f.1);
        let pipeline = self.pipeline(flags)?;
        // The second eye reprojected from the first's record, this slot's own: where the
        // colour of a point is the same from both eyes (no glow in empty space, no light whose
        // half vector or phase follows each eye's view).
        let reproject = settings.reproject
            && self.gpu.fragment_stores
            && flags & (RAY_GLOW | RAY_SCATTERING) == 0
            && settings.light_from.is_none();
        let (width, height) = target.drawn();
        // For the whole image, so that a render scale's change does not make it anew.
        let record_bytes = (target.width * target.height) as u64 * RECORD_TEXEL_BYTES;
        let record = if reproject {
            let slot_record = &mut self.records[slot];
            if slot_record.as_ref().is_none_or(|b| b.size != record_bytes) {
                *slot_record = Some(Buffer::new(
                    &self.gpu,
                    record_bytes,
                    vk::BufferUsageFlags::STORAGE_BUFFER,
                    MemoryLocation::GpuOnly,
                    "eye-record",
                )?);
            }
            let a = slot_record.as_ref().map_or(0, |b| b.address);
            Some((
                [a as u32, (a >> 32) as u32],
                self.pipeline(flags | RAY_RECORD)?,
                self.pipeline(flags | RAY_REPROJECT)?,
            ))
        } else {
            None
        };
        let [ox, oy] = blue_noise::RIGHT_EYE_OFFSET;
        let vp = views.map(|v| v.view_proj());
        assert!(
            frame.insets.len() <= MAX_INSETS,
            "at most {MAX_INSETS} insets"
        );
        // Per box slot: [lo, hi, scale, offset] and its words; an absent box has lo = hi = 0.
        let box_of = |s: usize| frame.insets.get(s);
        let [inset_lo, inset_hi, inset_scale, inset_offset] = [0, 1, 2, 3].map(|k| {
            std::array::from_fn(|s| {
                box_of(s).map_or([0.0; 4], |i| {
                    [i.lo, i.hi, i.scale, i.offset][k].extend(0.0).to_array()
                })
            })
        });
        let u = FrameUniforms {
            inv_view_proj: vp.map(|m| m.inverse().to_cols_array()),
            view_proj: vp.map(|m| m.to_cols_array()),
            tex_from_world: world_from_tex.inverse().to_cols_array(),
            extent_mm: [ext.x, ext.y, ext.z, step],
            value_map: [offset, scale, pre_offset, pre_scale],
            background: [
                settings.background[0],
                settings.background[1],
                settings.background[2],
                // The baseline between the eyes (a reprojected second eye's parallax).
                views[0].pose.position.distance(views[1].pose.position),
            ],
            viewport: [
                width as f32,
                height as f32,
                clip.map_or(0, |c| c.count) as f32,
                // The first eye's pixel footprint per unit of view depth (a reprojected second
                // eye's tolerance).
                (views[0].fov.angle_right.tan() - views[0].fov.angle_left.tan()) / width as f32,
            ],
            phong: [
                settings.ambient,
                settings.diffuse,
                settings.specular,
                PHONG[3],
            ],
            surface: [
                // In texel units per mm, as the shader's gradient is.
                crate::ao::MIN_GRADIENT * (hi - lo) / tex.scalar_map.1,
                if settings.cut_lighting {
                    CUT_LAYER_VOXELS * max_spacing
                } else {
                    0.0
                },
                if settings.use_ao {
                    AO_DIFFUSE_SHARE
                } else {
                    0.0
                },
                // The isovalue as the scalar image stores it.
                settings
                    .iso
                    .map_or(0.0, |v| (v - tex.scalar_map.0) / tex.scalar_map.1),
            ],
            cut_tint: match settings.cut_tint {
                Some([r, g, b]) => [r, g, b, CUT_TINT_WEIGHT],
                None => [0.0; 4],
            },
            jitter: [0.0, 0.0, ox as f32, oy as f32],
            lighting: {
                let inv_vmax = match &tex.variance {
                    Some(_) if settings.variance_max > 0.0 => 1.0 / settings.variance_max,
                    _ => 0.0,
                };
                match frame.sh {
                    Some(sh) => [
                        settings.sh_weight,
                        4.0 * sh.images.len() as f32,
                        if settings.sh_times_ao { 1.0 } else { 0.0 },
                        inv_vmax,
                    ],
                    None => [0.0, 0.0, 0.0, inv_vmax],
                }
            },
            bleeding: match frame.bleeding {
                Some(_) => [
                    settings.bleeding,
                    settings.scattering,
                    settings.anisotropy,
                    0.0,
                ],
                None => [0.0; 4],
            },
            glow: [
                GLOW_COLOUR[0],
                GLOW_COLOUR[1],
                GLOW_COLOUR[2],
                settings.glow,
            ],
            sh_light: std::array::from_fn(|k| {
                let l = frame.sh.map_or([[0.0; 16]; 3], |sh| *sh.light);
                let y0 = crate::light::sh::Y0 as f32;
                [y0 * l[0][k], y0 * l[1][k], y0 * l[2][k], 0.0]
            }),
            tool_reach: std::array::from_fn(|k| {
                let b = clip.and_then(|c| c.reach.get(k / 2));
                match (b, k % 2) {
                    (Some(b), 0) => [b.min[0], b.min[1], b.min[2], 0],
                    (Some(b), _) => [b.max[0], b.max[1], b.max[2], 0],
                    (None, _) => [0; 4],
                }
            }),
            structures: *tex.structure_table,
            protect: tex.protect,
            light: match settings.light_from {
                // Into the frame the shader's gradient lives in: along i, j, k, in mm.
                Some(l) => {
                    let t = world_from_tex
                        .inverse()
                        .transform_vector3(Vec3::from_array(l))
                        * ext;
                    t.normalize_or_zero().extend(1.0).to_array()
                }
                // The headlight stands at the head, midway between the eyes: a point in that
                // frame (texture coordinates times the extent).
                None => {
                    let head = 0.5 * (views[0].pose.position + views[1].pose.position);
                    let t = world_from_tex.inverse().transform_point3(head) * ext;
                    t.extend(0.0).to_array()
                }
            },
            ao_words: {
                let e = frame.bleeding.map_or(0, |b| b.address);
                let (a, _) = ao_addresses(frame.ao);
                [a[0], a[1], e as u32, (e >> 32) as u32]
            },
            inset_lo,
            inset_hi,
            inset_scale,
            inset_offset,
            inset_words: std::array::from_fn(|s| {
                let e = box_of(s).and_then(|i| i.bleeding).map_or(0, |b| b.address);
                let (a, _) = ao_addresses(box_of(s).map(|i| i.ao));
                [a[0], a[1], e as u32, (e >> 32) as u32]
            }),
            ao_tables: {
                let tables: Vec<[u32; 2]> = std::iter::once(frame.ao)
                    .chain((0..MAX_INSETS).map(|s| box_of(s).map(|i| i.ao)))
                    .map(|a| ao_addresses(a).1)
                    .collect();
                std::array::from_fn(|k| {
                    let (lo, hi) = (tables[2 * k], tables.get(2 * k + 1).copied());
                    let hi = hi.unwrap_or([0; 2]);
                    [lo[0], lo[1], hi[0], hi[1]]
                })
            },
        };
        self.uniforms[slot].write(0, bytemuck::bytes_of(&u))?;
        let uniforms = &self.uniforms[slot];

        let d = &self.gpu.device;
        target.cmd_begin(cmd);
        let bg = settings.background;
        let ubo = [uniforms
            .descriptor()
            .range(std::mem::size_of::<FrameUniforms>() as u64)];
        let img = |(binding, view): (u32, vk::ImageView)| {
            [vk::DescriptorImageInfo::default()
                .sampler(if binding == 19 {
                    self.nearest
                } else {
                    self.sampler
                })
                .image_view(view)
                .image_layout(vk::ImageLayout::SHADER_READ_ONLY_OPTIMAL)]
        };
        // Four SH slots; unused ones (4 coefficients, or no SH) repeat a bound image unread.
        let sh_views: [vk::ImageView; 4] = std::array::from_fn(|g| {
            frame.sh.map_or(tex.scalars.view, |sh| {
                sh.images.get(g).unwrap_or(&sh.images[0]).view
            })
        });
        // A foveated frame's coarse target, this slot's own (its last frame has finished).
        let coarse_size = settings.foveation.map(|f| {
            let c = |n: u32| n.div_ceil(f.factor);
            (c(width), c(height), f)
        });
        let slot_coarse = &mut self.coarse[slot];
        let coarse = match coarse_size {
            Some((w, h, f)) => {
                if slot_coarse
                    .as_ref()
                    .is_none_or(|c| (c.width, c.height) != (w, h))
                {
                    *slot_coarse = Some(StereoTarget::new(&self.gpu, w, h)?);
                }
                slot_coarse.as_ref().map(|c| (c, f))
            }
            None => None,
        };
        let coarse_views = coarse.map_or((self.no_coarse.view, self.no_coarse.view), |(c, _)| {
            (c.color.view, c.depth.view)
        });
        // The sampled images by binding (raycast.frag): var_s and E, where absent, are a bound
        // image standing in, unread (lighting.w = 0, bleeding.x = 0); so are the coarse images
        // but in a foveated eye's full pass.
        // Box s's image where it has one, else the shown volume's, else a stand-in (unread).
        let inset_or = |s: usize, of: fn(InsetBinding) -> Option<&Image>, shown: Option<&Image>| {
            frame
                .insets
                .get(s)
                .and_then(|&i| of(i))
                .or(shown)
                .unwrap_or(&tex.scalars)
                .view
        };
        let sampled_views = |coarse: (vk::ImageView, vk::ImageView)| {
            let fixed = [
                (1, tex.scalars.view),
                (3, tex.lut.view),
                (6, sh_views[0]),
                (7, sh_views[1]),
                (8, sh_views[2]),
                (9, sh_views[3]),
                (10, tex.variance.as_ref().unwrap_or(&tex.scalars).view),
                (12, tex.preint.view),
                (13, self.blue_noise.view),
                (14, tex.skip.view),
                (15, tex.preint_at.view),
                (16, tex.structures.view),
                (17, tex.glow.as_ref().unwrap_or(&tex.scalars).view),
                (18, coarse.0),
                (19, coarse.1),
            ];
            let boxes = INSET_BINDINGS.iter().enumerate().flat_map(|(s, b)| {
                [
                    (b[0], inset_or(s, |b| Some(b.scalars), None)),
                    (b[1], inset_or(s, |b| b.structures, Some(&tex.structures))),
                    (b[2], inset_or(s, |b| b.variance, tex.variance.as_ref())),
                    (b[3], inset_or(s, |b| b.glow, tex.glow.as_ref())),
                ]
            });
            fixed.into_iter().chain(boxes).collect::<Vec<_>>()
        };
        let plain = sampled_views((self.no_coarse.view, self.no_coarse.view));
        let full = sampled_views(coarse_views);
        let (plain_infos, full_infos): (Vec<_>, Vec<_>) = (
            plain.iter().map(|&v| img(v)).collect(),
            full.iter().map(|&v| img(v)).collect(),
        );
        let clip_tools = [clip.map_or(&self.no_clip, |c| c.tools).descriptor()];
        let clip_maps = [clip.map_or(&self.no_clip, |c| c.maps).descriptor()];
        let clip_bricks = [clip.map_or(&self.no_clip, |c| c.bricks).descriptor()];
        let buffers = [&ubo[..], &clip_tools[..], &clip_maps[..], &clip_bricks[..]];
        let plain_writes = descriptor_writes(buffers, &plain, &plain_infos);
        let full_writes = descriptor_writes(buffers, &full, &full_infos);
        // One eye's pass into layer `eye` of `into`.
        let draw = |into: &StereoTarget,
                    eye: u32,
                    pipeline: vk::Pipeline,
                    push: EyePush,
                    writes: &[vk::WriteDescriptorSet]| {
            let (width, height) = into.drawn();
            let area = vk::Rect2D {
                offset: vk::Offset2D::default(),
                extent: vk::Extent2D { width, height },
            };
            let color_att = [vk::RenderingAttachmentInfo::default()
                .image_view(into.color.layer_views[eye as usize])
                .image_layout(vk::ImageLayout::COLOR_ATTACHMENT_OPTIMAL)
                .load_op(vk::AttachmentLoadOp::CLEAR)
                .store_op(vk::AttachmentStoreOp::STORE)
                .clear_value(vk::ClearValue {
                    color: vk::ClearColorValue {
                        float32: [bg[0], bg[1], bg[2], 0.0],
                    },
                })];
            let depth_att = vk::RenderingAttachmentInfo::default()
                .image_view(into.depth.layer_views[eye as usize])
                .image_layout(vk::ImageLayout::DEPTH_ATTACHMENT_OPTIMAL)
                .load_op(vk::AttachmentLoadOp::CLEAR)
                .store_op(vk::AttachmentStoreOp::STORE)
                .clear_value(vk::ClearValue {
                    depth_stencil: vk::ClearDepthStencilValue {
                        depth: 1.0,
                        stencil: 0,
                    },
                });
            let info = vk::RenderingInfo::default()
                .render_area(area)
                .layer_count(1)
                .color_attachments(&color_att)
                .depth_attachment(&depth_att);
            // SAFETY: `cmd` is recording; the pipeline, layout and every bound resource live
            // until the frame's slot is reused, which the caller orders after this frame.
            unsafe {
                d.cmd_begin_rendering(cmd, &info);
                d.cmd_bind_pipeline(cmd, vk::PipelineBindPoint::GRAPHICS, pipeline);
                self.gpu.push_descriptor.cmd_push_descriptor_set(
                    cmd,
                    vk::PipelineBindPoint::GRAPHICS,
                    self.layout,
                    0,
                    writes,
                );
                d.cmd_push_constants(
                    cmd,
                    self.layout,
                    vk::ShaderStageFlags::FRAGMENT,
                    0,
                    bytemuck::bytes_of(&push),
                );
                d.cmd_set_viewport(
                    cmd,
                    0,
                    &[vk::Viewport {
                        x: 0.0,
                        y: 0.0,
                        width: width as f32,
                        height: height as f32,
                        min_depth: 0.0,
                        max_depth: 1.0,
                    }],
                );
                d.cmd_set_scissor(cmd, 0, &[area]);
                d.cmd_draw(cmd, 3, 1, 0, 0);
                d.cmd_end_rendering(cmd);
            }
        };
        let half_diagonal = 0.5 * (width as f32).hypot(height as f32);
        let push = |index: u32, pass: u32| EyePush {
            index,
            pass,
            scale: coarse.map_or(1.0, |(_, f)| f.factor as f32),
            radius: coarse.map_or(0.0, |(_, f)| f.radius * half_diagonal),
            record: record.map_or([0; 2], |r| r.0),
            centre: fovea_centre(&views[index as usize], frame.gaze, (width, height)),
        };
        // Each eye's casting pass: the first eye recording, the second reprojecting from it
        // (after its fragments' stores), where the frame reprojects.
        let casting = |eye: u32| match record {
            Some((_, first, second)) => {
                if eye == 1 {
                    let fragments = vk::PipelineStageFlags2::FRAGMENT_SHADER;
                    self.gpu.memory_barrier(
                        cmd,
                        (fragments, vk::AccessFlags2::SHADER_STORAGE_WRITE),
                        (fragments, vk::AccessFlags2::SHADER_STORAGE_READ),
                    );
                }
                if eye == 0 {
                    first
                } else {
                    second
                }
            }
            None => pipeline,
        };
        if let Some((c, _)) = coarse {
            // Foveated: the coarse pass casts, and reprojects, on its own grid.
            c.cmd_begin(cmd);
            for eye in 0..2u32 {
                draw(c, eye, casting(eye), push(eye, 1), &plain_writes);
            }
            c.color.transition(
                cmd,
                vk::ImageLayout::COLOR_ATTACHMENT_OPTIMAL,
                vk::ImageLayout::SHADER_READ_ONLY_OPTIMAL,
            );
            c.depth.transition(
                cmd,
                vk::ImageLayout::DEPTH_ATTACHMENT_OPTIMAL,
                vk::ImageLayout::SHADER_READ_ONLY_OPTIMAL,
            );
        }
        for eye in 0..2u32 {
            match coarse {
                // The full-rate centre casts both eyes; the rest reads the coarse pass.
                Some(_) => draw(target, eye, pipeline, push(eye, 2), &full_writes),
                None => draw(target, eye, casting(eye), push(eye, 0), &plain_writes),
            }
            after_eye(cmd, eye as usize);
        }
        Ok(())
    }
}

impl Drop for Renderer {
    fn drop(&mut self) {
        // SAFETY: the idle wait ends every frame that used these samplers, pipelines and layouts;
        // they are this renderer's own, destroyed once.
        unsafe {
            let d = &self.gpu.device;
            let _ = d.device_wait_idle();
            d.destroy_sampler(self.sampler, None);
            d.destroy_sampler(self.nearest, None);
            for (_, p) in self.pipelines.borrow_mut().drain() {
                d.destroy_pipeline(p, None);
            }
            d.destroy_pipeline_layout(self.layout, None);
            d.destroy_descriptor_set_layout(self.set_layout, None);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const LIMITS: VolumeLimits = VolumeLimits {
        max_image_dimension_3d: 2048,
        max_buffer_bytes: 1 << 32,
        device_local_bytes: 8 << 30,
    };

    #[test]
    fn volumes_within_the_limits_fit() {
        assert_eq!(
            check_volume_fits("ct", [512, 512, 400], &LIMITS, "gpu"),
            Ok(())
        );
        assert_eq!(
            check_volume_fits("edge", [2048, 1, 1], &LIMITS, "gpu"),
            Ok(())
        );
        // Past lavapipe's 128 MiB storage-buffer range: a routine chest CT and a long one.
        for dims in [[512, 512, 133], [512, 512, 600], [1024, 1024, 300]] {
            assert_eq!(check_volume_fits("ct", dims, &LIMITS, "gpu"), Ok(()));
        }
    }

    #[test]
    fn too_long_a_side_is_refused_with_a_downsample_hint() {
        let e = check_volume_fits("long", [4100, 64, 64], &LIMITS, "Fake GPU").unwrap_err();
        assert!(
            e.contains("volume long (4100 x 64 x 64)")
                && e.contains("Fake GPU")
                && e.contains("3D image limit of 2048")
                && e.contains("--downsample 3"),
            "{e}"
        );
    }

    #[test]
    fn the_fovea_is_where_the_gaze_meets_the_image_or_the_lens_centre() {
        use crate::space::{symmetric_fov, Fov, Pose};
        use glam::{Quat, Vec4Swizzles};
        let size = (2016, 2240);
        // A headset's left eye: more field outwards (left) and downwards than in and up.
        let view = View {
            pose: Pose {
                position: Vec3::new(-0.03, 1.6, 0.1),
                orientation: Quat::from_rotation_y(0.4) * Quat::from_rotation_x(-0.2),
            },
            fov: Fov {
                angle_left: -0.94,
                angle_right: 0.70,
                angle_up: 0.80,
                angle_down: -0.92,
            },
        };
        // Where a world point lands in the image, as the ray caster maps pixels to rays.
        let pixel_of = |p: Vec3| {
            let c = view.view_proj() * p.extend(1.0);
            let ndc = c.xy() / c.w;
            [
                (ndc.x * 0.5 + 0.5) * size.0 as f32,
                (ndc.y * 0.5 + 0.5) * size.1 as f32,
            ]
        };
        let close = |a: [f32; 2], b: [f32; 2]| (a[0] - b[0]).hypot(a[1] - b[1]) < 0.05;
        let eye = view.pose.position;
        for local in [
            Vec3::new(0.3, -0.2, -1.0),
            Vec3::new(-0.7, 0.5, -0.8),
            Vec3::new(0.05, 0.6, -1.2),
        ] {
            let target = eye + view.pose.orientation * local;
            let (at, want) = (fovea_centre(&view, Some(target), size), pixel_of(target));
            assert!(close(at, want), "{target}: {at:?} against {want:?}");
        }
        // No gaze: the lens centre, the point straight ahead, off the image's centre here.
        let ahead = eye + view.pose.orientation * Vec3::NEG_Z;
        let lens = fovea_centre(&view, None, size);
        assert!(close(lens, pixel_of(ahead)), "{lens:?}");
        assert!(lens[0] > 1100.0 && lens[1] < 1100.0, "{lens:?}");
        // A gaze behind the eye: the lens centre; one far to the side: held at the border.
        let back = eye + view.pose.orientation * Vec3::Z;
        assert_eq!(fovea_centre(&view, Some(back), size), lens);
        let side = eye + view.pose.orientation * Vec3::new(-1.0, 0.0, -0.05);
        assert_eq!(fovea_centre(&view, Some(side), size)[0], 0.0);
        // A gaze from between the eyes fixates at the volume's depth, on its ray.
        let gaze = Pose {
            position: eye + view.pose.orientation * Vec3::X * 0.032,
            orientation: view.pose.orientation,
        };
        let at = fixation(
            &gaze,
            eye + view.pose.orientation * Vec3::new(0.1, 0.0, -0.6),
        );
        let expect = gaze.position + view.pose.orientation * Vec3::new(0.0, 0.0, -0.6);
        assert!(at.distance(expect) < 1e-5, "{at} against {expect}");
        // A symmetric field of view: the image's centre exactly, as before gaze was known.
        let desk = View {
            fov: symmetric_fov(0.6),
            ..view
        };
        assert_eq!(fovea_centre(&desk, None, (96, 80)), [48.0, 40.0]);
    }

    #[test]
    fn foveation_parses_a_radius_and_a_factor_and_refuses_the_rest() {
        let f = |s: &str| s.parse::<Foveation>();
        assert_eq!(
            f("0.4"),
            Ok(Foveation {
                radius: 0.4,
                factor: Foveation::default().factor
            })
        );
        assert_eq!(
            f("0.25,3"),
            Ok(Foveation {
                radius: 0.25,
                factor: 3
            })
        );
        for bad in ["0", "1.5", "x", "0.3,1", "0.3,9", "0.3,2,1"] {
            assert!(f(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn too_many_bytes_are_refused_with_a_downsample_hint() {
        // 1280 x 1024^2 voxels x 8 bytes = 10 GiB > 8 GiB; / 2 per axis = 1.25 GiB fits.
        let limits = VolumeLimits {
            max_buffer_bytes: u64::MAX,
            ..LIMITS
        };
        let e = check_volume_fits("big", [1280, 1024, 1024], &limits, "gpu").unwrap_err();
        assert!(
            e.contains("volume big (1280 x 1024 x 1024)")
                && e.contains("10240 MiB")
                && e.contains("8192 MiB device-local heap")
                && e.contains("--downsample 2"),
            "{e}"
        );
        // Just over 4 GiB of f32 exceeds the largest buffer; the message says so.
        let e = check_volume_fits("buf", [1024, 1024, 1025], &LIMITS, "gpu").unwrap_err();
        assert!(
            e.contains("largest buffer the device allocates (4294967296 bytes)")
                && e.contains("--downsample 2"),
            "{e}"
        );
        // Past 2^31 voxels the shaders' indices would overflow.
        let huge = VolumeLimits {
            max_image_dimension_3d: 1 << 16,
            max_buffer_bytes: u64::MAX,
            device_local_bytes: u64::MAX,
        };
        let e = check_volume_fits("huge", [2048, 2048, 600], &huge, "gpu").unwrap_err();
        assert!(
            e.contains("a shader can index") && e.contains("--downsample 2"),
            "{e}"
        );
        // Nothing fits a heap of zero bytes.
        let none = VolumeLimits {
            device_local_bytes: 0,
            ..LIMITS
        };
        let e = check_volume_fits("any", [8, 8, 8], &none, "gpu").unwrap_err();
        assert!(e.contains("not even --downsample 64"), "{e}");
    }
}
