//! Local-histogram AO on the GPU (shaders histogram_local.comp, histogram_assign.comp,
//! histogram_sums.comp): the clustering's heavy parts (every voxel's local histogram, in
//! batches so memory stays bounded, and its assignment to the nearest centroid), the per-TF
//! expansion of the clusters' table into V_PAO and the bleeding volume, and the direct sums of
//! the clip update over any set of voxel boxes. [`super::histogram`] holds the CPU side and the
//! reference.

use super::cao::Mode;
use super::histogram::{self as hist, Clusters, HistParams, Neighbourhood, Packing, Shades};
use super::method::MethodBuffers;
use super::voxel_box::{dispatch_box, VoxelBox};
use crate::gpu::{Buffer, ComputePipeline, Gpu, Reach, Result};
use crate::shader_constants::SAME_AS_FRONT;
use crate::volume::labels::LabelMap;
use crate::volume::transfer::TransferFunction;
use crate::volume::Volume;
use ash::vk;
use gpu_allocator::MemoryLocation;
use rayon::prelude::*;
use std::path::Path;
use std::sync::Arc;

/// histogram_sums.comp's modes: how a pass treats each voxel of its boxes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Pass {
    /// The direct sums for every voxel, no mask (the unclipped precompute with `--clusters 0`).
    Direct = 0,
    /// CAO's categories: a -> 1, c -> the precomputed values, b -> the direct sums.
    Contextual = 1,
    /// a -> 1, everything else the direct sums (the naive baseline).
    Naive = 2,
    /// The precomputed values (last frame's boxes, before this frame's clip).
    Restore = 3,
    /// Every voxel its cluster's V_PAO (the clustered precompute; its E is the cluster's).
    Clustered = 4,
    /// The precomputed E alone ([`HistogramGpu::precomputed_e`]).
    PrecomputedE = 5,
}

/// Voxels per batch of local histograms: rows x shades floats stay within this many bytes, or
/// a fifth of what the GPU budget leaves (the rows are held twice, GPU and readable).
const BATCH_BYTES: usize = 64 << 20;

/// The training sample's size: 16 samples per cluster, at least this many.
const MIN_TRAINING: usize = 32768;

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct JobPush {
    dims: [i32; 4],
    job: [u32; 4],
}
crate::gpu::glsl_layout!(JobPush, 32, dims: 0, job: 16);

/// Push constants of histogram_sums.comp: a box, and S_r's reach per axis.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct SumsPush {
    dims: [i32; 4],
    box_min: [i32; 4],
    box_max: [i32; 4],
    reach: [i32; 4],
}
crate::gpu::glsl_layout!(SumsPush, 64, dims: 0, box_min: 16, box_max: 32, reach: 48);

/// How long each phase of the clustering took (wall ms) and the host memory it peaked at.
#[derive(Clone, Copy, Debug, Default)]
pub struct ClusterTiming {
    pub histograms_ms: f64,
    pub training_ms: f64,
    pub assignment_ms: f64,
    /// Bytes of the largest host buffers held at once (batch rows, sums, sample).
    pub peak_host_bytes: u64,
    /// Whether the clustering came from the cache.
    pub cached: bool,
}

/// The method's state: pipelines, the volume's bins, S_r, the clusters (when N > 0), the TF's
/// tables, and the precomputed and current bleeding volumes (RGBA8 per voxel).
pub struct HistogramGpu {
    gpu: Gpu,
    sums: ComputePipeline,
    pub params: HistParams,
    pub dims: [usize; 3],
    pub spacing: [f64; 3],
    range: (f32, f32),
    nb: Neighbourhood,
    neighbours: Buffer,
    /// Each voxel's shade, its bin with its structure folded in (host copy for q under a new
    /// TF).
    shades: Shades,
    /// The volume's label map: the shades' colours and opacities follow its structures.
    labels: Option<Arc<LabelMap>>,
    /// Each voxel's shade, as the shaders read it.
    bins: Buffer,
    /// The shade table ([`Shades::table`]): colour and opacity per shade.
    bin_table: Buffer,
    /// Cluster ids and the representatives (host), with N > 0.
    clusters: Option<Clusters>,
    ids: Buffer,
    cluster_table: Buffer,
    /// The shade table of the last TF (host copy).
    last_table: Vec<[f32; 4]>,
    /// The scalar per voxel in f32 (with hemispheres; a stand-in otherwise), whether it holds
    /// integers, and the split's parameters as histogram_sums.comp's `Split` reads them.
    scalars: (Buffer, bool),
    split: Buffer,
    /// The clear bricks of the last TF ([`hist::clear_bricks`]; none before one), mapped.
    clear: Buffer,
    /// The one-word brick table its precompute writes V_PAO whole through.
    whole: Buffer,
    /// E of the unclipped volume without clusters (with them a stand-in: a voxel's is its
    /// cluster's), and this frame's E (RGBA8 per voxel).
    pub pre_e: Buffer,
    pub e: Buffer,
    pub timing: ClusterTiming,
}

/// Most shades whose local histograms histogram_local.comp adds in an array of each voxel's own
/// (two rows of 4 bytes per shade); more are added in the rows in memory.
const PRIVATE_SHADES: usize = 512;

/// histogram_local.comp's specialization constant: the shades, where a voxel's sums fit an
/// array of its own; 0 where they are added in the rows in memory.
fn private_shades(shades: usize) -> u32 {
    if shades <= PRIVATE_SHADES {
        shades as u32
    } else {
        0
    }
}

/// Where the clustering's local histograms are summed: histogram_local.comp adding into device
/// rows, or its twin on the host's cores ([`hist::local_rows_f32`], the same bits) with the
/// hemispheres' split.
enum RowsOn<'a> {
    Gpu {
        local: ComputePipeline,
        rows: Buffer,
    },
    Host(Option<hist::SplitF32<'a>>),
}

/// histogram_assign.comp with its tables (the packing matrix, the centroids, the group
/// centres, firsts and members) and the ids it writes.
struct DeviceAssign {
    pipeline: ComputePipeline,
    groups: u32,
    tables: [Buffer; 5],
    ids: Buffer,
}

impl DeviceAssign {
    /// The cluster of each of the first `rows` rows of `device_rows` (`b` shades each, `k`
    /// clusters).
    fn run(
        &self,
        gpu: &Gpu,
        device_rows: &Buffer,
        rows: usize,
        (b, k): (usize, usize),
    ) -> Result<Vec<u32>> {
        let push = [rows as u32, b as u32, self.groups, k as u32];
        gpu.submit_and_wait(|cmd| {
            let [packing, centroids, gc, gf, gm] = &self.tables;
            self.pipeline.bind(
                cmd,
                &[device_rows, packing, centroids, &self.ids, gc, gf, gm],
                bytemuck::bytes_of(&push),
            );
            self.pipeline
                .dispatch(cmd, [(rows as u32).div_ceil(64), 1, 1]);
        })?;
        Ok(bytemuck::cast_slice(self.ids.mapped()?)[..rows].to_vec())
    }
}

/// Whether the clustering sums its local histograms on the host: by default on a CPU renderer
/// such as lavapipe, which makes each lane's scattered read and add one at a time (the host's
/// own code is several times faster there; docs/benchmarks.md), else on the GPU.
/// `CAO_XR_HISTOGRAM_ROWS=host` or `gpu` chooses.
fn rows_on_host(gpu: &Gpu) -> bool {
    match std::env::var("CAO_XR_HISTOGRAM_ROWS").as_deref() {
        Ok("host") => true,
        Ok("gpu") => false,
        _ => gpu.is_cpu(),
    }
}

/// The volume's scalars in f32, as the hemispheres' split reads them.
fn scalar_values(vol: &Volume) -> Vec<f32> {
    (0..vol.voxel_count())
        .into_par_iter()
        .map(|i| vol.voxels.get(i))
        .collect()
}

/// Rows of `dim` values, each zero-padded to a multiple of 4 (histogram_assign.comp reads vec4s).
fn pad4(rows: &[f32], dim: usize) -> Vec<f32> {
    let padded = dim.div_ceil(4) * 4;
    rows.chunks_exact(dim)
        .flat_map(|r| {
            r.iter()
                .copied()
                .chain(std::iter::repeat_n(0.0, padded - dim))
        })
        .collect()
}

/// Every `step`-th of `ids` (shades below 256 x 256, clusters below [`hist::MAX_CLUSTERS`]) as the
/// 16-bit words the shaders read.
fn words16(ids: &[u32], step: usize) -> Vec<u16> {
    ids.iter().step_by(step).map(|&k| k as u16).collect()
}

fn spv(name: &str) -> &'static [u8] {
    match name {
        "sums" => include_bytes!(concat!(env!("OUT_DIR"), "/histogram_sums.comp.spv")),
        "local" => include_bytes!(concat!(env!("OUT_DIR"), "/histogram_local.comp.spv")),
        _ => include_bytes!(concat!(env!("OUT_DIR"), "/histogram_assign.comp.spv")),
    }
}

impl HistogramGpu {
    /// Sets the method up for `vol`: bins, S_r and, with N > 0, the clustering, read from
    /// `cache_dir` when a valid entry for this volume and these parameters is there, else
    /// computed (`progress(done, total, phase)` is told along the way) and written there.
    pub fn new(
        gpu: &Gpu,
        vol: &Volume,
        params: HistParams,
        cache_dir: Option<&Path>,
        progress: &mut dyn FnMut(u64, u64, &str),
    ) -> Result<HistogramGpu> {
        params.validate().map_err(crate::gpu::GpuError::Other)?;
        let n = vol.voxel_count();
        let labels = vol.labels.clone();
        let shades = Shades::new(hist::bins(vol, params.bins), params.bins, labels.as_deref());
        let nb = Neighbourhood::new(params.radius_mm, vol.spacing);
        let geometry = (vol.dims, vol.spacing, vol.value_range());
        let storage = vk::BufferUsageFlags::STORAGE_BUFFER | vk::BufferUsageFlags::TRANSFER_SRC;
        let values = params.hemispheres.then(|| scalar_values(vol));
        // Integer scalars as 16-bit words above the least value (histogram_split.glsl).
        let integer = !matches!(vol.voxels, crate::volume::Voxels::F32(_));
        let scalars = match &values {
            Some(v) if integer => {
                let lo = geometry.2 .0;
                let words: Vec<u16> = v.par_iter().map(|&x| (x - lo) as u16).collect();
                Buffer::device_local(gpu, &words, storage, "hist-scalars")?
            }
            Some(v) => Buffer::device_local(gpu, v, storage, "hist-scalars")?,
            None => Buffer::new(gpu, 4, storage, MemoryLocation::GpuOnly, "hist-scalars")?,
        };
        let mut h = HistogramGpu::with_state(
            gpu,
            geometry,
            params,
            (shades, labels),
            nb,
            None,
            (scalars, integer),
        )?;
        if params.clusters > 0 {
            let key = hist::cache_key(vol.dims, vol.spacing, &h.shades, &params, values.as_deref());
            // The host's sums split by the scalars (the GPU holds its own copy).
            let on_host = rows_on_host(gpu);
            let values = values.filter(|_| on_host);
            let path = cache_dir.map(|d| hist::cache_path(d, key));
            let count = h.shades.count();
            let rows = n * h.hemispheres();
            let cached = path
                .as_deref()
                .and_then(|p| hist::load_cache(p, key, rows, count, &params));
            let clusters = match cached {
                Some(c) => {
                    h.timing.cached = true;
                    c
                }
                None => {
                    let c = h.cluster(values.as_deref(), on_host, progress)?;
                    if let Some(p) = &path {
                        if let Err(e) = hist::save_cache(p, key, &c) {
                            eprintln!("{}: cannot cache the clustering: {e}", p.display());
                        }
                    }
                    c
                }
            };
            h.set_clusters(clusters)?;
        }
        Ok(h)
    }

    /// The GPU state for the given shades, S_r and clusters (tables empty until
    /// [`HistogramGpu::set_tf`]).
    fn with_state(
        gpu: &Gpu,
        (dims, spacing, range): ([usize; 3], [f64; 3], (f32, f32)),
        params: HistParams,
        (shades, labels): (Shades, Option<Arc<LabelMap>>),
        nb: Neighbourhood,
        clusters: Option<Clusters>,
        scalars: (Buffer, bool),
    ) -> Result<HistogramGpu> {
        let storage = vk::BufferUsageFlags::STORAGE_BUFFER;
        let split = {
            let (half_inv_spacing, flat2) = hist::SplitF32::parameters(spacing, range);
            let mut words = [0u32; 8];
            words[0] = scalars.0.address as u32;
            words[1] = (scalars.0.address >> 32) as u32;
            words[2] = params.hemispheres as u32;
            words[3] = scalars.1 as u32;
            for a in 0..3 {
                words[4 + a] = half_inv_spacing[a].to_bits();
            }
            words[7] = flat2.to_bits();
            Buffer::from_slice(gpu, &words, storage, "hist-split")?
        };
        let n = shades.ids.len();
        let rgba8 = |name, n: usize| {
            Buffer::new(
                gpu,
                (n.max(1) * 4) as u64,
                storage | vk::BufferUsageFlags::TRANSFER_SRC | vk::BufferUsageFlags::TRANSFER_DST,
                MemoryLocation::GpuOnly,
                name,
            )
        };
        let mut h = HistogramGpu {
            gpu: gpu.clone(),
            sums: ComputePipeline::with_addresses(
                gpu,
                spv("sums"),
                &[
                    Reach::Address,
                    Reach::Address,
                    Reach::Descriptor,
                    Reach::Descriptor,
                    Reach::Address,
                    Reach::Address,
                    Reach::Address,
                    Reach::Address,
                    Reach::Address,
                    Reach::Address,
                    Reach::Descriptor,
                    Reach::Descriptor,
                    Reach::Descriptor,
                    Reach::Descriptor,
                ],
                64,
                &[],
            )?,
            params,
            dims,
            spacing,
            range,
            neighbours: Buffer::from_slice(gpu, &nb.gpu_table(), storage, "hist-neighbours")?,
            bins: Buffer::device_local(gpu, &words16(&shades.ids, 1), storage, "hist-bins")?,
            bin_table: Buffer::new(
                gpu,
                (shades.count() * 16) as u64,
                storage,
                MemoryLocation::CpuToGpu,
                "hist-bin-table",
            )?,
            clusters: None,
            // Stand-ins until a clustering exists (the shader only reads them in mode 4).
            ids: Buffer::new(gpu, 4, storage, MemoryLocation::GpuOnly, "hist-ids")?,
            cluster_table: Buffer::new(gpu, 16, storage, MemoryLocation::CpuToGpu, "hist-table")?,
            last_table: Vec::new(),
            pre_e: rgba8("hist-pre-e", if clusters.is_some() { 1 } else { n })?,
            e: rgba8("hist-e", n)?,
            scalars,
            split,
            clear: Buffer::new(
                gpu,
                hist::clear_brick_words(dims) as u64 * 4,
                storage,
                MemoryLocation::CpuToGpu,
                "hist-clear-bricks",
            )?,
            whole: super::pool::whole_table(gpu)?,
            timing: ClusterTiming::default(),
            nb,
            shades,
            labels,
        };
        if let Some(c) = clusters {
            h.set_clusters(c)?;
        }
        h.write_clear(&[])?;
        Ok(h)
    }

    fn set_clusters(&mut self, clusters: Clusters) -> Result<()> {
        let storage = vk::BufferUsageFlags::STORAGE_BUFFER;
        // The front hemisphere's ids alone: V_PAO and E are its cluster's.
        let hemis = if self.params.hemispheres { 2 } else { 1 };
        let front = words16(&clusters.ids, hemis);
        self.ids = Buffer::device_local(&self.gpu, &front, storage, "hist-ids")?;
        self.pre_e = Buffer::new(&self.gpu, 4, storage, MemoryLocation::GpuOnly, "hist-pre-e")?;
        self.cluster_table = Buffer::new(
            &self.gpu,
            (clusters.count() * 16) as u64,
            storage,
            MemoryLocation::CpuToGpu,
            "hist-table",
        )?;
        self.clusters = Some(clusters);
        Ok(())
    }

    /// An independent copy (buffers of its own, the same clustering, tables and V_PAO's
    /// bleeding volume), for a second CAO state.
    pub fn duplicate(&self) -> Result<HistogramGpu> {
        let geometry = (self.dims, self.spacing, self.range);
        let mut h = HistogramGpu::with_state(
            &self.gpu,
            geometry,
            self.params,
            (self.shades.clone(), self.labels.clone()),
            self.nb.clone(),
            self.clusters.clone(),
            (
                self.scalars.0.duplicate(
                    vk::BufferUsageFlags::STORAGE_BUFFER | vk::BufferUsageFlags::TRANSFER_SRC,
                    "hist-scalars",
                )?,
                self.scalars.1,
            ),
        )?;
        h.write_tables(self.last_table.clone())?;
        h.clear.write(0, self.clear.mapped()?)?;
        let usage = vk::BufferUsageFlags::STORAGE_BUFFER | vk::BufferUsageFlags::TRANSFER_SRC;
        h.pre_e = self.pre_e.duplicate(usage, "hist-pre-e")?;
        h.timing = self.timing;
        Ok(h)
    }

    /// The clusters, when N > 0.
    pub fn clusters(&self) -> Option<&Clusters> {
        self.clusters.as_ref()
    }

    /// S_r's farthest member in mm: the method's reach.
    pub fn reach_mm(&self) -> f64 {
        self.nb.reach_mm(self.spacing)
    }

    /// GPU memory the method holds beyond the volumes every method has.
    pub fn resident_bytes(&self) -> u64 {
        [
            &self.neighbours,
            &self.bins,
            &self.bin_table,
            &self.ids,
            &self.cluster_table,
            &self.pre_e,
            &self.e,
            &self.scalars.0,
            &self.split,
        ]
        .iter()
        .map(|b| b.size)
        .sum()
    }

    /// The local histograms of `rows` voxels (from `first`, or from the `first`-th voxel of
    /// `list`, its buffer and host copy; two rows each with the hemispheres) into `readback`,
    /// summed where `on` says.
    fn local_rows(
        &self,
        on: &RowsOn,
        (first, rows): (usize, usize),
        list: Option<(&Buffer, &[u32])>,
        readback: &mut Buffer,
    ) -> Result<()> {
        let (local, out) = match on {
            RowsOn::Host(split) => {
                let mut out = vec![0.0f32; rows * self.hemispheres() * self.shades.count()];
                hist::local_rows_f32(
                    self.dims,
                    (&self.shades.ids, self.shades.count()),
                    &self.nb.gpu_table(),
                    split.as_ref(),
                    |r| list.map_or(first + r, |(_, l)| l[first + r] as usize),
                    &mut out,
                );
                return readback.write(0, bytemuck::cast_slice(&out));
            }
            RowsOn::Gpu { local, rows } => (local, rows),
        };
        let push = JobPush {
            dims: self.dims4(self.nb.offsets.len() as i32),
            job: [
                rows as u32,
                self.shades.count() as u32,
                first as u32,
                list.is_some() as u32,
            ],
        };
        let bytes = (rows * self.hemispheres() * self.shades.count() * 4) as u64;
        self.gpu.submit_and_wait(|cmd| {
            let l = list.map_or(&self.bins, |(b, _)| b);
            local.bind(
                cmd,
                &[&self.bins, &self.neighbours, l, out, &self.split],
                bytemuck::bytes_of(&push),
            );
            local.dispatch(cmd, [(rows as u32).div_ceil(64), 1, 1]);
            self.gpu.barrier(cmd);
            let region = vk::BufferCopy::default().size(bytes.max(4));
            // SAFETY: `cmd` records; `out` (SRC), `readback` (DST) hold `bytes`, outlive the wait.
            unsafe {
                self.gpu
                    .device
                    .cmd_copy_buffer(cmd, out.raw, readback.raw, &[region]);
            }
            self.gpu.barrier(cmd);
        })?;
        Ok(())
    }

    /// The clustering of `vol` (this state's volume) computed again, on the host or by the
    /// shaders, whichever [`HistogramGpu::new`] took: the two must be the same.
    pub fn recluster(&mut self, vol: &Volume, on_host: bool) -> Result<Clusters> {
        let values = self.params.hemispheres.then(|| scalar_values(vol));
        self.cluster(values.as_deref(), on_host, &mut |_, _, _| {})
    }

    /// The voxels whose local histograms train the clusters: as many rows as with one sphere
    /// (half the voxels with two hemispheres, fewer where a flat voxel's second row is its
    /// first).
    pub fn training_sample(&self) -> Vec<u32> {
        hist::training_sample(
            self.dims,
            &self.shades.ids,
            MIN_TRAINING.max(16 * self.params.clusters) / self.hemispheres(),
        )
    }

    /// histogram_local.comp, and the device rows it adds into for batches of `rows` voxels.
    fn on_gpu(&self, rows: usize) -> Result<RowsOn<'static>> {
        let local = ComputePipeline::with_addresses(
            &self.gpu,
            spv("local"),
            &[
                Reach::Address,
                Reach::Descriptor,
                Reach::Descriptor,
                Reach::Descriptor,
                Reach::Descriptor,
            ],
            32,
            &[private_shades(self.shades.count())],
        )?;
        let bytes = rows * self.hemispheres() * self.shades.count() * 4;
        let rows = Buffer::new(
            &self.gpu,
            bytes.max(4) as u64,
            vk::BufferUsageFlags::STORAGE_BUFFER | vk::BufferUsageFlags::TRANSFER_SRC,
            MemoryLocation::GpuOnly,
            "hist-rows-gpu",
        )?;
        Ok(RowsOn::Gpu { local, rows })
    }

    /// The hemispheres' split as the host computes it, from the volume's scalars `values` (with
    /// the hemispheres; otherwise unused).
    fn host_split<'a>(&self, values: Option<&'a [f32]>) -> Option<hist::SplitF32<'a>> {
        let values = values.filter(|_| self.params.hemispheres)?;
        let (half_inv_spacing, flat2) = hist::SplitF32::parameters(self.spacing, self.range);
        Some(hist::SplitF32 {
            values,
            integer: self.scalars.1,
            half_inv_spacing,
            flat2,
        })
    }

    /// The local histograms of `voxels` as histogram_local.comp sums them, or with `host` (the
    /// volume) as its twin on the host's cores: per voxel a row of a sum per shade (H_f's then
    /// H_b's with the hemispheres; a flat voxel's second row is marked by a negative first
    /// entry).
    pub fn local_histograms(&self, voxels: &[u32], host: Option<&Volume>) -> Result<Vec<f32>> {
        let list = Buffer::from_slice(
            &self.gpu,
            voxels,
            vk::BufferUsageFlags::STORAGE_BUFFER,
            "hist-voxels",
        )?;
        let n = voxels.len() * self.hemispheres() * self.shades.count();
        let mut readback = self.readable(n * 4, "hist-rows")?;
        let values = host.map(scalar_values);
        let on = match host {
            Some(_) => RowsOn::Host(self.host_split(values.as_deref())),
            None => self.on_gpu(voxels.len())?,
        };
        self.local_rows(&on, (0, voxels.len()), Some((&list, voxels)), &mut readback)?;
        let rows: &[f32] = bytemuck::cast_slice(readback.mapped()?);
        Ok(rows[..n].to_vec())
    }

    /// A buffer of `bytes` (at least 4) the host reads: rows or ids copied or written there.
    fn readable(&self, bytes: usize, name: &str) -> Result<Buffer> {
        Buffer::new(
            &self.gpu,
            bytes.max(4) as u64,
            vk::BufferUsageFlags::STORAGE_BUFFER | vk::BufferUsageFlags::TRANSFER_DST,
            MemoryLocation::GpuToCpu,
            name,
        )
    }

    /// Local histograms per voxel: two with the hemispheres (H_f's, then H_b's), else one.
    fn hemispheres(&self) -> usize {
        1 + self.params.hemispheres as usize
    }

    /// S_r's largest offset on each axis, in voxels.
    pub fn reach_voxels(&self) -> [usize; 3] {
        let [x, y, z, _] = self.reach4();
        [x, y, z].map(|r| r as usize)
    }

    /// S_r's largest offset per axis.
    fn reach4(&self) -> [i32; 4] {
        let m = |a: usize| {
            self.nb
                .offsets
                .iter()
                .map(|o| o[a].abs())
                .max()
                .unwrap_or(0)
        };
        [m(0), m(1), m(2), 0]
    }

    fn dims4(&self, w: i32) -> [i32; 4] {
        [
            self.dims[0] as i32,
            self.dims[1] as i32,
            self.dims[2] as i32,
            w,
        ]
    }

    /// The clustering: the training sample's histograms on the GPU, packed and trained (LBG) on
    /// the host, then every voxel's histogram and nearest centroid on the GPU batch by batch,
    /// each cluster's representative the mean of its members' full histograms.
    /// The rows are summed and assigned on the host with `on_host` (split by `values`, the
    /// volume's scalars, with the hemispheres), else by the shaders.
    fn cluster(
        &mut self,
        values: Option<&[f32]>,
        on_host: bool,
        progress: &mut dyn FnMut(u64, u64, &str),
    ) -> Result<Clusters> {
        let (b, n, hemis) = (
            self.shades.count(),
            self.shades.ids.len(),
            self.hemispheres(),
        );
        let storage = vk::BufferUsageFlags::STORAGE_BUFFER;
        let packing = Packing::new(&self.shades.ids, b, hist::packed_dims(b));
        let p = packing.packed;
        // Training: the sample's histograms, packed.
        let t0 = std::time::Instant::now();
        progress(0, 1, "histograms of the training sample");
        let sample = self.training_sample();
        let list = Buffer::from_slice(&self.gpu, &sample, storage, "hist-sample")?;
        // One batch size for the sample and the assignment, within what the budget leaves.
        let batch_bytes = self
            .gpu
            .budget_left()
            .map_or(BATCH_BYTES, |left| BATCH_BYTES.min(left as usize / 5));
        let batch = (batch_bytes / (hemis * b * 4)).clamp(64, n.max(sample.len()).max(64));
        let mut rows = self.readable(batch * hemis * b * 4, "hist-rows")?;
        let on = if on_host {
            RowsOn::Host(self.host_split(values))
        } else {
            self.on_gpu(batch)?
        };
        let mut packed: Vec<f32> = Vec::new();
        for first in (0..sample.len()).step_by(batch) {
            let count = batch.min(sample.len() - first);
            self.local_rows(&on, (first, count), Some((&list, &sample)), &mut rows)?;
            let sample_rows: &[f32] = bytemuck::cast_slice(rows.mapped()?);
            packed.extend(
                sample_rows[..count * hemis * b]
                    .chunks_exact(b)
                    .filter(|lh| lh[0] >= 0.0)
                    .flat_map(|lh| packing.pack(lh)),
            );
        }
        drop(list);
        let sample_ms = t0.elapsed().as_secs_f64() * 1e3;
        progress(0, 1, "training the clusters (LBG)");
        let t1 = std::time::Instant::now();
        let centroids = hist::lbg(&packed, p, self.params.clusters);
        self.timing.training_ms = t1.elapsed().as_secs_f64() * 1e3;

        // Assignment, batch by batch, where the rows were summed.
        let groups = hist::Groups::new(&centroids, p);
        let host_assign = matches!(on, RowsOn::Host(_))
            .then(|| hist::HostAssign::new(&groups, &packing, &centroids));
        let device_assign = match &on {
            RowsOn::Gpu { .. } => Some(self.device_assign(&groups, &packing, &centroids, batch)?),
            RowsOn::Host(_) => None,
        };
        let k = self.params.clusters;
        let mut sums = vec![0.0f64; k * b];
        let mut pop = vec![0u64; k];
        let mut ids = Vec::with_capacity(n * hemis);
        let (mut hist_ms, mut assign_ms) = (sample_ms, 0.0);
        let batches = n.div_ceil(batch);
        for (i, first) in (0..n).step_by(batch).enumerate() {
            progress(i as u64, batches as u64, "local histograms and assignment");
            let count = batch.min(n - first);
            let t = std::time::Instant::now();
            self.local_rows(&on, (first, count), None, &mut rows)?;
            hist_ms += t.elapsed().as_secs_f64() * 1e3;
            let t = std::time::Instant::now();
            let batch_ids = match (&host_assign, &device_assign, &on) {
                (Some(host), _, _) => {
                    host.assign(&bytemuck::cast_slice(rows.mapped()?)[..count * hemis * b])
                }
                (None, Some(device), RowsOn::Gpu { rows, .. }) => {
                    device.run(&self.gpu, rows, count * hemis, (b, k))?
                }
                _ => unreachable!("the rows and their assignment are on one side"),
            };
            let batch_rows: &[f32] = bytemuck::cast_slice(rows.mapped()?);
            for (r, &c) in batch_ids.iter().enumerate() {
                // A flat voxel's second row is its first (marked, not assigned: only odd rows).
                let (c, row) = if c == SAME_AS_FRONT {
                    (batch_ids[r - 1], r - 1)
                } else {
                    (c, r)
                };
                pop[c as usize] += 1;
                let dst = &mut sums[c as usize * b..(c as usize + 1) * b];
                // A neighbourhood holds few of the shades: adding the zeros would change nothing.
                for (d, x) in dst.iter_mut().zip(&batch_rows[row * b..(row + 1) * b]) {
                    if *x != 0.0 {
                        *d += *x as f64;
                    }
                }
                ids.push(c);
            }
            assign_ms += t.elapsed().as_secs_f64() * 1e3;
        }
        progress(
            batches as u64,
            batches as u64,
            "local histograms and assignment",
        );
        self.timing.histograms_ms = hist_ms;
        self.timing.assignment_ms = assign_ms;
        self.timing.peak_host_bytes =
            (2 * batch * hemis * b * 4 + k * b * 8 + n * hemis * 4 + packed.len() * 4) as u64;
        let reps = sums
            .chunks_exact(b)
            .zip(&pop)
            .flat_map(|(s, &m)| {
                s.iter()
                    .map(move |x| if m > 0 { (x / m as f64) as f32 } else { 0.0 })
            })
            .collect();
        Ok(Clusters { bins: b, ids, reps })
    }

    /// histogram_assign.comp and its tables for batches of `batch` voxels.
    fn device_assign(
        &self,
        groups: &hist::Groups,
        packing: &Packing,
        centroids: &[f32],
        batch: usize,
    ) -> Result<DeviceAssign> {
        let p = packing.packed;
        let storage = vk::BufferUsageFlags::STORAGE_BUFFER;
        let table =
            |data: &[f32], name| Buffer::from_slice(&self.gpu, &pad4(data, p), storage, name);
        Ok(DeviceAssign {
            pipeline: ComputePipeline::with_addresses(
                &self.gpu,
                spv("assign"),
                &[Reach::Descriptor; 7],
                16,
                &[p.div_ceil(4) as u32],
            )?,
            groups: groups.first.len() as u32 - 1,
            tables: [
                table(&packing.matrix, "hist-packing")?,
                table(centroids, "hist-centroids")?,
                table(&groups.centres, "hist-group-centres")?,
                Buffer::from_slice(&self.gpu, &groups.first, storage, "hist-group-first")?,
                Buffer::from_slice(&self.gpu, &groups.members, storage, "hist-group-members")?,
            ],
            ids: self.readable(batch * self.hemispheres() * 4, "hist-batch-ids")?,
        })
    }

    /// Takes `tf` with the structures shown as `structures` (by structure index; empty: as the
    /// label map has them): the shade table (each shade's colour and opacity), and with
    /// clusters each cluster's A and E (one small table). Returns q of the unclipped volume
    /// (each voxel's bin opacity times its structure's a_l), the "opacity" CAO clips for this
    /// method.
    pub fn set_tf(&mut self, tf: &TransferFunction, structures: &[f32]) -> Result<Vec<f32>> {
        let bins = hist::bin_table(tf, self.range, self.params.bins);
        let table = self.shades.table(&bins, self.labels.as_deref(), structures);
        let q = self.shades.q(&table);
        self.write_tables(table)?;
        self.write_clear(&hist::clear_bricks(self.dims, &q, self.reach_voxels()))?;
        Ok(q)
    }

    /// The clear bricks' bits (empty: none clear, before a TF).
    fn write_clear(&mut self, bits: &[u32]) -> Result<()> {
        let mut words = vec![0u32; self.clear.size as usize / 4];
        words[..bits.len()].copy_from_slice(bits);
        self.clear.write(0, bytemuck::cast_slice(&words))
    }

    fn write_tables(&mut self, table: Vec<[f32; 4]>) -> Result<()> {
        if table.is_empty() {
            return Ok(());
        }
        self.bin_table.write(0, bytemuck::cast_slice(&table))?;
        if let Some(c) = &self.clusters {
            self.cluster_table
                .write(0, bytemuck::cast_slice(&c.tf_table(&table)))?;
        }
        self.last_table = table;
        Ok(())
    }

    /// Records V_PAO (`pre_a`) and [`HistogramGpu::pre_e`] of the unclipped volume's z-slices
    /// `z` for the TF last given to [`HistogramGpu::set_tf`]: the clusters' values, or with
    /// N = 0 the direct sums over `q`. Each voxel's values are its own, so slabs give the bits
    /// one pass gives.
    pub fn record_precompute(
        &self,
        cmd: vk::CommandBuffer,
        (q, pre_a): (&Buffer, &Buffer),
        z: std::ops::Range<usize>,
    ) {
        let mode = if self.clusters.is_some() {
            Pass::Clustered
        } else {
            Pass::Direct
        };
        let bufs = MethodBuffers::precompute(q, self.dims, (pre_a, &self.whole));
        let mut slab = VoxelBox::whole(self.dims);
        (slab.min[2], slab.max[2]) = (z.start as i32, z.end as i32);
        self.dispatch(cmd, &bufs, &self.pre_e, (&[slab], &[0]), mode);
    }

    /// The members of S_r summed over one z-slice of the volume: a slab's cost, in the unit of
    /// LAO's opacity samples.
    pub fn samples_per_slice(&self) -> f64 {
        (self.dims[0] * self.dims[1] * self.nb.offsets.len()) as f64
    }

    /// The bleeding colour of the unclipped volume, as the precompute left it (RGBA8 per voxel):
    /// [`HistogramGpu::pre_e`] without clusters, each voxel's (front) cluster's with them.
    pub fn precomputed_e(&self) -> Result<Buffer> {
        let n = self.dims.iter().product::<usize>().max(1);
        let usage = vk::BufferUsageFlags::STORAGE_BUFFER | vk::BufferUsageFlags::TRANSFER_SRC;
        let out = Buffer::new(
            &self.gpu,
            n as u64 * 4,
            usage,
            MemoryLocation::GpuOnly,
            "hist-e",
        )?;
        // The pass reads no density, mask or V_PAO: `out` stands in for them.
        let bufs = MethodBuffers::precompute(&out, self.dims, (&out, &self.whole));
        let all = [VoxelBox::whole(self.dims)];
        self.gpu.submit_and_wait(|cmd| {
            self.dispatch(cmd, &bufs, &out, (&all, &[0]), Pass::PrecomputedE)
        })?;
        Ok(out)
    }

    /// Records this method's values for the voxels of `boxes` into `bufs.out_a` and
    /// [`HistogramGpu::e`], from the clipped q (`bufs.density`) and CAO's categories as `mode`
    /// says ([`super::method::MethodGpu::record_update`]).
    pub fn record(
        &self,
        cmd: vk::CommandBuffer,
        bufs: &MethodBuffers,
        boxes: &[VoxelBox],
        at: &[i32],
        mode: Mode,
    ) {
        let pass = match mode {
            Mode::Contextual => Pass::Contextual,
            Mode::Naive => Pass::Naive,
        };
        self.dispatch(cmd, bufs, &self.e, (boxes, at), pass);
    }

    /// Records the bleeding colour (and V_AO) of the voxels of `boxes` back to the background
    /// state, as CAO's restore leaves V_AO: the precomputed values, or while `clipped` (a probe
    /// is active) those of category a, from the mask the restore just wrote
    /// ([`super::method::MethodGpu::record_restore`]).
    pub fn record_restore(
        &self,
        cmd: vk::CommandBuffer,
        bufs: &MethodBuffers,
        boxes: &[VoxelBox],
        at: &[i32],
        clipped: bool,
    ) {
        if clipped {
            self.gpu.barrier(cmd);
        }
        let pass = if clipped {
            Pass::Contextual
        } else {
            Pass::Restore
        };
        self.dispatch(cmd, bufs, &self.e, (boxes, at), pass);
    }

    fn dispatch(
        &self,
        cmd: vk::CommandBuffer,
        bufs: &MethodBuffers,
        out_e: &Buffer,
        (boxes, at): (&[VoxelBox], &[i32]),
        mode: Pass,
    ) {
        let r = self.reach4();
        let mode = mode as i32 + 8 * self.clusters.is_some() as i32;
        for (bx, &at) in boxes.iter().zip(at) {
            let push = SumsPush {
                dims: self.dims4(self.nb.offsets.len() as i32),
                box_min: [bx.min[0], bx.min[1], bx.min[2], mode],
                box_max: [bx.max[0], bx.max[1], bx.max[2], at],
                reach: [r[0], r[1], r[2], bufs.density_stride[0]],
            };
            let bufs = [
                bufs.density,
                &self.bins,
                &self.bin_table,
                &self.neighbours,
                bufs.mask,
                bufs.pre_a,
                &self.pre_e,
                bufs.out_a,
                out_e,
                &self.ids,
                &self.cluster_table,
                &self.split,
                &self.clear,
                bufs.ao_table,
            ];
            self.sums.bind(cmd, &bufs, bytemuck::bytes_of(&push));
            dispatch_box(&self.sums, cmd, bx);
        }
        self.gpu.barrier(cmd);
    }

    /// The bleeding volume of the last recorded frame, unpacked to RGB in [0, 1] (for export
    /// and tests).
    pub fn read_e(&self, buf: &Buffer) -> Result<Vec<[f32; 3]>> {
        let bytes = buf.read_back()?;
        Ok(bytemuck::cast_slice::<u8, u32>(&bytes)
            .iter()
            .map(|&x| [0, 8, 16].map(|s| ((x >> s) & 0xff) as f32 / 255.0))
            .collect())
    }
}
