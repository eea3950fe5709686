//! The transfer-function and AO-method switch (the menu button, `scene.tf_index`; the stick
//! click, `scene.ao_index`), and the structure menu (`scene.structures`: what is shown is part
//! of the opacity, so hiding a structure is a change of O like a TF change): progressive, so
//! the frame rate holds. O' and its skipping data are classified on a worker thread, then each
//! frame records one slab of V_PAO' (bounded by a budget of opacity samples; a filter method
//! refilters in one go) ahead of its CAO passes while the frame still shows the old TF, method,
//! structures and AO; with SH lighting and a new opacity, slabs of V_PSH' follow. The frame
//! after the last slab switches the LUT, the structure table, the CAO state (its method
//! included) and the SH volume over at once.

use super::common::{histogram_tables, AppError, Result};
use super::lighting::ShLighting;
use crate::ao::cao::Cao;
use crate::ao::filter_gpu::FilterGpu;
use crate::ao::filtered;
use crate::ao::histogram_gpu::HistogramGpu;
use crate::ao::lao::{LaoLayout, LaoParams, SkipData};
use crate::ao::method::{MethodGpu, Refresh};
use crate::ao::progressive::{HostTask, SlabScheduler};
use crate::ao::sh::ShVolume;
use crate::ao::{AoMethod, LaoGpu};
use crate::gpu::{Buffer, Gpu, GpuTimer};
use crate::render::VolumeTextures;
use crate::scene::Scene;
use crate::volume::labels::{shown_as, LabelMap};
use crate::volume::transfer::{presets_for_volume, TransferFunction};
use crate::volume::Volume;
use ash::vk;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

/// How far a switch has come: V_PAO' (and V_PSH', half each) of `name` (the new TF, or the
/// new AO method when that is what changed) is `fraction` done (0 while the host still
/// classifies). Shown as "TF ct-skin 40%" or "AO lao 40%".
#[derive(Clone, Debug, PartialEq)]
pub struct TfProgress {
    /// "TF" or "AO".
    pub what: &'static str,
    pub name: String,
    pub fraction: f32,
}

impl std::fmt::Display for TfProgress {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} {} {:.0}%",
            self.what,
            self.name,
            100.0 * self.fraction
        )
    }
}

/// The transfer functions the menu cycles through: `first` (the one asked for), then the
/// presets suited to the volume ([`presets_for_volume`]: CT or MR), each once.
pub fn tf_cycle(first: &TransferFunction, vol: &Volume) -> Vec<TransferFunction> {
    let mut tfs = vec![first.clone()];
    for tf in presets_for_volume(vol)
        .into_iter()
        .filter_map(TransferFunction::preset)
    {
        if !tfs.iter().any(|t| t.name == tf.name) {
            tfs.push(tf);
        }
    }
    tfs
}

/// Default V_PAO' budget per frame, in opacity samples (K*M per voxel): a few ms on a GPU; on a
/// CPU device (lavapipe, ~20 M samples/s) about a tenth of a second.
pub fn default_tf_samples_per_frame(gpu: &Gpu) -> f64 {
    if gpu.is_cpu() {
        2e6
    } else {
        2e8
    }
}

/// What is shown, or asked for: the TF and AO method (indices into [`TfSwitcher::tfs`] and
/// [`TfSwitcher::methods`]) and each structure's opacity a_l.
#[derive(Clone, Debug, PartialEq)]
struct Choice {
    tf: usize,
    method: usize,
    structures: Vec<f32>,
    /// The isovalue shown (its bits), if an isosurface is: then O is its solid's opacity.
    iso: Option<u32>,
}

impl Choice {
    /// Whether `other` classifies to the same opacity O (the same TF, structures and iso).
    fn same_opacity(&self, other: &Choice) -> bool {
        self.tf == other.tf && self.structures == other.structures && self.iso == other.iso
    }
}

/// The TF choice `c` classifies O with and colours by: its TF of `tfs`, or with an isovalue
/// that TF's iso solid ([`TransferFunction::iso_solid`]) over the volume's `range`.
fn tf_of(tfs: &[TransferFunction], range: (f32, f32), c: &Choice) -> TransferFunction {
    let tf = &tfs[c.tf];
    match c.iso {
        Some(bits) => tf.iso_solid(f32::from_bits(bits), range),
        None => tf.clone(),
    }
}

/// A switch in flight.
struct Switch {
    /// What it computes.
    choice: Choice,
    stage: Stage,
}

// At most one exists per loop: its size does not matter.
#[allow(clippy::large_enum_variant)]
enum Stage {
    /// O' and, for LAO (the only method that reads them), its skipping data, on a worker thread;
    /// the filters' state, made when the switch starts (None for LAO).
    Classifying {
        task: HostTask<(Vec<f32>, Option<SkipData>)>,
        filter: Option<FilterGpu>,
    },
    /// The new method's state and O', one slab of V_PAO' per frame, then (with SH lighting)
    /// one slab of V_PSH'.
    Computing {
        opacity: Buffer,
        method: MethodGpu,
        pao: Buffer,
        slabs: SlabScheduler,
        sh: Option<(ShVolume, SlabScheduler)>,
    },
}

impl Switch {
    fn fraction(&self) -> f32 {
        match &self.stage {
            Stage::Classifying { .. } => 0.0,
            Stage::Computing {
                slabs, sh: None, ..
            } => slabs.fraction(),
            Stage::Computing {
                slabs,
                sh: Some((_, sh_slabs)),
                ..
            } => 0.5 * (slabs.fraction() + sh_slabs.fraction()),
        }
    }
}

/// The local histograms' clustering (independent of the TF) computed on a worker thread while
/// the frames are lit by what is shown: its GPU batches are submitted beside the frames.
struct Clustering {
    /// The index of the method in [`TfSwitcher::methods`].
    method: usize,
    /// None until the first picture is out.
    task: Option<HostTask<std::result::Result<HistogramGpu, String>>>,
    /// Batches done (high 32 bits) and in all (low 32 bits), as the clustering tells them.
    progress: Arc<AtomicU64>,
}

impl Clustering {
    fn fraction(&self) -> f32 {
        let p = self.progress.load(Ordering::Relaxed);
        let (done, total) = ((p >> 32) as f32, (p & 0xffff_ffff) as f32);
        if total > 0.0 {
            done / total
        } else {
            0.0
        }
    }
}

/// The transfer functions and AO methods a frame loop can show, the ones it shows, and the
/// switch in flight.
pub struct TfSwitcher {
    gpu: Gpu,
    tfs: Vec<TransferFunction>,
    /// The volume's value range (an iso solid's colour is its TF's there).
    value_range: (f32, f32),
    methods: Vec<AoMethod>,
    shown: Choice,
    /// Nothing is computed yet (the CAO state's method is [`MethodGpu::Open`], AO 1): the
    /// shown choice's method is the one computed first, whatever the scene asks.
    open: bool,
    /// Open, the first switch (and any start, the local histograms' clustering) waits until a
    /// picture has left the GPU ([`TfSwitcher::picture_shown`]): its classification on the
    /// host would take the cores from that first picture (on lavapipe, 13 s instead of 5 at
    /// 512 x 512 x 600).
    first_picture_pending: bool,
    /// The structures' names, for the progress line.
    names: Vec<String>,
    switch: Option<Switch>,
    /// The local-histogram method's state while another method is shown (its clustering is
    /// kept, so switching back is a table update).
    parked: Option<HistogramGpu>,
    /// The local histograms' clustering on a worker thread, where the loop started without it
    /// (a fast start): parked when done.
    clustering: Option<Clustering>,
    lao: LaoGpu,
    lao_dirs: Buffer,
    /// The LAO parameters a switch to LAO computes with (`lao_dirs` holds their directions).
    params: LaoParams,
    timer: GpuTimer,
}

impl TfSwitcher {
    /// `lao_dirs` holds the directions of the CAO state's LAO parameters (V_PAO' uses them).
    /// The CAO state shows the first of `tfs`, `methods[shown_method]` and the structures of
    /// `labels` as it sets them; `open`: it shows no method yet, and `methods[shown_method]`
    /// is computed first.
    pub fn new(
        gpu: &Gpu,
        tfs: Vec<TransferFunction>,
        (methods, shown_method, open): (Vec<AoMethod>, usize, bool),
        (labels, value_range, iso): (Option<&LabelMap>, (f32, f32), Option<f32>),
        (lao, lao_dirs, params): (LaoGpu, Buffer, LaoParams),
    ) -> Result<Self> {
        Ok(TfSwitcher {
            gpu: gpu.clone(),
            tfs,
            methods,
            shown: Choice {
                tf: 0,
                method: shown_method,
                structures: labels.map_or_else(Vec::new, LabelMap::opacities),
                iso: iso.map(f32::to_bits),
            },
            value_range,
            open,
            first_picture_pending: true,
            names: labels.map_or_else(Vec::new, |l| {
                l.structures.iter().map(|s| s.name.clone()).collect()
            }),
            switch: None,
            parked: None,
            clustering: None,
            lao,
            lao_dirs,
            params,
            timer: GpuTimer::new(gpu, 2)?,
        })
    }

    pub fn all(&self) -> &[TransferFunction] {
        &self.tfs
    }

    /// The transfer function whose colours and AO the frames show.
    pub fn shown(&self) -> &TransferFunction {
        &self.tfs[self.shown.tf]
    }

    /// The TF a choice classifies O with and colours by ([`tf_of`]).
    fn tf_of(&self, c: &Choice) -> TransferFunction {
        tf_of(&self.tfs, self.value_range, c)
    }

    /// What `scene` asks for. A scene whose structure list does not match (none set) asks
    /// for the structures as shown.
    fn wanted(&self, scene: &Scene) -> Choice {
        let structures = if scene.structures.len() == self.shown.structures.len() {
            scene.structures.clone()
        } else {
            self.shown.structures.clone()
        };
        Choice {
            tf: scene.tf_index % self.tfs.len(),
            method: if self.open {
                self.shown.method
            } else {
                scene.ao_index % self.methods.len()
            },
            structures,
            iso: scene.iso.map(f32::to_bits),
        }
    }

    /// The AO methods the stick click cycles through.
    pub fn methods(&self) -> &[AoMethod] {
        &self.methods
    }

    /// The AO method shown, and the TF its O was classified with (an isosurface's solid).
    pub fn shown_ao(&self) -> (AoMethod, TransferFunction) {
        (self.methods[self.shown.method], self.tf_of(&self.shown))
    }

    /// The structures' opacities a_l the shown AO classified O with (by structure index).
    pub fn shown_structures(&self) -> &[f32] {
        &self.shown.structures
    }

    /// Whether what `scene` asks for (transfer function, AO method, structures) is shown with
    /// no switch in flight: then [`TfSwitcher::advance`] replaces nothing and records no slab.
    pub fn settled(&self, scene: &Scene) -> bool {
        self.switch.is_none()
            && self.clustering.is_none()
            && !self.open
            && self.wanted(scene) == self.shown
    }

    /// A frame has left the GPU: an open start's first switch may begin.
    pub fn picture_shown(&mut self) {
        self.first_picture_pending = false;
    }

    /// The switch in flight, if any (an open start's first one from the first frame, at 0 %
    /// while it waits for the first picture).
    pub fn progress(&self) -> Option<TfProgress> {
        if let Some(c) = &self.clustering {
            return Some(TfProgress {
                what: "AO",
                name: self.methods[c.method].name(),
                fraction: c.fraction(),
            });
        }
        if self.open && self.switch.is_none() {
            return Some(TfProgress {
                what: "AO",
                name: self.methods[self.shown.method].name(),
                fraction: 0.0,
            });
        }
        self.switch.as_ref().map(|sw| {
            let (want, shown) = (&sw.choice, &self.shown);
            let (what, name) = if want.tf != shown.tf && !self.open {
                ("TF", self.tfs[want.tf].name.clone())
            } else if want.iso != shown.iso && !self.open {
                let iso = want
                    .iso
                    .map_or(String::new(), |b| f32::from_bits(b).to_string());
                ("iso", iso)
            } else if want.method != shown.method || self.open {
                ("AO", self.methods[want.method].name())
            } else {
                ("labels", self.structure_change(&want.structures))
            };
            TfProgress {
                what,
                name,
                fraction: sw.fraction(),
            }
        })
    }

    /// How `structures` differ from the shown ones, by name ("ribs hidden").
    fn structure_change(&self, structures: &[f32]) -> String {
        let changed: Vec<String> = structures
            .iter()
            .zip(&self.shown.structures)
            .enumerate()
            .filter(|(_, (a, b))| a != b)
            .map(|(k, (&a, _))| format!("{} {}", self.names[k], shown_as(a)))
            .collect();
        changed.join(", ")
    }

    /// Follows what `scene` asks for (its TF and AO-method indices and structure opacities):
    /// starts, restarts or drops a switch, sizes the slabs still to come for `budget`, hands finished host work to the GPU,
    /// and switches `cao`, `tex` and `lighting` over once every slab has executed. Runs before
    /// the frame is recorded, after the previous frame's wait, so no submitted work uses what it
    /// drops.
    pub fn advance(
        &mut self,
        scene: &Scene,
        vol: &Arc<Volume>,
        budget: f64,
        cao: &mut Cao,
        tex: &mut VolumeTextures,
        lighting: Option<&mut ShLighting>,
    ) -> Result<()> {
        let want = self.wanted(scene);
        let table = self.methods[want.method].refresh() == Refresh::Table;
        if (table && self.parked.is_none() && cao.histogram().is_none())
            || self.clustering.is_some()
        {
            // The local histograms not clustered yet (a fast start): on a worker thread, once
            // the first picture is out; the frames meanwhile show what is shown.
            if !self.cluster(want.method, vol)? && table {
                return Ok(());
            }
        }
        if table && (want != self.shown || self.open) {
            // The local histograms follow a new TF (or come back) with one table update.
            self.switch = None;
            return self.switch_to_histogram(want, vol, cao, tex);
        }
        let target = self.switch.as_ref().map_or(&self.shown, |s| &s.choice);
        // Open, the first switch starts though the choice is the shown one (once the first
        // picture is out).
        let first = self.open && self.switch.is_none() && !self.first_picture_pending;
        if &want != target || first {
            // Dropping the switch in flight frees O', V_PAO' and skip': safe, because the frame
            // loop waits for the frame in flight before a frame that is not
            // [`TfSwitcher::settled`], so none of them is in use any more; an unfinished
            // classification thread is detached and its result discarded.
            self.switch = None;
            if want != self.shown || first {
                self.switch = Some(self.start(want, vol)?);
            }
        }
        let Some(sw) = self.switch.as_mut() else {
            return Ok(());
        };
        if let Stage::Classifying { task, filter } = &mut sw.stage {
            let Some(done) = task.poll() else {
                return Ok(());
            };
            let name = &tf_of(&self.tfs, self.value_range, &sw.choice).name;
            let (opacity, skip) = done.map_err(|msg| {
                AppError::Usage(format!(
                    "{}: classifying with transfer function '{name}' failed: {msg}",
                    vol.name
                ))
            })?;
            // The SH visibility depends on the opacity (TF and structures), not on the AO
            // method.
            let sh = match &lighting {
                Some(l) if self.open || !sw.choice.same_opacity(&self.shown) => {
                    let v = ShVolume::new(&self.gpu, vol, l.volume.params)?;
                    let slabs =
                        SlabScheduler::with_budget(v.grid.dims[2], v.samples_per_slice(), budget);
                    Some((v, slabs))
                }
                _ => None,
            };
            // O in its method's format: f32 for the filters, else 16-bit (`Cao::clipped_stride`).
            let usage = vk::BufferUsageFlags::STORAGE_BUFFER;
            let opacity = match filter {
                Some(_) => Buffer::device_local(&self.gpu, &opacity, usage, "opacity")?,
                None => crate::ao::stored::upload(&self.gpu, &opacity, usage, "opacity")?,
            };
            let method =
                MethodGpu::switched(&self.gpu, &self.lao, vol, self.params, filter.take(), skip)?;
            // The filters refilter the whole volume in one go (they are cheap); LAO goes a
            // bounded slab of slices per frame.
            let slabs = match self.methods[sw.choice.method].refresh() {
                Refresh::Slabs => SlabScheduler::with_budget(
                    vol.dims[2],
                    LaoGpu::samples_per_slice(vol.dims, &self.params),
                    budget,
                ),
                Refresh::OneGo | Refresh::Table => SlabScheduler::new(1, 1),
            };
            sw.stage = Stage::Computing {
                sh,
                opacity,
                method,
                pao: self.lao.output_buffer(vol.dims)?,
                slabs,
            };
        }
        if let Stage::Computing { slabs, sh, .. } = &mut sw.stage {
            slabs.set_budget(budget);
            if let Some((_, sh_slabs)) = sh {
                sh_slabs.set_budget(budget);
            }
        }
        let finished = matches!(&sw.stage, Stage::Computing { slabs, sh, .. }
            if slabs.is_finished() && sh.as_ref().is_none_or(|s| s.1.is_finished()));
        if finished {
            let sw = self.switch.take().expect("checked above");
            let Stage::Computing {
                opacity,
                method,
                pao,
                sh,
                ..
            } = sw.stage
            else {
                unreachable!("finished implies computing")
            };
            tex.set_transfer_function(&self.tf_of(&sw.choice))?;
            tex.set_structure_opacities(&sw.choice.structures);
            cao.replace_precomputed(opacity, pao)?;
            if let MethodGpu::Histogram(h) = cao.set_method(method)? {
                self.parked = Some(h);
            }
            // Now, slab by slab, rather than whole in the next frame (fewer bytes staged).
            cao.restore_whole()?;
            if let (Some((mut v, _)), Some(l)) = (sh, lighting) {
                self.gpu.submit_and_wait(|cmd| v.record_publish(cmd))?;
                l.volume = v;
            }
            self.shown = sw.choice;
            self.open = false;
        }
        Ok(())
    }

    /// Starts the clustering of local-histogram method `method` on a worker thread (once the
    /// first picture is out), or polls it: true once it is parked (then a switch to it is a
    /// table update), or where no clustering is wanted.
    fn cluster(&mut self, method: usize, vol: &Arc<Volume>) -> Result<bool> {
        let AoMethod::Histogram(params) = self.methods[method] else {
            // Not wanted now: one running goes on (parked when done), one not begun is dropped.
            if self.clustering.as_ref().is_some_and(|c| c.task.is_none()) {
                self.clustering = None;
            }
            return match self.clustering {
                Some(_) => self.poll_clustering(vol),
                None => Ok(true),
            };
        };
        let c = self.clustering.get_or_insert_with(|| Clustering {
            method,
            task: None,
            progress: Arc::new(AtomicU64::new(0)),
        });
        if c.task.is_some() {
            return self.poll_clustering(vol);
        }
        if self.first_picture_pending {
            return Ok(false);
        }
        let (gpu, v, told) = (self.gpu.clone(), Arc::clone(vol), Arc::clone(&c.progress));
        let task = HostTask::spawn("cao-xr-cluster", move || {
            let cache = crate::ao::histogram::default_cache_dir();
            HistogramGpu::new(&gpu, &v, params, Some(&cache), &mut |done, total, _| {
                told.store((done << 32) | total, Ordering::Relaxed)
            })
            .map_err(|e| e.to_string())
        })
        .map_err(|e| {
            AppError::Usage(format!(
                "{}: cannot start a thread for the local histograms: {e}",
                vol.name
            ))
        })?;
        c.task = Some(task);
        Ok(false)
    }

    /// Takes the clustering's result once it is there (parked): whether it is.
    fn poll_clustering(&mut self, vol: &Volume) -> Result<bool> {
        let Some(done) = self
            .clustering
            .as_mut()
            .and_then(|c| c.task.as_mut())
            .and_then(HostTask::poll)
        else {
            return Ok(false);
        };
        let h = done
            .and_then(|r| r)
            .map_err(|e| AppError::Usage(format!("{}: local histograms: {e}", vol.name)))?;
        self.clustering = None;
        self.parked = Some(h);
        Ok(true)
    }

    /// Shows the local-histogram method under TF `index` at once: the bins' and clusters'
    /// tables, q, and one pass for V_PAO and the bleeding volume.
    fn switch_to_histogram(
        &mut self,
        want: Choice,
        vol: &Volume,
        cao: &mut Cao,
        tex: &mut VolumeTextures,
    ) -> Result<()> {
        let tf = &self.tf_of(&want);
        let (gpu, lao) = (&self.gpu, &self.lao);
        let shown = (tf, &want.structures[..]);
        let build = |h: &mut HistogramGpu| histogram_tables(gpu, lao, vol.dims, h, shown);
        let shown_here = match cao.histogram_mut() {
            Some(h) => Some(build(h)?),
            None => None,
        };
        match shown_here {
            Some(t) => cao.replace_precomputed(t.opacity, t.pao)?,
            None => {
                let mut h = self.parked.take().ok_or_else(|| {
                    AppError::Usage("the local-histogram method was not set up".into())
                })?;
                let t = build(&mut h)?;
                cao.replace_precomputed(t.opacity, t.pao)?;
                cao.set_method(MethodGpu::Histogram(h))?;
            }
        }
        cao.restore_whole()?;
        tex.set_transfer_function(tf)?;
        tex.set_structure_opacities(&want.structures);
        self.shown = want;
        self.open = false;
        Ok(())
    }

    fn start(&self, choice: Choice, vol: &Arc<Volume>) -> Result<Switch> {
        let filter = match self.methods[choice.method] {
            AoMethod::Filter(p) => Some(FilterGpu::new(&self.gpu, vol.dims, vol.spacing, p)?),
            _ => None,
        };
        let vol = Arc::clone(vol);
        let tf = self.tf_of(&choice);
        let tf_name = tf.name.clone();
        let structures = choice.structures.clone();
        let params = self.params;
        let input = filter.as_ref().map(|f| f.params.input);
        let name = vol.name.clone();
        let task = HostTask::spawn("cao-xr-classify", move || {
            let opacity = tf.opacity_volume_showing(&vol, &structures);
            match input {
                Some(input) => (filtered::density(input, &opacity, &vol), None),
                None => {
                    let skip = SkipData::new(&opacity, vol.dims, vol.spacing, &params);
                    (opacity, Some(skip))
                }
            }
        })
        .map_err(|e| {
            AppError::Usage(format!(
                "{name}: cannot start a thread to classify with transfer function '{tf_name}': {e}"
            ))
        })?;
        Ok(Switch {
            choice,
            stage: Stage::Classifying { task, filter },
        })
    }

    /// Records this frame's slab of V_PAO' (or, once those are done, of V_PSH'). It writes only
    /// buffers of its own, which no other pass of the frame reads, so it needs no barrier.
    /// Returns whether a slab was recorded (then [`TfSwitcher::read_ms`] has its time).
    pub fn record_slab(&mut self, cmd: vk::CommandBuffer, vol: &Volume) -> bool {
        let Some(Switch {
            stage:
                Stage::Computing {
                    opacity,
                    method,
                    pao,
                    slabs,
                    sh,
                },
            ..
        }) = self.switch.as_mut()
        else {
            return false;
        };
        if let Some(z) = slabs.next_slab() {
            self.timer.begin(cmd);
            method.record_precompute(cmd, &self.lao, &self.lao_dirs, opacity, pao, z);
            self.timer.mark(cmd, "tf-slab");
            return true;
        }
        if let Some((v, sh_slabs)) = sh.as_mut() {
            if sh_slabs.done() == 0 {
                let [x, y, z, _] = LaoLayout::unpadded_stride(vol.dims);
                let stride = [x, y, z, method.float_density() as i32];
                v.record_pyramid(cmd, opacity, stride);
            }
            if let Some(z) = sh_slabs.next_slab() {
                self.timer.begin(cmd);
                v.record_precompute_slab(cmd, z);
                self.timer.mark(cmd, "tf-slab");
                return true;
            }
        }
        false
    }

    /// GPU ms of the slab recorded in the frame just waited for.
    pub fn read_ms(&self) -> Result<f64> {
        Ok(self.timer.read()?.first().map_or(0.0, |t| t.1))
    }
}
