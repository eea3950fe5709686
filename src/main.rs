//! The cao-xr command line. Every subcommand is a thin call into the library.

use anyhow::{bail, Context, Result};
use cao_xr::ao::filtered::{FilterInput, FilterParams, VarianceModulation};
use cao_xr::ao::histogram::HistParams;
use cao_xr::ao::lao::LaoKernel;
use cao_xr::ao::sh::ShParams;
use cao_xr::ao::{AoConfig, AoMethod, LaoParams};
use cao_xr::app;
use cao_xr::app::lighting::{LightingMode, LightingOptions, ShadingOptions};
use cao_xr::app::session::SessionSpec;
use cao_xr::gpu::Gpu;
use cao_xr::input::{write_script, ScriptKind, ScriptParams};
use cao_xr::render::{RenderSettings, Shading};
use cao_xr::volume::raw::{RawSpec, RawType};
use cao_xr::volume::transfer::TransferFunction;
use cao_xr::volume::{ct_head, phantom};
use clap::{Args, Parser, Subcommand};
use std::path::PathBuf;
use std::sync::Arc;

#[derive(Parser)]
#[command(
    name = "cao-xr",
    version,
    about = "Stereo CT/MRI volume viewer with (Contextual) Ambient Occlusion"
)]
struct Cli {
    /// Turn Vulkan validation on (default: on in debug builds; env CAO_XR_VALIDATION=0/1).
    #[arg(long, global = true)]
    validation: bool,
    #[command(subcommand)]
    cmd: Cmd,
}

#[derive(Subcommand)]
enum Cmd {
    /// The main job: a headset session if an OpenXR runtime answers, else the desktop window if
    /// there is a display, else a headless render of a carved volume to out/render.
    Start(StartArgs),
    /// Render both eyes of a volume (LAO-lit) to DIR/left.png, right.png and stereo.png.
    Render(RenderArgs),
    /// Precompute the LAO volume; write it as float32 NRRD plus a JSON sidecar.
    Ao(AoArgs),
    /// Benchmarks that print tables (medians of several runs).
    Bench(BenchCmdArgs),
    /// PSNR and SSIM (on luma) of picture B against picture A, e.g. a render against
    /// `render --reference`; optionally a difference image.
    Compare(CompareArgs),
    /// Fetch the real CT head (Debian's invesalius-examples) and convert it to NRRD in the cache.
    FetchCt(FetchCtArgs),
    /// Write the procedural head phantom as NRRD.
    Phantom(PhantomArgs),
    /// Render every frame of a pose stream headless (both eyes side by side) with per-frame
    /// metrics: DIR/frame-00000.png ..., DIR/metrics.csv, optionally an animated PNG.
    Replay(ReplayArgs),
    /// Open a desktop window: the mouse and keys are the head and the right hand (see README).
    View(ViewArgs),
    /// Run a headset session through OpenXR (XR_KHR_vulkan_enable2): both eyes into the
    /// runtime's swapchain, controllers as hands, optionally recording the pose stream.
    Xr(XrArgs),
    /// Generate a scripted pose stream (JSON Lines) for replay and tests.
    Script(ScriptArgs),
    /// Print a volume's dimensions, type, spacing, orientation and value range.
    Info(InfoArgs),
}

#[derive(Args)]
struct StartArgs {
    #[command(flatten)]
    vol: VolumeArgs,
    #[command(flatten)]
    lao: LaoArgs,
    #[command(flatten)]
    light: LightArgs,
}

#[derive(Args)]
struct RenderArgs {
    #[command(flatten)]
    vol: VolumeArgs,
    #[command(flatten)]
    lao: LaoArgs,
    #[command(flatten)]
    light: LightArgs,
    /// Output directory.
    #[arg(long, default_value = "out/render")]
    out: PathBuf,
    /// Pixels per eye, WIDTHxHEIGHT.
    #[arg(long, default_value = "640x640", value_parser = parse_size)]
    size: (u32, u32),
    /// Render without ambient occlusion (for comparison).
    #[arg(long)]
    no_ao: bool,
    /// Weight of the gradient diffuse term (overrides the --shading mode's).
    #[arg(long)]
    diffuse: Option<f32>,
    /// Render the reference to measure against: a step 1/16 of the default, point samples,
    /// no jitter (compare with `cao-xr compare`).
    #[arg(long)]
    reference: bool,
    /// A clipping tool, SHAPE[:SIZE_MM[:X,Y,Z]] (sphere, box, cylinder, torus; prefix probe-
    /// to keep only its inside; offset in mm from the volume centre, x right, y up, z towards
    /// the viewer). Repeatable. The AO around the cut is CAO.
    #[arg(long)]
    tool: Vec<String>,
    /// The background: R,G,B (0..1), or `transparent` for RGBA PNGs (straight alpha) of what
    /// an ALPHA_BLEND (passthrough) runtime composites over the world.
    #[arg(long, value_parser = parse_background)]
    background: Option<Background>,
}

#[derive(Args)]
struct AoArgs {
    #[command(flatten)]
    vol: VolumeArgs,
    #[command(flatten)]
    lao: LaoArgs,
    /// Output AO volume (.nrrd); the sidecar goes next to it as .json.
    #[arg(long)]
    out: PathBuf,
    /// Also write the opacity volume O that the AO was computed from (the filters' density d,
    /// the local histograms' q).
    #[arg(long)]
    opacity_out: Option<PathBuf>,
    /// With --ao histogram: also write the bleeding colour E (RGB NRRD).
    #[arg(long)]
    bleeding_out: Option<PathBuf>,
    /// Use the CPU reference implementation instead of the GPU.
    #[arg(long)]
    cpu: bool,
}

#[derive(Args)]
struct BenchCmdArgs {
    #[command(subcommand)]
    what: BenchCmd,
}

#[derive(Args)]
struct CompareArgs {
    a: PathBuf,
    b: PathBuf,
    /// Write |A - B| (luma, times 8) as a PNG here.
    #[arg(long)]
    diff: Option<PathBuf>,
}

#[derive(Args)]
struct FetchCtArgs {
    /// Fetch again even if the cache already holds it.
    #[arg(long)]
    force: bool,
}

#[derive(Args)]
struct PhantomArgs {
    /// Voxels per axis.
    #[arg(long, default_value_t = 128)]
    size: usize,
    #[arg(long)]
    out: PathBuf,
}

#[derive(Args)]
struct ReplayArgs {
    /// The pose stream (.jsonl), e.g. controllers/scripts/sphere-sweep.jsonl.
    script: PathBuf,
    #[command(flatten)]
    vol: VolumeArgs,
    #[command(flatten)]
    lao: LaoArgs,
    #[command(flatten)]
    light: LightArgs,
    #[arg(long, default_value = "out/replay")]
    out: PathBuf,
    /// Keep one frame in N as PNG.
    #[arg(long, default_value_t = 1)]
    every: usize,
    /// Write an animated PNG (APNG) of the kept frames.
    #[arg(long)]
    preview: Option<PathBuf>,
    /// Pixels per eye, WIDTHxHEIGHT.
    #[arg(long, default_value = "320x320", value_parser = parse_size)]
    size: (u32, u32),
    /// Recompute LAO for every voxel every frame (the baseline) instead of CAO.
    #[arg(long)]
    naive: bool,
    /// Play at the recorded timing instead of as fast as possible.
    #[arg(long)]
    realtime: bool,
    /// The right hand's tool: sphere, box, cylinder, torus (default: from the stream).
    #[arg(long)]
    shape: Option<String>,
    /// Frames the GPU may hold at once: 2 records the next frame (and writes the last one's
    /// PNG) while the GPU renders; 1 waits for every frame. The images are the same.
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=2))]
    frames_in_flight: Option<u32>,
    /// Place the volume's centre at X,Y,Z metres in the stage (default: where the recorded
    /// session put it, else 0,1.4,-0.6).
    #[arg(long, value_parser = cao_xr::xr::parse_point, allow_hyphen_values = true)]
    volume_at: Option<glam::Vec3>,
    /// Every N frames print a line on stdout: host RSS, GPU memory in use (the allocator's
    /// report), CPU and wall time, validation messages so far.
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u64).range(1..))]
    stats_every: Option<u64>,
}

#[derive(Args)]
struct ViewArgs {
    #[command(flatten)]
    vol: VolumeArgs,
    #[command(flatten)]
    lao: LaoArgs,
    #[command(flatten)]
    light: LightArgs,
    /// Pixels per eye, WIDTHxHEIGHT (the window shows both eyes side by side).
    #[arg(long, default_value = "480x480", value_parser = parse_size)]
    size: (u32, u32),
    /// Close after this many frames.
    #[arg(long)]
    frames: Option<usize>,
    /// Record the session as a pose stream (JSON Lines) that `cao-xr replay` plays back.
    #[arg(long)]
    record: Option<PathBuf>,
    /// Move head and tool automatically (an orbit and a carving sweep).
    #[arg(long)]
    demo: bool,
    /// Save the last frame the window showed as PNG.
    #[arg(long)]
    screenshot: Option<PathBuf>,
    /// Write every frame shown (both eyes side by side) as DIR/frame-00000.png, ...
    #[arg(long)]
    dump: Option<PathBuf>,
    /// Frames the GPU may hold at once: 2 lets the next frame's input and interaction (and the
    /// host's work on the last one) run while the GPU renders; 1 waits for every frame.
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=2))]
    frames_in_flight: Option<u32>,
    /// Hold this frame time (ms) by lengthening the ray step (up to 3x), then foveating, then
    /// lowering the render scale (down to 0.5); the AO is untouched. Off by default in the
    /// window.
    #[arg(long, value_parser = parse_budget)]
    frame_budget_ms: Option<f64>,
}

#[derive(Args)]
struct XrArgs {
    #[command(flatten)]
    vol: VolumeArgs,
    #[command(flatten)]
    lao: LaoArgs,
    #[command(flatten)]
    light: LightArgs,
    /// Submit this many frames, then end the session cleanly.
    #[arg(long)]
    frames: Option<usize>,
    /// Record the session as a pose stream (JSON Lines) that `cao-xr replay` plays back.
    #[arg(long)]
    record: Option<PathBuf>,
    /// Pixels per eye, WIDTHxHEIGHT (default: the runtime's recommended size).
    #[arg(long, value_parser = parse_size)]
    size: Option<(u32, u32)>,
    /// Directory of controller binding files (default: controllers/bindings, else built in).
    #[arg(long)]
    bindings: Option<PathBuf>,
    /// Hold the right trigger from the first frame (carving on without a button press).
    #[arg(long)]
    carve: bool,
    /// Place the volume's centre at X,Y,Z metres in the stage (default 0,1.4,-0.6).
    #[arg(long, value_parser = cao_xr::xr::parse_point, allow_hyphen_values = true)]
    volume_at: Option<glam::Vec3>,
    /// Also show the left eye in a desktop window (X11) while the session runs.
    #[arg(long)]
    mirror: bool,
    /// The environment blend mode: auto (the runtime's preferred one, or with --passthrough
    /// the first of alpha-blend and additive it offers), opaque, additive or alpha-blend. A
    /// mode the runtime does not offer is refused, with the list it does offer.
    #[arg(long, default_value = "auto")]
    blend: cao_xr::xr::blend::BlendRequest,
    /// Mixed reality: the world shows through where the volume is not.
    #[arg(long)]
    passthrough: bool,
    /// Frames the GPU may hold at once: 2 lets the next frame's input and interaction (and the
    /// host's work on the last one) run while the GPU renders; 1 waits for every frame.
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=2))]
    frames_in_flight: Option<u32>,
    /// Hold this frame time (ms) by lengthening the ray step (up to 3x), then foveating, then
    /// lowering the render scale (down to 0.5); the AO is untouched. 0 turns it off. Default:
    /// 90 Hz.
    #[arg(long, value_parser = parse_budget, default_value_t = app::budget::HEADSET_FRAME_MS)]
    frame_budget_ms: f64,
    /// Cast every pixel of both eyes: in the headset the right eye is reprojected from the
    /// left where that is valid (--reproject) unless this is given.
    #[arg(long)]
    cast_both_eyes: bool,
}

#[derive(Args)]
struct ScriptArgs {
    /// sphere-sweep, box-push-pull, torus-pass, two-tools, grab-scale, tremor, tf-switch,
    /// hand-pinch or carve-loop (a tool carving without a pause, for soak runs).
    kind: String,
    #[arg(long)]
    out: PathBuf,
    #[arg(long, default_value_t = ScriptParams::default().frames)]
    frames: usize,
    #[arg(long, default_value_t = ScriptParams::default().fps)]
    fps: f64,
    /// How far the motion reaches from the volume centre, in metres.
    #[arg(long, default_value_t = ScriptParams::default().radius_m)]
    radius: f32,
    /// Seed of the tremor.
    #[arg(long, default_value_t = ScriptParams::default().seed)]
    seed: u64,
}

#[derive(Args)]
struct InfoArgs {
    #[command(flatten)]
    vol: VolumeArgs,
}

#[derive(Subcommand)]
enum BenchCmd {
    /// Every AO method side by side: full compute, per-frame clip update, TF change, memory,
    /// the filters' error and each picture against LAO at K = 54: phantom 64^3 and 128^3 and the
    /// CT head (or VOLUME).
    Ao(BenchAoArgs),
    /// CAO vs the naive full LAO recompute per frame, a 25 mm sphere sweeping through the
    /// phantom at 64^3 and 128^3 and the CT head (or VOLUME).
    Cao(BenchCaoArgs),
    /// SH visibility precompute time with the hierarchy on and off and its error: phantom 64^3
    /// and 128^3 and the CT head (or VOLUME).
    Sh(BenchShArgs),
    /// The ray caster's pictures against the reference render (PSNR, SSIM) and their GPU time,
    /// for step multiples 1, 2, 4 with and without pre-integration, two views each: phantom
    /// 64^3 and 128^3 and the CT head (or VOLUME).
    Quality(BenchQualityArgs),
    /// GPU ms of every pass of a frame (a sphere carving), two eyes against one, the CAO update
    /// against the tool's radius and against the volume padded to 2x per axis, and fps with
    /// one and two frames in flight: the phantom at 64^3 (or VOLUME).
    Frame(BenchFrameArgs),
    /// How cao-xr scales with the volume: synthetic chest CTs of clinical sizes, written as
    /// NIfTI and read back; per size the load time and the time to a first picture, per size
    /// and method the precompute, GPU bytes per voxel, peak host memory, the CAO update of a
    /// fixed tool and the ray cast per eye.
    Scale(BenchScaleArgs),
    /// LAO precompute time and throughput: phantom 64^3 and 128^3 and the CT head (or VOLUME).
    Lao(BenchLaoArgs),
}

#[derive(Args)]
struct BenchAoArgs {
    #[command(flatten)]
    common: BenchArgs,
    /// LAO's ray count K.
    #[arg(long, default_value_t = LaoParams::default().rays)]
    rays: u32,
    /// Filter radii R in mm.
    #[arg(long, value_delimiter = ',', default_value = "6,10")]
    radii: Vec<f64>,
    /// Frames of the sweep.
    #[arg(long, default_value_t = 8)]
    frames: usize,
    /// The transfer function the TF change switches to.
    #[arg(long, default_value = "ct-skin")]
    tf_after: String,
    /// Cluster counts N of the local-histogram table (0: the direct sums; none: skip it).
    #[arg(long, value_delimiter = ',', default_value = "256,512,1024,2048")]
    hist_clusters: Vec<usize>,
    /// The local histograms' radius r in mm.
    #[arg(long, default_value_t = HistParams::default().radius_mm)]
    hist_radius_mm: f64,
    /// The local histograms' bins B.
    #[arg(long, default_value_t = HistParams::default().bins)]
    hist_bins: usize,
    /// Only the local-histogram table (its clusterings take minutes on a large volume).
    #[arg(long)]
    histogram_only: bool,
    /// The local-histogram table also with two hemispheres per voxel, each N beside one sphere.
    #[arg(long)]
    hist_hemispheres: bool,
}

#[derive(Args)]
struct BenchCaoArgs {
    #[command(flatten)]
    common: BenchArgs,
    #[arg(long, value_delimiter = ',', default_value = "6,14,26,54")]
    rays: Vec<u32>,
    /// Frames of the sweep.
    #[arg(long, default_value_t = 8)]
    frames: usize,
    /// Compare every naive frame with CAO bit for bit; exit non-zero on a difference.
    #[arg(long)]
    verify: bool,
    /// Radii in mm of the probe sweeps after the carving table.
    #[arg(long, value_delimiter = ',', default_value = "20,40,60")]
    probe_radii: Vec<f32>,
    /// No probe table.
    #[arg(long)]
    no_probes: bool,
}

#[derive(Args)]
struct BenchShArgs {
    #[command(flatten)]
    common: BenchArgs,
    /// SH volume rates 1:N (volume voxels per SH voxel and axis).
    #[arg(long, value_delimiter = ',', default_value = "1,2,4,8")]
    sh_downsample: Vec<u32>,
    /// Coefficient counts (4 = bands 0-1, 16 = bands 0-3).
    #[arg(long, value_delimiter = ',', default_value = "4,16")]
    coeffs: Vec<u32>,
    /// Directions per voxel.
    #[arg(long, value_delimiter = ',', default_value = "100,400")]
    directions: Vec<u32>,
    /// Visibility ray length in mm.
    #[arg(long, default_value_t = ShParams::default().length_mm)]
    sh_length: f32,
}

#[derive(Args)]
struct BenchQualityArgs {
    #[command(flatten)]
    common: BenchArgs,
    /// Pixels per side of each eye.
    #[arg(long, default_value_t = 256)]
    size: u32,
}

#[derive(Args)]
struct BenchFrameArgs {
    #[command(flatten)]
    common: BenchArgs,
    /// LAO's ray count K.
    #[arg(long, default_value_t = 14)]
    rays: u32,
    /// Pixels per eye, WIDTHxHEIGHT.
    #[arg(long, default_value = "320x320", value_parser = parse_size)]
    size: (u32, u32),
    /// Frames of the sweep.
    #[arg(long, default_value_t = 16)]
    frames: usize,
}

#[derive(Args)]
struct BenchScaleArgs {
    /// Grids, WxHxD, comma-separated.
    #[arg(long, value_delimiter = ',', default_value = "512x512x133,512x512x600", value_parser = parse_dims)]
    sizes: Vec<[usize; 3]>,
    /// Voxel spacing in mm, X,Y,Z (a routine chest CT's by default).
    #[arg(long, default_value = "0.7,0.7,2.5", value_parser = parse_spacing)]
    spacing: [f64; 3],
    /// AO methods to measure at each size.
    #[arg(long, value_delimiter = ',', default_value = "filter-gauss,lao")]
    methods: Vec<String>,
    #[command(flatten)]
    lao: LaoArgs,
    /// Transfer function.
    #[arg(long, default_value = "ct-bone")]
    tf: String,
    /// Pixels per eye, WIDTHxHEIGHT.
    #[arg(long, default_value = "320x320", value_parser = parse_size)]
    size: (u32, u32),
    /// Frames with the fixed tool.
    #[arg(long, default_value_t = 5)]
    frames: usize,
    /// The fixed tool, SHAPE[:SIZE_MM[:X,Y,Z]] as for render --tool.
    #[arg(long, default_value = "sphere:40:0,0,60")]
    tool: String,
    /// Where the NIfTI files are written (and removed after reading).
    #[arg(long, default_value = "out/bench-scale")]
    dir: PathBuf,
}

#[derive(Args)]
struct BenchLaoArgs {
    #[command(flatten)]
    common: BenchArgs,
    /// Ray counts to measure.
    #[arg(long, value_delimiter = ',', default_value = "6,14,26")]
    rays: Vec<u32>,
    /// The kernel: new, old (the one before issue 18) or both, interleaved run by run, with
    /// their ratio.
    #[arg(long, default_value = "both", value_parser = ["new", "old", "both"])]
    kernel: String,
}

#[derive(Args)]
struct BenchArgs {
    /// Volume to measure instead of the default set.
    volume: Option<String>,
    /// Runs per row (the median is printed).
    #[arg(long, default_value_t = 3)]
    runs: usize,
    #[arg(long, default_value_t = LaoParams::default().steps)]
    steps: u32,
    #[arg(long, default_value_t = LaoParams::default().step_mm)]
    step_mm: f32,
    /// Transfer function for every volume (fixed, so that tables compare).
    #[arg(long, default_value = "ct-bone")]
    tf: String,
    /// Average N x N x N voxel blocks of VOLUME first (N = 2, 3, ...).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=64))]
    downsample: u32,
}

/// What both benchmarks start from: the transfer function, the volumes, the GPU, base LAO
/// parameters (K is set per row).
struct BenchSetup {
    tf: TransferFunction,
    volumes: Vec<cao_xr::volume::Volume>,
    gpu: Gpu,
    base: LaoParams,
    runs: usize,
}

impl BenchSetup {
    /// What the tables measure on.
    fn on(&self) -> app::bench::BenchOn<'_> {
        app::bench::BenchOn {
            gpu: &self.gpu,
            volumes: &self.volumes,
            tf: &self.tf,
        }
    }
}

impl BenchArgs {
    fn setup(self, validation: bool) -> Result<BenchSetup> {
        Ok(BenchSetup {
            tf: TransferFunction::resolve(&self.tf)?,
            volumes: bench_volumes(self.volume, self.downsample as usize)?,
            gpu: gpu(validation)?,
            base: LaoParams {
                rays: 6,
                steps: self.steps,
                step_mm: self.step_mm,
            },
            runs: self.runs,
        })
    }
}

#[derive(Args)]
struct VolumeArgs {
    /// A .nrrd/.nhdr/.nii/.mha file (FILE#T: volume T of a 4-D NIfTI or NRRD), a DICOM series
    /// directory (DIR, or DIR#N / DIR#UID to pick one of several series), a raw file (with
    /// --raw-dims), `phantom[:N]` or `ct-head`.
    /// Default: the CT head if fetched (cao-xr fetch-ct), else the phantom.
    volume: Option<String>,
    /// Transfer function: a preset (CT: ct-bone, ct-soft-tissue, ct-muscle-bone, ct-lung,
    /// ct-angio, ct-skin; MR: mr-default, mr-angio) or a JSON file. Default: ct-bone for CT
    /// (Hounsfield) data, mr-default otherwise.
    #[arg(long)]
    tf: Option<String>,
    /// Average N x N x N voxel blocks first (N = 2, 3, ...), for volumes too large for the GPU.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=64))]
    downsample: u32,
    /// Raw volume dimensions X,Y,Z (x fastest).
    #[arg(long, value_parser = cao_xr::space::parse_triple::<usize>)]
    raw_dims: Option<[usize; 3]>,
    /// Raw voxel type: u8, u16, i16.
    #[arg(long, default_value = "i16")]
    raw_type: String,
    /// Raw voxel spacing X,Y,Z in mm.
    #[arg(long, value_parser = cao_xr::space::parse_triple::<f64>, default_value = "1,1,1")]
    raw_spacing: [f64; 3],
    /// Raw data is big-endian.
    #[arg(long)]
    raw_big_endian: bool,
    /// Bytes to skip at the start of a raw file.
    #[arg(long, default_value_t = 0)]
    raw_header: u64,
    /// A segmentation shown over the volume: a multi-label NIfTI (TotalSegmentator --ml), a
    /// folder of binary NIfTI masks (one per structure, named by the file), a 3D Slicer
    /// .seg.nrrd, or a DICOM SEG (the file, or a folder holding one, such as the series' own).
    /// Resampled into the volume's grid by physical position.
    #[arg(long)]
    labels: Option<PathBuf>,
    /// Names and colours of the label values: an ITK-SNAP label description file or a 3D Slicer
    /// colour table.
    #[arg(long, requires = "labels")]
    label_names: Option<PathBuf>,
    /// Show only these structures (names or label values, comma-separated).
    #[arg(long, value_delimiter = ',', requires = "labels")]
    show: Vec<String>,
    /// Hide these structures.
    #[arg(long, value_delimiter = ',', requires = "labels")]
    hide: Vec<String>,
    /// A structure's opacity, NAME=A (A in 0..1; repeatable or comma-separated).
    #[arg(long, value_delimiter = ',', requires = "labels")]
    opacity: Vec<String>,
    /// Structures the tools leave standing inside a cut (comma-separated).
    #[arg(long, value_delimiter = ',', requires = "labels")]
    protect: Vec<String>,
    /// Points and rulers to show over the volume: a 3D Slicer markups file (.mrk.json; points
    /// and lines, LPS or RAS); the rulers' lengths are printed.
    #[arg(long)]
    markups: Option<PathBuf>,
    /// Where the window, the headset and replay write the session's markups (those loaded and
    /// those placed with a measuring tool) when it ends. Without it a session that placed any
    /// writes them to cao-xr-markups-<time>.mrk.json in the current folder (replay: into --out).
    #[arg(long)]
    save_markups: Option<PathBuf>,
    /// A structure's safety margin, NAME=MM (repeatable or comma-separated): a tool within MM
    /// of it is warned (a haptic pulse, the tool drawn in the warning colour, a stats line).
    #[arg(long, value_delimiter = ',', requires = "labels")]
    margin: Vec<String>,
}

#[derive(Args)]
struct LightArgs {
    /// ao: ambient occlusion and a headlight; sh: an environment light through the SH
    /// visibility volume (E = albedo * (L . V)); ao+sh: both, the environment times the AO.
    #[arg(long, default_value = "ao")]
    lighting: LightingMode,
    /// The environment for sh lighting: studio, sky, white, constant:R,G,B (linear), or an
    /// equirectangular .png or .hdr image (top row up).
    #[arg(long, default_value = "studio")]
    light: String,
    /// Turn of the environment about the up axis in degrees (the desktop's [ and ] keys turn it
    /// at run time, with no recompute).
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    light_yaw: f32,
    /// SH visibility volume rate 1:N (1, 2, 4 or 8 volume voxels per SH voxel and axis).
    #[arg(long, default_value_t = ShParams::default().downsample)]
    sh_downsample: u32,
    /// SH coefficients: 4 (bands 0-1) or 16 (bands 0-3).
    #[arg(long, default_value_t = ShParams::default().coeffs)]
    sh_coeffs: u32,
    /// Monte Carlo directions per SH voxel.
    #[arg(long, default_value_t = ShParams::default().directions)]
    sh_directions: u32,
    /// Visibility ray length in mm.
    #[arg(long, default_value_t = ShParams::default().length_mm)]
    sh_length: f32,
    /// March the full-resolution opacity instead of the expected-opacity pyramid.
    #[arg(long)]
    sh_no_hierarchy: bool,
    /// ao: AO alone (C = AO * C_tf); phong: Blinn-Phong with a headlight; phong+ao: Phong whose
    /// ambient and part of whose diffuse term the AO multiplies.
    #[arg(long, default_value = "phong+ao")]
    shading: Shading,
    /// Light cut faces by the data's gradient instead of the tool's surface normal.
    #[arg(long)]
    no_cut_lighting: bool,
    /// Tint the faces a tool cut (R,G,B in 0..1; without a value a warm yellow), to show where
    /// tissue was removed.
    #[arg(long, value_parser = parse_rgb, num_args = 0..=1, default_missing_value = "1,0.8,0.3")]
    cut_tint: Option<[f32; 3]>,
    /// Classify point samples instead of pre-integrating the transfer function over each step.
    #[arg(long)]
    no_preintegration: bool,
    /// Start every ray at the same offset instead of a blue-noise jitter.
    #[arg(long)]
    no_jitter: bool,
    /// Reconstruct the scalars with a cubic B-spline (smoother close-ups, 8x the fetches).
    #[arg(long)]
    tricubic: bool,
    /// Visit every sample instead of jumping over bricks where nothing can be seen (the same
    /// image, slower; for measuring).
    #[arg(long)]
    no_empty_skip: bool,
    /// Ray-casting step in mm (default: half the smallest voxel spacing).
    #[arg(long, default_value_t = 0.0)]
    ray_step_mm: f32,
    /// Show the first-hit isosurface of this data value (HU for CT) instead of the volume: opaque,
    /// in the TF's colour there, lit by the AO of the surface's solid (what lies above the
    /// value); the left thumbstick moves it in the headset.
    #[arg(long, value_parser = parse_finite, allow_hyphen_values = true)]
    iso: Option<f32>,
    /// Foveated ray casting, RADIUS[,FACTOR]: every pixel within RADIUS (a fraction of the
    /// image's half-diagonal) of each eye's centre casts its ray, beyond it one ray per FACTOR x
    /// FACTOR block, interpolated. Without a value 0.25,3.
    #[arg(long, num_args = 0..=1, default_missing_value = "0.25,3")]
    foveate: Option<cao_xr::render::Foveation>,
    /// The second eye reuses the first eye's pixels where both see the same opaque surface
    /// (found along the second eye's ray in the first's depths), casting its own rays where
    /// not: two eyes for less than twice one. Not with --foveate.
    #[arg(long)]
    reproject: bool,
    /// Scattering weight of --ao histogram: the neighbourhood's colour E scattered towards the
    /// eye by the Henyey-Greenstein phase function between the light and the view direction,
    /// so homogeneous tissue glows with the colour of what surrounds it (0: off).
    #[arg(long, default_value_t = 0.0, value_parser = parse_unit)]
    hist_scattering: f32,
    /// The scattering's anisotropy g in (-1, 1): > 0 forwards (tissue glows lit from behind),
    /// 0 evenly, < 0 backwards.
    #[arg(long, default_value_t = cao_xr::render::DEFAULT_ANISOTROPY, allow_hyphen_values = true, value_parser = parse_anisotropy)]
    hist_anisotropy: f32,
    /// A light fixed in the world, X,Y,Z towards it (head-tracking space: +Y up, -Z ahead of
    /// where the session started), instead of a headlight at the head.
    #[arg(long, value_parser = parse_direction, allow_hyphen_values = true)]
    light_from: Option<[f32; 3]>,
}

impl LightArgs {
    fn options(&self) -> LightingOptions {
        LightingOptions {
            mode: self.lighting,
            environment: self.light.clone(),
            sh: ShParams {
                downsample: self.sh_downsample,
                coeffs: self.sh_coeffs,
                directions: self.sh_directions,
                length_mm: self.sh_length,
                hierarchy: !self.sh_no_hierarchy,
                ..Default::default()
            },
            yaw_deg: self.light_yaw,
            shading: ShadingOptions {
                shading: self.shading,
                cut_lighting: !self.no_cut_lighting,
                cut_tint: self.cut_tint,
                preintegrated: !self.no_preintegration,
                jitter: !self.no_jitter,
                tricubic: self.tricubic,
                skip_empty: !self.no_empty_skip,
                step_mm: self.ray_step_mm,
                iso: self.iso,
                foveation: self.foveate,
                reproject: self.reproject,
                scattering: self.hist_scattering,
                anisotropy: self.hist_anisotropy,
                light_from: self.light_from,
                ..Default::default()
            },
        }
    }
}

#[derive(Args)]
struct LaoArgs {
    /// Rays per voxel K (6, 14, 26 use the neighbour directions; others a Fibonacci sphere).
    #[arg(long, default_value_t = LaoParams::default().rays)]
    rays: u32,
    /// Steps per ray M.
    #[arg(long, default_value_t = LaoParams::default().steps)]
    steps: u32,
    /// Step length D in mm.
    #[arg(long, default_value_t = LaoParams::default().step_mm)]
    step_mm: f32,
    /// The AO method: lao, volumetric AO by separable filtering (Ruiz et al.) with the
    /// filter-cdf (t^beta), filter-gauss, filter-penner or filter-exact (brute force) estimator,
    /// or histogram (local histograms with colour bleeding, Ropinski et al.).
    #[arg(long, default_value = "lao")]
    ao: String,
    /// The local histograms' radius r in mm.
    #[arg(long, default_value_t = HistParams::default().radius_mm)]
    hist_radius_mm: f64,
    /// The local histograms' bins B over the data's value range.
    #[arg(long, default_value_t = HistParams::default().bins)]
    hist_bins: usize,
    /// Clusters N of the local histograms (0: the direct, unclustered sums).
    #[arg(long, default_value_t = HistParams::default().clusters)]
    clusters: usize,
    /// Two hemispheres per voxel split by the scalar's gradient: the local histograms' AO and
    /// colour from the one facing down the gradient, away from the higher values. On by
    /// default; `--hist-hemispheres=false` takes one sphere per voxel.
    #[arg(long, default_value_t = HistParams::default().hemispheres, num_args = 0..=1,
          default_missing_value = "true", require_equals = true, value_name = "BOOL")]
    hist_hemispheres: bool,
    /// Colour bleeding weight W of --ao histogram: the TF colour moves towards the
    /// neighbourhood's colour by W times its occlusion (0: off).
    #[arg(long, default_value_t = cao_xr::ao::DEFAULT_BLEEDING)]
    bleeding: f32,
    /// The filters' radius R in mm (the tangent box's half-size).
    #[arg(long, default_value_t = FilterParams::default().radius_mm)]
    filter_radius_mm: f64,
    /// What the filters filter: opacity (the TF's, clipped) or scalar (the normalised value).
    #[arg(long, default_value = "opacity", value_parser = ["opacity", "scalar"])]
    filter_input: String,
    /// Variance opacity modulation (with any AO method): each sample's opacity times
    /// min(var/V, 1), var the data's variance over the centred box of --filter-radius-mm, V in
    /// the data's units squared (HU^2 for CT); homogeneous tissue fades. Off by default.
    #[arg(long, value_name = "V")]
    variance_max: Option<f64>,
}

impl LaoArgs {
    fn params(&self) -> LaoParams {
        LaoParams {
            rays: self.rays,
            steps: self.steps,
            step_mm: self.step_mm,
        }
    }

    fn variance(&self) -> Result<Option<VarianceModulation>> {
        match self.variance_max {
            Some(v) if !(v.is_finite() && v > 0.0) => {
                bail!("--variance-max must be a positive number (data units squared), got {v}")
            }
            Some(max) => Ok(Some(VarianceModulation {
                radius_mm: self.filter_radius_mm,
                max,
            })),
            None => Ok(None),
        }
    }

    fn hist(&self) -> HistParams {
        HistParams {
            radius_mm: self.hist_radius_mm,
            bins: self.hist_bins,
            clusters: self.clusters,
            hemispheres: self.hist_hemispheres,
        }
    }

    fn config(&self) -> Result<AoConfig> {
        let filter = FilterParams {
            radius_mm: self.filter_radius_mm,
            input: match self.filter_input.as_str() {
                "scalar" => FilterInput::Scalar,
                _ => FilterInput::Opacity,
            },
            ..Default::default()
        };
        // The stick click cycles through the filters whatever --ao says: check them up front.
        filter.validate().map_err(anyhow::Error::msg)?;
        let hist = self.hist();
        if !(self.bleeding.is_finite() && (0.0..=1.0).contains(&self.bleeding)) {
            bail!("--bleeding must be in [0, 1], got {}", self.bleeding);
        }
        Ok(AoConfig {
            method: AoMethod::parse(&self.ao, filter, hist).map_err(anyhow::Error::msg)?,
            lao: self.params(),
            filter,
            bleeding: self.bleeding,
        })
    }
}

impl VolumeArgs {
    fn load(&self) -> Result<(cao_xr::volume::Volume, TransferFunction)> {
        let raw = match &self.raw_dims {
            None => None,
            Some(dims) => Some(RawSpec {
                dims: *dims,
                ty: self
                    .raw_type
                    .parse::<RawType>()
                    .map_err(anyhow::Error::msg)?,
                spacing: self.raw_spacing,
                big_endian: self.raw_big_endian,
                header_bytes: self.raw_header,
            }),
        };
        let mut vol = app::load_volume(self.volume.as_deref(), raw.as_ref())?;
        if let Some(path) = &self.labels {
            let mut map = cao_xr::volume::labels::load(path, self.label_names.as_deref(), &vol)?;
            map.apply(&cao_xr::volume::labels::LabelDisplay {
                show: self.show.clone(),
                hide: self.hide.clone(),
                opacity: self.opacity.clone(),
                protect: self.protect.clone(),
                margin: self.margin.clone(),
            })
            .map_err(anyhow::Error::msg)?;
            vol.labels = Some(std::sync::Arc::new(map));
        }
        // The labels are read into the full-resolution grid and downsampled with it (each
        // block's majority), as a volume too large for the GPU is.
        if self.downsample > 1 {
            vol = vol.downsample(self.downsample as usize);
            eprintln!(
                "downsampled {0}x{0}x{0}: {1} x {2} x {3} voxels",
                self.downsample, vol.dims[0], vol.dims[1], vol.dims[2]
            );
        }
        let tf = match &self.tf {
            Some(t) => TransferFunction::resolve(t)?,
            None => TransferFunction::default_for(&vol),
        };
        Ok((vol, tf))
    }
}

/// A frame time in ms: 0 (off) to 10 s.
fn parse_budget(s: &str) -> Result<f64, String> {
    s.parse::<f64>()
        .ok()
        .filter(|v| (0.0..=10_000.0).contains(v))
        .ok_or_else(|| format!("'{s}': a frame time in ms, 0..10000 (e.g. 11.1 for 90 Hz)"))
}

/// WxHxD voxels, each 1..=65536.
fn parse_dims(s: &str) -> Result<[usize; 3], String> {
    let d: Vec<usize> = s
        .split('x')
        .map(|v| v.parse::<usize>().ok().filter(|n| (1..=65536).contains(n)))
        .collect::<Option<_>>()
        .ok_or_else(|| format!("'{s}': expected WxHxD with each 1..=65536, e.g. 512x512x133"))?;
    d.try_into()
        .map_err(|_| format!("'{s}': expected three sizes WxHxD, e.g. 512x512x133"))
}

/// X,Y,Z in mm, each positive and finite.
fn parse_spacing(s: &str) -> Result<[f64; 3], String> {
    let v = cao_xr::space::parse_triple::<f64>(s).map_err(|e| format!("'{s}': {e}"))?;
    if v.iter().all(|x| x.is_finite() && *x > 0.0) {
        Ok(v)
    } else {
        Err(format!(
            "'{s}': each spacing must be a positive number of mm"
        ))
    }
}

fn parse_size(s: &str) -> Result<(u32, u32), String> {
    let (w, h) = s
        .split_once('x')
        .ok_or("expected WIDTHxHEIGHT, e.g. 640x640")?;
    let p = |v: &str| v.parse::<u32>().ok().filter(|v| (16..=8192).contains(v));
    match (p(w), p(h)) {
        (Some(w), Some(h)) => Ok((w, h)),
        _ => Err("width and height must be 16..=8192".into()),
    }
}

/// VOLUME if given, else the phantom at 64^3 and 128^3 and the CT head if fetched.
fn bench_volumes(volume: Option<String>, downsample: usize) -> Result<Vec<cao_xr::volume::Volume>> {
    Ok(match volume {
        Some(v) => vec![app::load_volume(Some(&v), None)?.downsample(downsample)],
        None => {
            let mut v = vec![phantom::head(64), phantom::head(128)];
            match app::load_volume(Some("ct-head"), None) {
                Ok(ct) => v.push(ct),
                Err(e) => eprintln!("skipping the CT head: {e}"),
            }
            v
        }
    })
}

fn gpu(validation: bool) -> Result<Gpu> {
    app::session::start_gpu(validation, false).context("cannot start Vulkan")
}

/// What a session shows, from its volume, AO and lighting arguments.
fn session_spec(vol: &VolumeArgs, lao: &LaoArgs, light: &LightArgs) -> Result<SessionSpec> {
    let (v, tf) = vol.load()?;
    Ok(SessionSpec {
        volume: Arc::new(v),
        tf,
        ao: lao.config()?,
        lighting: light.options(),
        variance: lao.variance()?,
        markups: match &vol.markups {
            Some(p) => cao_xr::volume::markups::Markups::read(p)?,
            None => Default::default(),
        },
        save_markups: vol.save_markups.clone(),
    })
}

/// `render --background`.
#[derive(Clone, Copy, Debug)]
enum Background {
    Transparent,
    Colour([f32; 3]),
}

fn parse_background(s: &str) -> std::result::Result<Background, String> {
    if s == "transparent" {
        return Ok(Background::Transparent);
    }
    parse_rgb(s)
        .map(Background::Colour)
        .map_err(|e| format!("{e} (or transparent)"))
}

/// A finite number (`--iso`).
fn parse_finite(s: &str) -> std::result::Result<f32, String> {
    s.trim()
        .parse::<f32>()
        .ok()
        .filter(|v| v.is_finite())
        .ok_or_else(|| format!("'{s}': expected a finite number"))
}

/// A number in [0, 1].
fn parse_unit(s: &str) -> std::result::Result<f32, String> {
    parse_finite(s)
        .ok()
        .filter(|v| (0.0..=1.0).contains(v))
        .ok_or_else(|| format!("'{s}': expected a number in [0, 1]"))
}

/// The Henyey-Greenstein anisotropy g, in (-1, 1) (at +-1 the phase function has no finite
/// value against the light).
fn parse_anisotropy(s: &str) -> std::result::Result<f32, String> {
    parse_finite(s)
        .ok()
        .filter(|g| g.abs() < 1.0)
        .ok_or_else(|| format!("'{s}': the anisotropy g must lie strictly between -1 and 1"))
}

/// X,Y,Z: a direction (not all zero).
fn parse_direction(s: &str) -> std::result::Result<[f32; 3], String> {
    let d = cao_xr::space::parse_triple::<f32>(s)?;
    if d.iter().all(|v| *v == 0.0) {
        return Err(format!("'{s}': a direction cannot be 0,0,0"));
    }
    Ok(d)
}

/// R,G,B with each in 0..1.
fn parse_rgb(s: &str) -> std::result::Result<[f32; 3], String> {
    let c: Vec<f32> = s
        .split(',')
        .map(|x| {
            x.trim()
                .parse::<f32>()
                .ok()
                .filter(|v| (0.0..=1.0).contains(v))
        })
        .collect::<Option<_>>()
        .ok_or_else(|| format!("'{s}': expected R,G,B with each in 0..1"))?;
    match c[..] {
        [r, g, b] => Ok([r, g, b]),
        _ => Err(format!("'{s}': expected three numbers R,G,B")),
    }
}

/// Says on stderr that a session ended on a signal, before main ends the process by it.
fn interrupted_note() {
    if let Some(sig) = app::interrupt::caught() {
        eprintln!(
            "{}: the session ended cleanly (its recording, if any, is complete)",
            app::interrupt::name(sig)
        );
    }
}

fn main() -> std::process::ExitCode {
    // Output piped into `head` and closed early ends the process quietly, as Unix tools do,
    // instead of panicking in println!.
    // SAFETY: called before any other thread exists; SIG_DFL is a valid disposition.
    #[cfg(unix)]
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
    let code = match run(Cli::parse()) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            // The cause chain on one line, without a backtrace, skipping causes that the message
            // before them already quotes.
            let mut line = e.to_string();
            for cause in e.chain().skip(1) {
                let c = cause.to_string();
                if !line.contains(&c) {
                    line = format!("{line}: {c}");
                }
            }
            eprintln!("error: {line}");
            std::process::ExitCode::FAILURE
        }
    };
    // A session ended by SIGINT or SIGTERM (its recording finished) ends by that signal.
    app::interrupt::reraise();
    code
}

fn run(cli: Cli) -> Result<()> {
    match cli.cmd {
        Cmd::Start(a) => start(a, cli.validation),
        Cmd::Render(a) => render(a, cli.validation),
        Cmd::Ao(a) => ao(a, cli.validation),
        Cmd::Bench(a) => bench(a.what, cli.validation),
        Cmd::Compare(a) => compare(a),
        Cmd::FetchCt(a) => fetch_ct(a),
        Cmd::Phantom(a) => phantom(a),
        Cmd::Replay(a) => replay(a, cli.validation),
        Cmd::View(a) => view(a, cli.validation),
        Cmd::Xr(a) => xr(a, cli.validation),
        Cmd::Script(a) => script(a),
        Cmd::Info(a) => info(a),
    }
}

fn bench(what: BenchCmd, validation: bool) -> Result<()> {
    match what {
        BenchCmd::Ao(a) => bench_ao(a, validation),
        BenchCmd::Cao(a) => bench_cao(a, validation),
        BenchCmd::Sh(a) => bench_sh(a, validation),
        BenchCmd::Quality(a) => bench_quality(a, validation),
        BenchCmd::Frame(a) => bench_frame(a, validation),
        BenchCmd::Scale(a) => bench_scale(a, validation),
        BenchCmd::Lao(a) => bench_lao(a, validation),
    }
}

fn start(a: StartArgs, validation: bool) -> Result<()> {
    let StartArgs { vol, lao, light } = a;
    let spec = session_spec(&vol, &lao, &light)?;
    println!("{}", app::start(&spec, validation)?);
    Ok(())
}

fn render(a: RenderArgs, validation: bool) -> Result<()> {
    let RenderArgs {
        vol,
        lao,
        light,
        out,
        size,
        no_ao,
        diffuse,
        reference,
        tool,
        background,
    } = a;
    let mut spec = session_spec(&vol, &lao, &light)?;
    let shading = &mut spec.lighting.shading;
    shading.no_ao = no_ao;
    shading.diffuse = diffuse;
    if reference {
        *shading = shading.reference(spec.volume.spacing);
    }
    let v = &spec.volume;
    eprintln!(
        "volume {} {:?} spacing {:?} mm, tf {}",
        v.name, v.dims, v.spacing, spec.tf.name
    );
    let gpu = gpu(validation)?;
    let mut settings = RenderSettings::default();
    match background {
        Some(Background::Transparent) => settings.transparent = true,
        Some(Background::Colour(c)) => settings.background = c,
        None => {}
    }
    let placement = cao_xr::space::Placement::default();
    let tools = tool
        .iter()
        .map(|t| app::parse_tool(t, &placement))
        .collect::<Result<Vec<_>, _>>()?;
    let t0 = std::time::Instant::now();
    let m = app::render_to_dir(&gpu, &spec, &tools, size, &settings, &out)?;
    if let Some(m) = m {
        println!(
            "CAO: {} clipped, {} recomputed ({:.2} %), GPU restore {:.1} ms, clip {:.1} ms, update {:.1} ms",
            m.clipped,
            m.recomputed,
            m.percent_recomputed(),
            m.restore_ms,
            m.clip_ms,
            m.update_ms
        );
    }
    let peak = gpu.session_memory_peak();
    println!(
        "GPU memory: peak {} MiB, {:.1} bytes per voxel",
        peak >> 20,
        peak as f64 / spec.volume.voxel_count().max(1) as f64
    );
    println!(
        "wrote {0}/left.png {0}/right.png {0}/stereo.png in {1:.1} s",
        out.display(),
        t0.elapsed().as_secs_f64()
    );
    Ok(())
}

fn ao(a: AoArgs, validation: bool) -> Result<()> {
    let AoArgs {
        vol,
        lao,
        out,
        opacity_out,
        bleeding_out,
        cpu,
    } = a;
    let (v, tf) = vol.load()?;
    let gpu = if cpu { None } else { Some(gpu(validation)?) };
    let t = app::write_ao(
        gpu.as_ref(),
        &v,
        &tf,
        &lao.config()?,
        &out,
        opacity_out.as_deref(),
        bleeding_out.as_deref(),
    )?;
    println!(
        "wrote {} and {} ({:.1} ms{})",
        out.display(),
        out.with_extension("json").display(),
        if cpu { t.wall_ms } else { t.gpu_ms },
        if cpu { " on the CPU" } else { " GPU time" }
    );
    Ok(())
}

fn bench_ao(a: BenchAoArgs, validation: bool) -> Result<()> {
    let BenchAoArgs {
        common,
        rays,
        radii,
        frames,
        tf_after,
        hist_clusters,
        hist_radius_mm,
        hist_bins,
        histogram_only,
        hist_hemispheres,
    } = a;
    let b = common.setup(validation)?;
    let tf_after = TransferFunction::resolve(&tf_after)?;
    let base = LaoParams { rays, ..b.base };
    if !histogram_only {
        app::bench_ao::bench_ao(b.on(), &tf_after, &radii, &base, frames.max(1), b.runs)?;
    }
    if !hist_clusters.is_empty() {
        let p = HistParams {
            radius_mm: hist_radius_mm,
            bins: hist_bins,
            clusters: 0,
            hemispheres: false,
        };
        p.validate().map_err(anyhow::Error::msg)?;
        println!();
        app::bench_ao::bench_histogram(
            b.on(),
            &tf_after,
            p,
            &hist_clusters,
            hist_hemispheres,
            &base,
            frames.max(1),
        )?;
    }
    Ok(())
}

fn bench_cao(a: BenchCaoArgs, validation: bool) -> Result<()> {
    let BenchCaoArgs {
        common,
        rays,
        frames,
        verify,
        probe_radii,
        no_probes,
    } = a;
    let b = common.setup(validation)?;
    let frames = frames.max(1);
    if let Some(r) = probe_radii.iter().find(|r| !(r.is_finite() && **r > 0.0)) {
        bail!("--probe-radii must be positive, got {r}");
    }
    app::bench::bench_cao(
        b.on(),
        &rays,
        &b.base,
        frames,
        b.runs,
        verify,
        if no_probes { &[] } else { &probe_radii },
    )?;
    Ok(())
}

fn bench_sh(a: BenchShArgs, validation: bool) -> Result<()> {
    let BenchShArgs {
        common,
        sh_downsample,
        coeffs,
        directions,
        sh_length,
    } = a;
    let b = common.setup(validation)?;
    let base = ShParams {
        length_mm: sh_length,
        ..ShParams::default()
    };
    for d in &directions {
        ShParams {
            directions: *d,
            ..base
        }
        .validate()
        .map_err(anyhow::Error::msg)?;
    }
    app::bench::bench_sh(b.on(), &sh_downsample, &coeffs, &directions, &base, b.runs)?;
    Ok(())
}

fn bench_quality(a: BenchQualityArgs, validation: bool) -> Result<()> {
    let BenchQualityArgs { common, size } = a;
    let b = common.setup(validation)?;
    let lao = LaoParams {
        rays: LaoParams::default().rays,
        ..b.base
    };
    app::bench_quality::bench_quality(&b.gpu, &b.volumes, &b.tf, lao, size, b.runs)?;
    Ok(())
}

fn bench_frame(a: BenchFrameArgs, validation: bool) -> Result<()> {
    let BenchFrameArgs {
        mut common,
        rays,
        size,
        frames,
    } = a;
    common.volume.get_or_insert_with(|| "phantom:64".into());
    let b = common.setup(validation)?;
    let lao = LaoParams { rays, ..b.base };
    app::bench_frame::bench_frame(&b.gpu, &b.volumes[0], &b.tf, lao, size, frames, b.runs)?;
    Ok(())
}

fn bench_scale(a: BenchScaleArgs, validation: bool) -> Result<()> {
    let BenchScaleArgs {
        sizes,
        spacing,
        methods,
        lao,
        tf,
        size,
        frames,
        tool,
        dir,
    } = a;
    let config = lao.config()?;
    let methods = methods
        .iter()
        .map(|m| AoMethod::parse(m, config.filter, lao.hist()))
        .collect::<std::result::Result<Vec<_>, _>>()
        .map_err(anyhow::Error::msg)?;
    let opts = app::bench_scale::ScaleOptions {
        sizes,
        spacing,
        config,
        methods,
        tf: TransferFunction::resolve(&tf)?,
        eye: size,
        frames,
        tool: app::parse_tool(&tool, &cao_xr::space::Placement::default())?,
    };
    app::bench_scale::bench_scale(&gpu(validation)?, &opts, &dir)?;
    Ok(())
}

fn bench_lao(a: BenchLaoArgs, validation: bool) -> Result<()> {
    let BenchLaoArgs {
        common,
        rays,
        kernel,
    } = a;
    let b = common.setup(validation)?;
    let kernels: &[LaoKernel] = match kernel.as_str() {
        "old" => &[LaoKernel::Old],
        "new" => &[LaoKernel::New],
        _ => &[LaoKernel::Old, LaoKernel::New],
    };
    app::bench::bench_lao(b.on(), &rays, &b.base, b.runs, kernels)?;
    Ok(())
}

fn compare(a: CompareArgs) -> Result<()> {
    let CompareArgs { a, b, diff } = a;
    use cao_xr::render::compare;
    let read = |p: &PathBuf| compare::read_png(p).map_err(anyhow::Error::msg);
    let (pa, pb) = (read(&a)?, read(&b)?);
    let (c, image) = compare::compare(&pa, &pb)
        .map_err(|e| anyhow::anyhow!("{} against {}: {e}", b.display(), a.display()))?;
    if let Some(path) = &diff {
        cao_xr::render::png_out::write_rgb(path, pa.width as u32, pa.height as u32, &image)
            .with_context(|| format!("cannot write {}", path.display()))?;
    }
    println!(
        "PSNR {:.2} dB  SSIM {:.4}  max |d luma| {:.0}  ({}x{})",
        c.psnr, c.ssim, c.max_diff, pa.width, pa.height
    );
    Ok(())
}

fn fetch_ct(a: FetchCtArgs) -> Result<()> {
    let FetchCtArgs { force } = a;
    let cached = ct_head::cached_path();
    if cached.exists() && !force {
        println!(
            "CT head already cached at {} (--force fetches it again)",
            cached.display()
        );
        return Ok(());
    }
    let path = ct_head::fetch(&mut |msg| eprintln!("{msg}"))?;
    println!("CT head cached at {}", path.display());
    Ok(())
}

fn phantom(a: PhantomArgs) -> Result<()> {
    let PhantomArgs { size, out } = a;
    if !(4..=1024).contains(&size) {
        bail!("--size must be 4..=1024");
    }
    let v = phantom::head(size);
    cao_xr::volume::nrrd::write_volume(&out, &v, true)?;
    println!("wrote {}", out.display());
    Ok(())
}

fn replay(a: ReplayArgs, validation: bool) -> Result<()> {
    let ReplayArgs {
        script,
        vol,
        lao,
        light,
        out,
        every,
        preview,
        size,
        naive,
        realtime,
        shape,
        frames_in_flight,
        volume_at,
        stats_every,
    } = a;
    let spec = session_spec(&vol, &lao, &light)?;
    let gpu = gpu(validation)?;
    let shape = match shape.as_deref() {
        None => None,
        Some(s) => Some(app::parse_tool(s, &Default::default())?.shape),
    };
    let opts = app::replay::ReplayOptions {
        every,
        preview,
        size,
        mode: if naive {
            cao_xr::ao::cao::Mode::Naive
        } else {
            Default::default()
        },
        realtime,
        shape,
        frames_in_flight: frames_in_flight.map(|n| n as usize),
        volume_at,
        stats_every: stats_every.map(|n| n as usize),
    };
    let s = app::replay::replay(&gpu, &script, &spec, &out, &opts)?;
    println!(
        "replayed {} frames into {} ({} PNGs, metrics.csv): mean AO update {:.1} ms, {:.2} % recomputed; {} frames recorded while the one before was in flight",
        s.frames,
        out.display(),
        s.pngs,
        s.mean_ao_ms,
        s.mean_percent_recomputed,
        s.overlapped
    );
    Ok(())
}

fn view(a: ViewArgs, validation: bool) -> Result<()> {
    let ViewArgs {
        vol,
        lao,
        light,
        size,
        frames,
        record,
        demo,
        screenshot,
        dump,
        frames_in_flight,
        frame_budget_ms,
    } = a;
    let spec = session_spec(&vol, &lao, &light)?;
    let opts = app::desktop::ViewOptions {
        frame_budget_ms,
        size,
        frames,
        record,
        demo,
        screenshot,
        dump,
        validation,
        frames_in_flight: frames_in_flight.map(|n| n as usize),
    };
    let n = app::desktop::run(&spec, opts)?;
    println!("closed after {n} frames");
    interrupted_note();
    Ok(())
}

fn xr(a: XrArgs, validation: bool) -> Result<()> {
    let XrArgs {
        vol,
        lao,
        mut light,
        frames,
        record,
        size,
        bindings,
        carve,
        volume_at,
        mirror,
        blend,
        passthrough,
        frames_in_flight,
        frame_budget_ms,
        cast_both_eyes,
    } = a;
    // The headset reprojects its second eye by default: two eyes for less than twice one.
    light.reproject |= !cast_both_eyes;
    let spec = session_spec(&vol, &lao, &light)?;
    let opts = cao_xr::xr::XrOptions {
        frames,
        record,
        size,
        bindings,
        carve,
        volume_at,
        mirror,
        validation,
        blend,
        passthrough,
        frames_in_flight: frames_in_flight.map(|n| n as usize),
        frame_budget_ms: (frame_budget_ms > 0.0).then_some(frame_budget_ms),
    };
    let s = app::headset::run(&spec, opts)?;
    interrupted_note();
    println!(
        "xr session ended cleanly: {} frames submitted, {} with tracked hands, states {}, focused {}, haptic pulses {}, space {}, blend {} (offered {})",
        s.frames,
        s.tracked_frames,
        s.states.join(">"),
        s.focused,
        s.pulses,
        s.space,
        s.blend,
        s.blend_offered.join(", ")
    );
    match &s.depth_missing {
        None => println!("depth layer: submitted with {} frames", s.depth_frames),
        Some(why) => println!("depth layer: {why}"),
    }
    println!(
        "hand tracking: {}, joints drove {} frames",
        if s.hand_tracking { "on" } else { "off" },
        s.hand_frames
    );
    println!(
        "eye gaze: {}, tracked in {} frames",
        if s.eye_gaze { "on" } else { "off" },
        s.gaze_frames
    );
    Ok(())
}

fn script(a: ScriptArgs) -> Result<()> {
    let ScriptArgs {
        kind,
        out,
        frames,
        fps,
        radius,
        seed,
    } = a;
    let kind: ScriptKind = kind.parse()?;
    let params = ScriptParams {
        frames,
        fps,
        radius_m: radius,
        seed,
        ..Default::default()
    };
    write_script(kind, &params, &out)?;
    println!("wrote {} ({frames} frames of {kind})", out.display());
    Ok(())
}

fn info(a: InfoArgs) -> Result<()> {
    let InfoArgs { vol } = a;
    if let Some((listing, chosen)) = app::dicom_listing(vol.volume.as_deref())? {
        print!("{listing}");
        if !chosen {
            println!("pick one as DIR#N or DIR#SERIES_UID for its volume info");
            return Ok(());
        }
    }
    let (v, tf) = vol.load()?;
    print!("{}", app::info_report(&v, &tf));
    Ok(())
}
