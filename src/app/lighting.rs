//! Environment lighting through the SH visibility volume (Ritschel 2007): what the command line
//! asks for, the one SH volume every view shares, and the light projected into the volume's
//! data frame each frame (so turning the light or the volume never recomputes visibility).

use super::common::{progress_bar, AppError, Result};
use crate::ao::cao::Cao;
use crate::ao::sh::{ShFrameMetrics, ShParams, ShVolume};
use crate::gpu::Gpu;
use crate::light::environment::{Environment, ShLight};
use crate::render::{RenderSettings, ShBinding, Shading};
use crate::space::world_from_lps;
use crate::space::Placement;
use crate::volume::Volume;
use glam::{DMat3, DQuat};

/// Which terms light the volume.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum LightingMode {
    /// Ambient occlusion (k * AO) plus the gradient headlight.
    #[default]
    Ao,
    /// The environment through the SH visibility volume alone: E = albedo * (L . V).
    Sh,
    /// Both: a dimmer AO ambient term plus the environment term multiplied by the AO (the
    /// exact local occlusion darkens creases the coarser SH visibility misses), and the headlight.
    AoSh,
}

impl std::str::FromStr for LightingMode {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s {
            "ao" => Ok(LightingMode::Ao),
            "sh" => Ok(LightingMode::Sh),
            "ao+sh" | "sh+ao" => Ok(LightingMode::AoSh),
            _ => Err(format!("unknown lighting '{s}' (ao, sh or ao+sh)")),
        }
    }
}

/// How a session is lit.
#[derive(Clone, Debug)]
pub struct LightingOptions {
    pub mode: LightingMode,
    /// A built-in environment name, `constant:R,G,B` or an equirectangular .png/.hdr.
    pub environment: String,
    pub sh: ShParams,
    /// Turn of the environment about the world's up axis, degrees.
    pub yaw_deg: f32,
    /// How the ray caster shades and samples.
    pub shading: ShadingOptions,
}

/// The ray caster's shading and sampling as the command line asks for them (`--shading`,
/// `--cut-tint`, `--ray-step-mm`, ...), the same for every front end.
#[derive(Clone, Copy, Debug)]
pub struct ShadingOptions {
    pub shading: Shading,
    /// Overrides the mode's diffuse weight (`render --diffuse`).
    pub diffuse: Option<f32>,
    /// No AO at all, whatever the mode (`render --no-ao`).
    pub no_ao: bool,
    pub cut_lighting: bool,
    pub cut_tint: Option<[f32; 3]>,
    pub preintegrated: bool,
    pub jitter: bool,
    pub tricubic: bool,
    pub skip_empty: bool,
    /// Ray step in mm; 0 = a fraction of the smallest spacing.
    pub step_mm: f32,
    /// The isosurface's data value (`--iso`), if one is shown instead of the volume.
    pub iso: Option<f32>,
    /// Foveated ray casting (`--foveate`).
    pub foveation: Option<crate::render::Foveation>,
    /// The second eye reprojected from the first where valid (`--reproject`).
    pub reproject: bool,
    /// The local histograms' scattering weight and anisotropy g (`--hist-scattering`,
    /// `--hist-anisotropy`).
    pub scattering: f32,
    pub anisotropy: f32,
    /// A light fixed in the world instead of the headlight (`--light-from`).
    pub light_from: Option<[f32; 3]>,
}

impl Default for ShadingOptions {
    fn default() -> Self {
        let s = RenderSettings::default();
        ShadingOptions {
            shading: Shading::default(),
            diffuse: None,
            no_ao: false,
            cut_lighting: s.cut_lighting,
            cut_tint: s.cut_tint,
            preintegrated: s.preintegrated,
            jitter: s.jitter,
            tricubic: s.tricubic,
            skip_empty: s.skip_empty,
            step_mm: s.step_mm,
            iso: s.iso,
            foveation: s.foveation,
            reproject: s.reproject,
            scattering: s.scattering,
            anisotropy: s.anisotropy,
            light_from: s.light_from,
        }
    }
}

impl ShadingOptions {
    /// `render --reference`: [`RenderSettings::reference`]'s finer step, point samples, no jitter.
    pub fn reference(self, spacing: [f64; 3]) -> ShadingOptions {
        let r = RenderSettings {
            step_mm: self.step_mm,
            ..RenderSettings::default()
        }
        .reference(spacing);
        ShadingOptions {
            step_mm: r.step_mm,
            preintegrated: r.preintegrated,
            jitter: r.jitter,
            ..self
        }
    }

    pub fn apply(&self, s: &mut RenderSettings) {
        self.shading.apply(s);
        if let Some(kd) = self.diffuse {
            s.diffuse = kd;
        }
        s.use_ao &= !self.no_ao;
        s.cut_lighting = self.cut_lighting;
        s.cut_tint = self.cut_tint;
        s.preintegrated = self.preintegrated;
        s.jitter = self.jitter;
        s.tricubic = self.tricubic;
        s.skip_empty = self.skip_empty;
        s.step_mm = self.step_mm;
        s.iso = self.iso;
        s.foveation = self.foveation;
        s.reproject = self.reproject;
        s.scattering = self.scattering;
        s.anisotropy = self.anisotropy;
        s.light_from = self.light_from;
    }
}

impl Default for LightingOptions {
    fn default() -> Self {
        LightingOptions {
            mode: LightingMode::Ao,
            environment: "studio".into(),
            sh: ShParams::default(),
            yaw_deg: 0.0,
            shading: ShadingOptions::default(),
        }
    }
}

impl LightingOptions {
    pub fn uses_sh(&self) -> bool {
        self.mode != LightingMode::Ao
    }

    /// Sets the ray caster's shading, then its weights for this lighting mode.
    pub fn apply(&self, s: &mut RenderSettings) {
        self.shading.apply(s);
        match self.mode {
            LightingMode::Ao => s.sh_weight = 0.0,
            LightingMode::Sh => {
                s.ambient = 0.0;
                s.diffuse = 0.0;
                s.specular = 0.0;
                s.sh_weight = 1.0;
                s.sh_times_ao = false;
            }
            LightingMode::AoSh => {
                s.ambient *= 0.4;
                s.sh_weight = 1.0;
                s.sh_times_ao = true;
            }
        }
    }
}

/// The shared SH visibility volume and the environment lighting it.
pub struct ShLighting {
    pub volume: ShVolume,
    pub environment: Environment,
    /// Turn of the environment about the world's up axis (radians); changing it costs one
    /// projection of the light, no visibility.
    pub yaw: f32,
    light: ShLight,
}

impl ShLighting {
    /// Loads the environment, precomputes V_PSH of `cao`'s opacity O (of `vol`'s geometry; a
    /// progress bar when asked) and gives `cao` the SH dilation radius, so its tools get SH
    /// dilation maps.
    pub fn new(
        gpu: &Gpu,
        vol: &Volume,
        opts: &LightingOptions,
        cao: &mut Cao,
        show_progress: bool,
    ) -> Result<ShLighting> {
        let environment = Environment::from_spec(&opts.environment)
            .map_err(|e| AppError::Usage(format!("--light: {e}")))?;
        opts.sh
            .validate()
            .map_err(|e| AppError::Usage(format!("SH visibility: {e}")))?;
        let mut volume = ShVolume::new(gpu, vol, opts.sh)?;
        let slices = volume.grid.dims[2] as u64;
        let bar = show_progress.then(|| progress_bar(slices, "SH visibility"));
        let (o, stride) = cao.opacity()?;
        volume.precompute((&o, stride), &mut |done, _| {
            if let Some(b) = &bar {
                b.set_position(done as u64)
            }
        })?;
        if let Some(b) = bar {
            b.finish_and_clear();
        }
        cao.sh_radius_mm = Some(volume.grid.radius_mm(&opts.sh));
        Ok(ShLighting {
            volume,
            environment,
            yaw: opts.yaw_deg.to_radians(),
            light: ShLight {
                coeffs: [[0.0; 16]; 3],
            },
        })
    }

    /// Projects the environment, turned by `turn` (radians) more than [`ShLighting::yaw`],
    /// into the data frame of `vol` placed by `placement`.
    pub fn update_light(&mut self, vol: &Volume, placement: &Placement, turn: f32) {
        self.light =
            self.environment
                .project(data_from_environment(vol, placement, self.yaw + turn));
    }

    /// Records this frame's clip-aware SH update (after CAO's, which it reads).
    pub fn record_frame(
        &mut self,
        gpu: &Gpu,
        cmd: ash::vk::CommandBuffer,
        cao: &Cao,
    ) -> ShFrameMetrics {
        gpu.barrier(cmd);
        self.volume.record_frame(cmd, cao, false)
    }

    /// What the ray caster binds: the volume's textures and the current light.
    pub fn binding(&self) -> ShBinding<'_> {
        ShBinding {
            images: &self.volume.images,
            light: &self.light.coeffs,
        }
    }
}

/// The rotation taking environment directions (world axes turned by `yaw` about +Y) to the
/// volume's data frame (voxel axes in mm, where the visibility rays were cast).
pub fn data_from_environment(vol: &Volume, placement: &Placement, yaw: f32) -> DMat3 {
    let world_from_data = DMat3::from_quat(placement.rotation.as_dquat())
        * world_from_lps().as_dmat3()
        * vol.directions;
    world_from_data.inverse() * DMat3::from_quat(DQuat::from_rotation_y(yaw as f64))
}
