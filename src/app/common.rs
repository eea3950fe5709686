//! What app/'s files build on, importing none of them: the error type, progress bars, opening
//! a volume, precomputing its AO with each method, the headless renderer, and what `info` and
//! `ao` print and write. The subcommands that run a frame loop (`render`, `start`) are app/'s
//! own (mod.rs), over frame_loop, session, desktop and headset.

use crate::ao::cao::MethodGpu;
use crate::ao::histogram::{self, HistParams};
use crate::ao::histogram_gpu::HistogramGpu;
use crate::ao::lao::{directions, LaoTiming};
pub use crate::ao::method::{histogram_tables, AoVolume, HistogramTables};
use crate::ao::{filtered, AoConfig, AoMethod, LaoGpu, LaoParams};
use crate::gpu::{Gpu, GpuError, OutOfMemory};
use crate::render::png_out::PngError;
use crate::render::{
    FrameViews, RenderSettings, Renderer, StereoImage, StereoTarget, VolumeTextures,
};
use crate::scene::Tool;
use crate::space::Placement;
use crate::volume::nrrd::{self, NrrdData};
use crate::volume::raw::RawSpec;
use crate::volume::transfer::{TfError, TransferFunction};
use crate::volume::{ct_head, phantom, Volume, VolumeError};
use std::path::Path;

#[derive(Debug, thiserror::Error)]
pub enum AppError {
    #[error(transparent)]
    Gpu(#[from] GpuError),
    #[error(transparent)]
    Volume(#[from] VolumeError),
    #[error(transparent)]
    Tf(#[from] TfError),
    #[error(transparent)]
    Png(#[from] PngError),
    #[error("{0}")]
    Usage(String),
    #[error("{path}: {msg}")]
    Output { path: String, msg: String },
    #[error(transparent)]
    Xr(Box<crate::xr::XrError>),
}

impl From<crate::xr::XrError> for AppError {
    fn from(e: crate::xr::XrError) -> Self {
        AppError::Xr(Box::new(e))
    }
}

pub type Result<T> = std::result::Result<T, AppError>;

/// Default phantom size when no volume is given and the CT head has not been fetched.
pub const DEFAULT_PHANTOM: usize = 128;

/// Opens a volume: a file path (.nrrd, .nhdr, or raw with `raw`), `phantom[:N]`, `ct-head`, or
/// nothing (the CT head if `cao-xr fetch-ct` has cached it, else the phantom).
pub fn load_volume(spec: Option<&str>, raw: Option<&RawSpec>) -> Result<Volume> {
    let cached = ct_head::cached_path();
    match spec {
        None if cached.exists() => Ok(nrrd::load(&cached)?),
        None => Ok(phantom::head(DEFAULT_PHANTOM)),
        Some("ct-head") => {
            if !cached.exists() {
                return Err(AppError::Usage(format!(
                    "the CT head is not in the data cache ({}): run `cao-xr fetch-ct` first",
                    cached.display()
                )));
            }
            Ok(nrrd::load(&cached)?)
        }
        Some(s) if s == "phantom" || s.starts_with("phantom:") => {
            let n = match s.strip_prefix("phantom:") {
                None => DEFAULT_PHANTOM,
                Some(n) => n
                    .parse::<usize>()
                    .ok()
                    .filter(|n| (4..=1024).contains(n))
                    .ok_or_else(|| {
                        AppError::Usage(format!(
                            "'{s}': phantom size must be 4..=1024, e.g. phantom:64"
                        ))
                    })?,
            };
            Ok(phantom::head(n))
        }
        Some(path) => {
            let p = Path::new(path);
            if raw.is_none() && crate::volume::dicom::is_series_spec(path) {
                return Ok(crate::volume::dicom::load_spec(path)?);
            }
            if let Some(spec) = raw {
                return Ok(crate::volume::raw::load(p, spec)?);
            }
            // FILE#T: volume T of a 4-D NIfTI or NRRD file (a file named so exists wins)
            let four_d = |f: &str| {
                let l = f.to_lowercase();
                [".nii", ".nii.gz", ".nrrd", ".nhdr"]
                    .iter()
                    .any(|e| l.ends_with(e))
            };
            let (p, frame) = match path.rsplit_once('#') {
                Some((file, t)) if !p.exists() && four_d(file) => {
                    let t = t.parse::<u64>().map_err(|_| {
                        AppError::Usage(format!(
                            "'{path}': after # comes the volume number of a 4-D file, e.g. {file}#0"
                        ))
                    })?;
                    (Path::new(file), Some(t))
                }
                _ => (p, None),
            };
            let ext = p
                .extension()
                .and_then(|e| e.to_str())
                .unwrap_or("")
                .to_lowercase();
            let lower = p.to_string_lossy().to_lowercase();
            match ext.as_str() {
                "nrrd" | "nhdr" => Ok(nrrd::load_frame(p, frame)?),
                "nii" => Ok(crate::volume::nifti::load_frame(p, frame)?),
                "gz" if lower.ends_with(".nii.gz") => {
                    Ok(crate::volume::nifti::load_frame(p, frame)?)
                }
                "mha" | "mhd" => Ok(crate::volume::metaimage::load(p)?),
                // one file of a DICOM series (named so, or found to be one): the whole series
                "dcm" | "dicom" | "ima" if p.exists() => {
                    Ok(crate::volume::dicom::load_file_series(p)?)
                }
                "raw" | "dat" | "bin" => Err(AppError::Usage(format!(
                    "{path}: a raw volume needs --raw-dims X,Y,Z (and --raw-type, --raw-spacing)"
                ))),
                _ if crate::volume::dicom::is_dicom_file(p) => {
                    Ok(crate::volume::dicom::load_file_series(p)?)
                }
                _ if !p.exists() => Err(AppError::Usage(format!(
                    "{path}: no such file or directory (volumes: a .nrrd/.nhdr/.nii/.nii.gz/.mha/.mhd file, a DICOM series directory DIR or DIR#N or one of its files, raw with --raw-dims, phantom[:N], ct-head)"
                ))),
                _ => Err(AppError::Usage(format!(
                    "{path}: unknown volume format (supported: .nrrd, .nhdr, .nii, .nii.gz, .mha, .mhd, a DICOM series directory or file, raw with --raw-dims)"
                ))),
            }
        }
    }
}

/// For `info` on a DICOM series argument (`DIR`, `DIR#N`, `DIR#UID`): the listing of the
/// directory's series, and whether one series is chosen (only one, or picked) so that
/// `load_volume` will load it. `None` for any other volume argument.
pub fn dicom_listing(spec: Option<&str>) -> Result<Option<(String, bool)>> {
    use crate::volume::dicom;
    let Some(spec) = spec.filter(|s| dicom::is_series_spec(s)) else {
        return Ok(None);
    };
    let (dir, pick) = dicom::parse_spec(spec);
    let scan = dicom::scan(&dir)?;
    let chosen = pick.is_some() || scan.series.len() == 1;
    let head = format!(
        "{}: {} DICOM series\n{}",
        dir.display(),
        scan.series.len(),
        scan.listing()
    );
    Ok(Some((head, chosen)))
}

/// A terminal progress bar counting slices (hidden when stderr is not a terminal).
pub fn progress_bar(len: u64, label: &str) -> indicatif::ProgressBar {
    progress_bar_of(len, label, "slices")
}

/// A terminal progress bar counting `unit`.
pub fn progress_bar_of(len: u64, label: &str, unit: &str) -> indicatif::ProgressBar {
    let bar = indicatif::ProgressBar::new(len);
    bar.set_style(
        indicatif::ProgressStyle::with_template(&format!(
            "{{msg:>12}} [{{bar:40}}] {{pos}}/{{len}} {unit}  {{elapsed_precise}} (eta {{eta}})"
        ))
        .unwrap()
        .progress_chars("=> "),
    );
    bar.set_message(label.to_string());
    bar
}

/// Classifies the volume and precomputes its LAO on the GPU, with a progress bar.
pub fn precompute_ao(
    gpu: &Gpu,
    lao: &LaoGpu,
    vol: &Volume,
    tf: &TransferFunction,
    params: &LaoParams,
    show_progress: bool,
) -> Result<AoVolume> {
    params.validate().map_err(AppError::Usage)?;
    crate::render::check_volume_fits_gpu(gpu, vol)?;
    let opacity = tf.opacity_volume(vol);
    let bar = show_progress.then(|| progress_bar(vol.dims[2] as u64, "LAO"));
    let v = AoVolume::lao(gpu, lao, vol, opacity, params, &mut |done, _| {
        if let Some(b) = &bar {
            b.set_position(done as u64)
        }
    })?;
    if let Some(b) = bar {
        b.finish_and_clear();
    }
    Ok(v)
}

/// Bytes per voxel of an upload's host-visible staging copy (one f32 volume at a time).
const STAGING_BYTES_PER_VOXEL: u64 = 4;

/// The smallest `--downsample N` that the GPU memory `m` says was missing would make room for:
/// allocations of at least a byte per voxel are taken to scale with the volume, at no less
/// than [`crate::render::GPU_BYTES_PER_VOXEL`] plus a staging copy per voxel in all; the others
/// to stay as they are. None where not even N = 64 fits.
pub fn downsample_estimate(vol: &Volume, m: &OutOfMemory) -> Option<usize> {
    let voxels = vol.voxel_count().max(1) as u64;
    let (scaled, fixed): (Vec<u64>, Vec<u64>) =
        m.held.iter().chain([&m.bytes]).partition(|&&b| b >= voxels);
    let per_voxel = (scaled.iter().sum::<u64>() as f64 / voxels as f64)
        .max((crate::render::GPU_BYTES_PER_VOXEL + STAGING_BYTES_PER_VOXEL) as f64);
    let fixed: u64 = fixed.iter().sum();
    (2..=MAX_DOWNSAMPLE).find(|&n| {
        let v: u64 = vol
            .dims
            .iter()
            .map(|&d| (d as u64).div_ceil(n as u64))
            .product();
        fixed as f64 + per_voxel * v as f64 <= m.available as f64
    })
}

/// The largest `--downsample` suggested.
pub const MAX_DOWNSAMPLE: usize = 64;

/// GPU memory running out while `vol` is set up (past the limits check: beside everything else
/// the GPU holds), told with the volume and the `--downsample N` that would fit (`fits`, else
/// [`downsample_estimate`]). Any other error is returned as it is.
pub fn fit_advice(vol: &Volume, e: AppError, fits: Option<usize>) -> AppError {
    let AppError::Gpu(GpuError::OutOfMemory(m)) = &e else {
        return e;
    };
    let [x, y, z] = vol.dims;
    // N is for this volume; a volume already downsampled by D needs D x N from the file
    let done = vol.downsampled_by();
    AppError::Gpu(GpuError::Other(format!(
        "volume {} ({x} x {y} x {z}) does not fit beside everything else on the GPU: {m}; {}",
        vol.name,
        match fits.or_else(|| downsample_estimate(vol, m)) {
            Some(n) => format!("try --downsample {}", n * done),
            None => format!(
                "not even --downsample {} makes it fit: free GPU memory first",
                MAX_DOWNSAMPLE * done
            ),
        }
    )))
}

/// Classifies the volume and precomputes V_PAO with the configured AO method: LAO (with a
/// progress bar when asked), or the filters over the density they filter (one fast pass).
/// Running out of GPU memory is told with [`fit_advice`].
pub fn precompute(
    gpu: &Gpu,
    lao: &LaoGpu,
    vol: &Volume,
    tf: &TransferFunction,
    ao: &AoConfig,
    show_progress: bool,
) -> Result<AoVolume> {
    precompute_method(gpu, lao, vol, tf, ao, show_progress).map_err(|e| fit_advice(vol, e, None))
}

/// The AO of no method yet ([`AoVolume::open`]).
pub(crate) fn open_ao(gpu: &Gpu, vol: &Volume) -> Result<AoVolume> {
    crate::render::check_volume_fits_gpu(gpu, vol)?;
    Ok(AoVolume::open(gpu, vol)?)
}

/// [`precompute`] with GPU memory exhaustion left as it is (for a caller that tells it).
pub(crate) fn precompute_method(
    gpu: &Gpu,
    lao: &LaoGpu,
    vol: &Volume,
    tf: &TransferFunction,
    ao: &AoConfig,
    show_progress: bool,
) -> Result<AoVolume> {
    let fp = match ao.method {
        AoMethod::Lao => return precompute_ao(gpu, lao, vol, tf, &ao.lao, show_progress),
        AoMethod::Histogram(hp) => {
            let h = histogram_state(
                gpu,
                vol,
                hp,
                Some(&histogram::default_cache_dir()),
                show_progress,
            )?;
            return precompute_histogram(gpu, lao, vol, tf, &ao.lao, h);
        }
        AoMethod::Filter(fp) => fp,
    };
    ao.lao.validate().map_err(AppError::Usage)?;
    fp.validate().map_err(AppError::Usage)?;
    crate::render::check_volume_fits_gpu(gpu, vol)?;
    let density = filtered::density(fp.input, &tf.opacity_volume(vol), vol);
    Ok(AoVolume::filter(gpu, vol, density, fp)?)
}

/// The local-histogram method set up for `vol` (the clustering loaded from `cache` or computed,
/// with a progress bar when asked).
pub fn histogram_state(
    gpu: &Gpu,
    vol: &Volume,
    hp: HistParams,
    cache: Option<&Path>,
    show_progress: bool,
) -> Result<HistogramGpu> {
    hp.validate().map_err(AppError::Usage)?;
    crate::render::check_volume_fits_gpu(gpu, vol)?;
    let bar = show_progress.then(|| progress_bar_of(1, "local histograms", "batches"));
    let h = HistogramGpu::new(gpu, vol, hp, cache, &mut |done, total, phase| {
        if let Some(b) = &bar {
            b.set_length(total.max(1));
            b.set_position(done);
            b.set_message(phase.to_string());
        }
    })?;
    if let Some(b) = bar {
        b.finish_and_clear();
        let t = &h.timing;
        if t.cached {
            eprintln!("{}: local histograms read from the cache", vol.name);
        } else if hp.clusters > 0 {
            eprintln!(
                "{}: local histograms {:.1} s, LBG training {:.1} s, assignment {:.1} s",
                vol.name,
                t.histograms_ms / 1e3,
                t.training_ms / 1e3,
                t.assignment_ms / 1e3
            );
        }
    }
    Ok(h)
}

/// V_PAO and the bleeding volume of the local-histogram method `h` under `tf`: one table
/// update and one pass (the clusters' values, or with N = 0 the direct sums).
pub fn precompute_histogram(
    gpu: &Gpu,
    lao: &LaoGpu,
    vol: &Volume,
    tf: &TransferFunction,
    params: &LaoParams,
    h: HistogramGpu,
) -> Result<AoVolume> {
    params.validate().map_err(AppError::Usage)?;
    Ok(AoVolume::histogram(gpu, lao, vol, tf, h)?)
}

/// Everything needed to render a volume from scratch on the GPU.
pub struct HeadlessRenderer {
    pub gpu: Gpu,
    pub lao: LaoGpu,
    pub renderer: Renderer,
}

impl HeadlessRenderer {
    pub fn new(gpu: &Gpu) -> Result<Self> {
        Ok(HeadlessRenderer {
            gpu: gpu.clone(),
            lao: LaoGpu::new(gpu)?,
            renderer: Renderer::new(gpu)?,
        })
    }

    /// Renders both eyes of `frame` (with its AO buffer, or no AO) in one command buffer.
    pub fn render(
        &mut self,
        tex: &VolumeTextures,
        frame: &FrameViews,
        size: (u32, u32),
        settings: &RenderSettings,
    ) -> Result<StereoImage> {
        let target = StereoTarget::new(&self.gpu, size.0, size.1)?;
        tex.prepare(settings)?;
        let renderer = &mut self.renderer;
        let mut rec = Ok(());
        let gpu = &self.gpu;
        gpu.submit_and_wait(|cmd| {
            // V_AO was written by earlier submissions' compute passes.
            gpu.barrier(cmd);
            rec = renderer
                .record(cmd, &target, tex, frame, settings)
                .map(|()| target.cmd_finish(cmd));
        })?;
        rec?;
        Ok(target.read_back(&self.gpu)?)
    }
}

/// `cao-xr info`: the volume's dims, type, spacing, orientation, range, modality, size, the
/// transfer function chosen for it and the presets suited to it.
pub fn info_report(v: &Volume, tf: &TransferFunction) -> String {
    let (lo, hi) = v.value_range();
    let ext = v.extent_mm();
    let d = v.directions;
    let presets = crate::volume::transfer::presets_for_volume(v).join(", ");
    [
        format!("name        {}", v.name),
        format!("dims        {} x {} x {}", v.dims[0], v.dims[1], v.dims[2]),
        format!("type        {}", v.voxels.type_name()),
        format!(
            "spacing     {:.4} x {:.4} x {:.4} mm",
            v.spacing[0], v.spacing[1], v.spacing[2]
        ),
        format!(
            "directions  i {:?}  j {:?}  k {:?} (LPS)",
            d.x_axis, d.y_axis, d.z_axis
        ),
        format!("values      {lo} .. {hi}"),
        format!("modality    {:?}", v.modality),
        format!("size        {:.1} x {:.1} x {:.1} mm", ext.x, ext.y, ext.z),
        format!("tf          {}", tf.name),
        format!("presets     {presets}"),
        format!("GPU         {}", gpu_report(v)),
    ]
    .map(|l| l + "\n")
    .concat()
        + &v.labels
            .as_ref()
            .map_or(String::new(), |l| l.report(v.spacing))
}

/// "lao 22.6, filters 49.0, histogram 37.0 bytes per voxel (2.5, 5.7, 4.3 GiB) ...": what the GPU
/// holds of `vol` under each method with its default parameters ([`gpu_volumes`]).
fn gpu_report(vol: &Volume) -> String {
    let methods = [
        ("lao", AoMethod::Lao),
        ("filters", AoMethod::Filter(Default::default())),
        ("histogram", AoMethod::Histogram(HistParams::default())),
    ];
    let per_voxel: Vec<(&str, f64)> = methods
        .iter()
        .map(|(name, m)| (*name, gpu_volumes(vol, m).iter().map(|x| x.1).sum()))
        .collect();
    let n = vol.voxel_count() as f64;
    let each = |f: &dyn Fn(f64) -> String| {
        per_voxel
            .iter()
            .map(|&(_, b)| f(b))
            .collect::<Vec<_>>()
            .join(", ")
    };
    format!(
        "{} bytes per voxel ({} GiB) held once set up (loading's staging, the clustering's \
         batches, a frame's images, its tools' staged boxes and O_c over the slices its tools \
         reach come on top)",
        per_voxel
            .iter()
            .map(|(name, b)| format!("{name} {b:.1}"))
            .collect::<Vec<_>>()
            .join(", "),
        each(&|b| format!("{:.1}", b * n / (1u64 << 30) as f64)),
    )
}

/// The volumes the GPU holds for `vol` under `method`, in bytes per
/// voxel by name: what every method holds (the scalar image, O_c, CAO's mask, V_AO, which the
/// ray caster reads itself, and with labels their ids and the margins' glow) and the method's
/// own. O and V_PAO are the host's once CAO is set up, and the GPU holds O_c only over the
/// z-slices a frame's tools reach ([`crate::ao::cao::Cao::windowed`]; whole with the SH
/// visibility on). A frame's images, tables, staged boxes and O_c slices and the
/// staging copies while loading come on top (the peak `render` prints).
pub fn gpu_volumes(vol: &Volume, method: &AoMethod) -> Vec<(&'static str, f64)> {
    let scalar = match vol.voxels {
        crate::volume::Voxels::U8(_) => 1.0,
        crate::volume::Voxels::U16(_) | crate::volume::Voxels::I16(_) => 2.0,
        crate::volume::Voxels::F32(_) => 4.0,
    };
    let ao = crate::ao::stored::BYTES_PER_VOXEL as f64;
    let mut v = vec![("scalars", scalar), ("mask", 0.25), ("V_AO", ao)];
    if let Some(l) = vol.labels.as_deref() {
        v.push(("structure ids (ray caster, CAO)", 2.0));
        if l.structures.iter().any(|s| s.margin_mm.is_some()) {
            v.push(("margin glow", 1.0));
        }
    }
    match method {
        // O_c only over the slices a frame's tools reach (O and V_PAO are the host's: a frame
        // stages only its boxes'); the box statistics over a window of slices.
        AoMethod::Lao => v.push(("clear bits", 1.0 / 8.0)),
        AoMethod::Filter(p) => {
            let (_, window) =
                crate::ao::filter_gpu::stats_window(vol.dims, vol.spacing, p, (None, None));
            v.push((
                "box statistics",
                32.0 * window as f64 / vol.dims[2].max(1) as f64,
            ));
        }
        AoMethod::Histogram(h) => {
            v.push(("shades", 2.0));
            if h.clusters > 0 {
                // The precomputed E is the front cluster's.
                v.extend([("E", 4.0), ("front cluster ids", 2.0)]);
            } else {
                v.push(("E (precomputed, current)", 8.0));
            }
            if h.hemispheres {
                // 16-bit words for integer data (histogram_split.glsl), else f32.
                v.push(("scalars (the hemispheres' split)", scalar.max(2.0)));
            }
        }
    }
    v
}

/// Parses `SHAPE[:SIZE_MM[:X,Y,Z]]` (offset in mm from the volume centre: x right, y up, z
/// towards the viewer; default a cut into the front) into a carving tool, or a probe with a
/// `probe-` prefix (`probe-sphere:60`).
pub fn parse_tool(spec: &str, placement: &Placement) -> Result<Tool> {
    use crate::clip::Shape;
    use crate::scene::ToolMode;
    let bad = |why: &str| AppError::Usage(format!("--tool '{spec}': {why}"));
    let mut parts = spec.split(':');
    let name = parts.next().unwrap_or("");
    let (mode, name) = match name.strip_prefix("probe-") {
        Some(n) => (ToolMode::Probe, n),
        None => (ToolMode::Carve, name),
    };
    let shape =
        Shape::builtin(name).ok_or_else(|| bad("shape must be sphere, box, cylinder or torus"))?;
    let size_mm: f32 = match parts.next() {
        Some(s) => s
            .parse()
            .ok()
            .filter(|v: &f32| *v > 0.0 && *v < 1000.0)
            .ok_or_else(|| bad("size must be 0..1000 mm"))?,
        None => 30.0,
    };
    let offset = match parts.next() {
        Some(s) => crate::space::parse_triple::<f32>(s)
            .map(glam::Vec3::from_array)
            .map_err(|e| bad(&format!("the offset must be X,Y,Z in mm ({e})")))?,
        None => glam::Vec3::new(0.0, 30.0, 70.0),
    };
    if let Some(extra) = parts.next() {
        return Err(bad(&format!(
            "unexpected ':{extra}': expected SHAPE[:SIZE_MM[:X,Y,Z]]"
        )));
    }
    Ok(Tool {
        shape,
        pose: crate::space::Pose {
            position: placement.center + offset * 1e-3 * placement.scale,
            orientation: glam::Quat::IDENTITY,
        },
        size: size_mm * 1e-3 * placement.scale,
        mode,
        active: true,
    })
}

/// The JSON sidecar of an AO volume: everything an outside checker needs to recompute it.
pub fn ao_sidecar(vol: &Volume, tf: &TransferFunction, ao: &AoConfig) -> serde_json::Value {
    let params = &ao.lao;
    if let AoMethod::Histogram(h) = &ao.method {
        return serde_json::json!({
            "volume": vol.name,
            "method": "histogram",
            "radius_mm": h.radius_mm,
            "bins": h.bins,
            "clusters": h.clusters,
            "hemispheres": h.hemispheres,
            "dims": vol.dims,
            "spacing_mm": vol.spacing,
            "transfer_function": tf,
            "value_range": [vol.value_range().0, vol.value_range().1],
            "definition": "docs/design.md, Local-histogram AO: bin(u) = min(B-1, floor(B (value - v_min) \
        / (v_max - v_min))); q = coverage * TF opacity at the bin centre (the written opacity file); \
        S_r = {u != v : |(u - v) s| <= r mm}, w = (s_min / |(u - v) s|)^2, W = sum of w over S_r \
        (out-of-grid members included, with q = 0); A = 1 - sum w q / W; E = sum w q rgb / sum w q \
        (the bleeding file); clusters > 0: each voxel its cluster's values; hemispheres: \
        Delta(v) = the scalar's central differences (neighbours clamped), flat where \
        |Delta_i / (2 s_i)| < 0.004 (v_max - v_min) per mm (S_r kept), else the sums and W run \
        over H_f = {o in S_r : o . Delta <= 0}",
        });
    }
    if let AoMethod::Filter(f) = &ao.method {
        return serde_json::json!({
            "volume": vol.name,
            "method": "filter",
            "estimator": f.estimator.name(),
            "radius_mm": f.radius_mm,
            "half_widths": f.half_widths(vol.spacing),
            "input": f.input.name(),
            "dims": vol.dims,
            "spacing_mm": vol.spacing,
            "transfer_function": tf,
            "value_range": [vol.value_range().0, vol.value_range().1],
            "definition": "docs/design.md, Filtered AO: the density d (the written opacity file) \
        over the tangent box B(c), h_a = max(1, round(R/s_a)), c = v + round(-R n_a/s_a) clamped, \
        out-of-grid members d = 0",
        });
    }
    let dirs: Vec<[f64; 3]> = directions(params.rays)
        .iter()
        .map(|d| d.to_array())
        .collect();
    serde_json::json!({
        "volume": vol.name,
        "dims": vol.dims,
        "spacing_mm": vol.spacing,
        "rays": params.rays,
        "directions": dirs,
        "steps": params.steps,
        "step_mm": params.step_mm,
        "transfer_function": tf,
        "value_range": [vol.value_range().0, vol.value_range().1],
        "definition": "A(v) = 1/(K M) sum_k sum_{m=1..M} prod_{i=1..m-1} (1 - O(p_i))^(D/1mm), \
    p_i = x + i D d_k in mm, x = (index + 0.5) * spacing, O trilinear at voxel centres, 0 outside",
    })
}

fn write_json(path: &Path, value: &serde_json::Value) -> Result<()> {
    let text = serde_json::to_string_pretty(value).expect("JSON values serialise");
    std::fs::write(path, text + "\n").map_err(|e| AppError::Output {
        path: path.display().to_string(),
        msg: e.to_string(),
    })
}

/// `cao-xr ao`: the AO volume as float32 NRRD, its JSON sidecar, optionally the opacity volume
/// (for the filters: the density they filtered; for the local histograms: q) and, for the local
/// histograms, the bleeding colour E (RGB). With `cpu`, the CPU reference computes it instead of
/// the GPU.
pub fn write_ao(
    gpu: Option<&Gpu>,
    vol: &Volume,
    tf: &TransferFunction,
    config: &AoConfig,
    out: &Path,
    opacity_out: Option<&Path>,
    bleeding_out: Option<&Path>,
) -> Result<LaoTiming> {
    let params = &config.lao;
    let histogram = matches!(config.method, AoMethod::Histogram(_));
    if bleeding_out.is_some() && !histogram {
        return Err(AppError::Usage(
            "--bleeding-out: only the local-histogram method (--ao histogram) has a bleeding colour"
                .into(),
        ));
    }
    let (ao, opacity, timing, bleeding) = match gpu {
        Some(gpu) => {
            let lao = LaoGpu::new(gpu)?;
            let r = precompute(gpu, &lao, vol, tf, config, true)?;
            let ao = crate::ao::stored::read(&r.ao_buf, vol.voxel_count())?;
            let e = match &r.method {
                MethodGpu::Histogram(h) => Some(h.read_e(&h.precomputed_e()?)?),
                _ => None,
            };
            (ao, r.opacity, r.timing, e)
        }
        None => {
            params.validate().map_err(AppError::Usage)?;
            let opacity = tf.opacity_volume(vol);
            let t0 = std::time::Instant::now();
            let mut bleeding = None;
            let (ao, opacity) = match &config.method {
                AoMethod::Lao => (
                    crate::ao::cpu::lao(&opacity, vol.dims, vol.spacing, params),
                    opacity,
                ),
                AoMethod::Filter(f) => {
                    f.validate().map_err(AppError::Usage)?;
                    let d = filtered::density(f.input, &opacity, vol);
                    (filtered::filtered_ao(&d, vol.dims, vol.spacing, f), d)
                }
                AoMethod::Histogram(h) => {
                    h.validate().map_err(AppError::Usage)?;
                    if h.clusters > 0 {
                        return Err(AppError::Usage(
                            "--cpu computes the direct definition of the local-histogram AO: \
                             add --clusters 0"
                                .into(),
                        ));
                    }
                    let (q, shades, table) = histogram::direct_inputs(vol, tf, h.bins, &[]);
                    let nb = histogram::Neighbourhood::new(h.radius_mm, vol.spacing);
                    let splits = if h.hemispheres {
                        histogram::splits(vol)
                    } else {
                        Vec::new()
                    };
                    let (a, e) =
                        histogram::direct_reference(vol.dims, &q, &shades, &table, &nb, &splits);
                    bleeding = Some(e);
                    (a, q)
                }
            };
            let timing = LaoTiming {
                wall_ms: t0.elapsed().as_secs_f64() * 1e3,
                ..Default::default()
            };
            (ao, opacity, timing, bleeding)
        }
    };
    let grid = vol.grid();
    let write = |path: &Path, data: &[f32]| nrrd::write(path, &grid, NrrdData::F32(data), false);
    write(out, &ao)?;
    write_json(&out.with_extension("json"), &ao_sidecar(vol, tf, config))?;
    if let Some(o) = opacity_out {
        write(o, &opacity)?;
    }
    if let (Some(path), Some(e)) = (bleeding_out, bleeding) {
        let flat: Vec<f32> = e.iter().flatten().copied().collect();
        nrrd::write_rgb(path, &grid, &flat)?;
    }
    Ok(timing)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tool_specs_are_parsed_strictly_and_refused_by_name() {
        let p = Placement::default();
        let t = parse_tool("probe-box:25:10,-5,30", &p).unwrap();
        assert_eq!(t.mode, crate::scene::ToolMode::Probe);
        let want = p.center + glam::Vec3::new(10.0, -5.0, 30.0) * 1e-3 * p.scale;
        assert!((t.pose.position - want).length() < 1e-6);
        for bad in [
            "sphere:30:1,x,2,3",
            "sphere:30:nan,0,0",
            "sphere:30:0,inf,0",
            "sphere:30:1,2",
            "sphere:30:1,2,3:4",
            "sphere:nan",
            "cone:30",
        ] {
            let e = parse_tool(bad, &p).unwrap_err().to_string();
            assert!(e.contains(&format!("--tool '{bad}'")), "{bad}: {e}");
        }
    }
}
