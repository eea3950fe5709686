//! V_AO in bricks (docs/design.md, "V_AO in bricks"): where GPU memory is short, a CAO state
//! stores V_AO only in the bricks of [`AO_BRICK`]³ voxels where some voxel's AO can differ
//! from 1; a CT is mostly air.
//!
//! A brick is left out where every voxel of it has V_PAO 1 and no voxel with O > 0 lies within
//! the method's reach of it (and the trilinear footprint). Every value a frame can write there
//! is then 1: a clipped voxel gets 1, an unaffected one its V_PAO, a recomputed one the method
//! on O_c <= O, which finds nothing within reach (LAO 1, the filters 1, the local histograms'
//! sums A = 1). The writers skip such a brick and the ray caster reads 1 for it, so the
//! pictures and V_AO are those of a whole V_AO bit for bit. A table gives each brick (x fastest)
//! its slot in the pool, or [`AO_NONE`]; a one-word table [`AO_WHOLE`] stands for a V_AO stored
//! whole (a precompute's V_PAO). The shaders' side is shaders/include/ao_pool.glsl.

use crate::gpu::{Buffer, Gpu, Result};
pub use crate::shader_constants::{AO_BRICK_SHIFT, AO_NONE, AO_WHOLE};
use ash::vk;
use rayon::prelude::*;

/// Edge of a brick, in voxels.
pub const AO_BRICK: usize = 1 << AO_BRICK_SHIFT;
const BRICK_VOXELS: usize = AO_BRICK * AO_BRICK * AO_BRICK;

/// The share of bricks kept above which V_AO is stored whole ([`AoPool::new`]).
pub const KEEP_WHOLE: f64 = 0.75;

/// V_AO is stored in bricks by default only where GPU memory is short: where less than this
/// many times V_AO stored whole is left ([`memory_short`]). The ray caster's table reads cost
/// about a tenth of its time on lavapipe (docs/benchmarks.md, "V_AO in bricks").
pub const SHORT_FACTOR: u64 = 4;

/// Whether the GPU has less than [`SHORT_FACTOR`] times a whole V_AO of `dims` left, within the
/// budget ([`crate::gpu::BUDGET_ENV`]) and the device-local heap, counting `freed` bytes about
/// to be freed as left.
pub fn memory_short(gpu: &Gpu, dims: [usize; 3], freed: u64) -> bool {
    let whole = super::stored::bytes(dims.iter().product::<usize>() as u64);
    let heap = gpu
        .device_local_heap_bytes()
        .saturating_sub(gpu.memory_in_use());
    let left = gpu.budget_left().map_or(heap, |b| b.min(heap)) + freed;
    left < SHORT_FACTOR * whole
}

/// Which bricks V_AO keeps ([`needed`], from O's words of `es` bytes, V_PAO's and the reach in
/// voxels), or None to store it whole: as `bricks` says, or where it is None where GPU memory
/// is short ([`memory_short`], `freed` bytes about to be freed).
pub fn kept_bricks(
    gpu: &Gpu,
    dims: [usize; 3],
    (opacity, es, pao): (&[u8], usize, &[u8]),
    reach: [usize; 3],
    (bricks, freed): (Option<bool>, u64),
) -> Option<Vec<bool>> {
    bricks
        .unwrap_or_else(|| memory_short(gpu, dims, freed))
        .then(|| needed(dims, opacity, es, pao, reach))
}

/// Bricks per axis of a volume of `dims`.
pub fn bricks(dims: [usize; 3]) -> [usize; 3] {
    dims.map(|d| d.div_ceil(AO_BRICK).max(1))
}

/// A method's reach of `reach_mm` in voxels per axis, with the trilinear footprint.
pub fn reach_voxels(reach_mm: f64, spacing: [f64; 3]) -> [usize; 3] {
    spacing.map(|s| (reach_mm / s).ceil() as usize + 1)
}

/// Which bricks V_AO must store, x fastest: those with a voxel whose V_PAO word (`pao`, 16-bit)
/// is not 1, or with a voxel of O > 0 (`opacity`, words of `es` bytes: 2, or 4 for f32) within
/// `reach` voxels per axis of one of theirs.
pub fn needed(
    dims: [usize; 3],
    opacity: &[u8],
    es: usize,
    pao: &[u8],
    reach: [usize; 3],
) -> Vec<bool> {
    let nb = bricks(dims);
    let plane = nb[0] * nb[1];
    let (nx, ny) = (dims[0], dims[1]);
    // Per brick: some O > 0 in it, and some V_PAO below 1; a z-row of bricks per task.
    let flags: Vec<(bool, bool)> = (0..nb[2])
        .into_par_iter()
        .flat_map_iter(|bz| {
            let mut row = vec![(false, false); plane];
            let z1 = ((bz + 1) * AO_BRICK).min(dims[2]);
            for z in bz * AO_BRICK..z1 {
                for y in 0..ny {
                    let first = nx * (y + ny * z);
                    let at = (y / AO_BRICK) * nb[0];
                    for x in 0..nx {
                        let i = first + x;
                        let o = &opacity[i * es..(i + 1) * es];
                        let occupied = if es == 4 {
                            f32::from_le_bytes([o[0], o[1], o[2], o[3]]) > 0.0
                        } else {
                            o != [0, 0]
                        };
                        let shaded = pao[2 * i..2 * i + 2] != [0xFF, 0xFF];
                        let f = &mut row[at + x / AO_BRICK];
                        f.0 |= occupied;
                        f.1 |= shaded;
                    }
                }
            }
            row
        })
        .collect();
    // Dilate the occupied bricks by the reach, in bricks (conservative), one axis at a time.
    let r = reach.map(|h| h.div_ceil(AO_BRICK));
    let strides = [1, nb[0], plane];
    let occupied = (0..3).fold(
        flags.iter().map(|f| f.0).collect::<Vec<bool>>(),
        |src, axis| {
            (0..src.len())
                .into_par_iter()
                .map(|b| {
                    let pos = [b % nb[0], (b / nb[0]) % nb[1], b / plane][axis];
                    let lo = pos.saturating_sub(r[axis]);
                    let hi = (pos + r[axis]).min(nb[axis] - 1);
                    let base = b - pos * strides[axis];
                    (lo..=hi).any(|p| src[base + p * strides[axis]])
                })
                .collect()
        },
    );
    occupied
        .iter()
        .zip(&flags)
        .map(|(&near, f)| near || f.1)
        .collect()
}

/// Each brick's slot: the kept ones numbered in order, the others [`AO_NONE`].
pub fn slots(kept: &[bool]) -> Vec<u32> {
    let mut next = 0;
    kept.iter()
        .map(|&k| {
            if k {
                next += 1;
                next - 1
            } else {
                AO_NONE
            }
        })
        .collect()
}

/// Where voxel `v` lies in a pool of `slots`, or None where its brick is not stored.
pub fn index(slots: &[u32], dims: [usize; 3], v: [usize; 3]) -> Option<usize> {
    let nb = bricks(dims);
    let b = v.map(|c| c >> AO_BRICK_SHIFT);
    let slot = slots[b[0] + nb[0] * (b[1] + nb[1] * b[2])];
    let l = v.map(|c| c & (AO_BRICK - 1));
    (slot != AO_NONE)
        .then(|| slot as usize * BRICK_VOXELS + l[0] + AO_BRICK * (l[1] + AO_BRICK * l[2]))
}

/// V_AO of a CAO state: the stored bricks and their table.
pub struct AoPool {
    /// The stored bricks' 16-bit words (each brick x fastest), at least one brick.
    pub words: Buffer,
    /// Per brick its slot in `words` or [`AO_NONE`] (32-bit words, the shaders' AoTable).
    pub table: Buffer,
    slots: Vec<u32>,
    dims: [usize; 3],
}

impl AoPool {
    /// A pool of the bricks `kept` (x fastest) of a volume of `dims`, its words uninitialised,
    /// or V_AO stored whole where `kept` is None or holds more than [`KEEP_WHOLE`] of the
    /// bricks (the little it would save is not worth the ray caster's table reads).
    /// Its table is copied in by `cmd` (recording, outside a render pass; a barrier follows)
    /// from the staging buffer returned beside it, which must outlive that submission: no
    /// submission of its own, so it can be made while a frame is recorded.
    pub fn new(
        gpu: &Gpu,
        dims: [usize; 3],
        kept: Option<&[bool]>,
        cmd: vk::CommandBuffer,
    ) -> Result<(AoPool, Buffer)> {
        let count = |k: &[bool]| k.iter().filter(|&&k| k).count();
        let (slots, stored) = match kept {
            Some(k) if count(k) as f64 <= KEEP_WHOLE * k.len() as f64 => {
                (slots(k), count(k).max(1))
            }
            _ => {
                let voxels: usize = dims.iter().product();
                (vec![AO_WHOLE], voxels.div_ceil(BRICK_VOXELS))
            }
        };
        let usage = vk::BufferUsageFlags::STORAGE_BUFFER
            | vk::BufferUsageFlags::TRANSFER_SRC
            | vk::BufferUsageFlags::TRANSFER_DST;
        let words = Buffer::new(
            gpu,
            (stored * BRICK_VOXELS) as u64 * super::stored::BYTES_PER_VOXEL,
            usage,
            gpu_allocator::MemoryLocation::GpuOnly,
            "cao-ao",
        )?;
        let bytes = (slots.len() * 4) as u64;
        let table = Buffer::new(
            gpu,
            bytes,
            usage,
            gpu_allocator::MemoryLocation::GpuOnly,
            "ao-brick-table",
        )?;
        let staging = Buffer::from_slice(
            gpu,
            &slots,
            vk::BufferUsageFlags::TRANSFER_SRC,
            "ao-brick-table-staging",
        )?;
        // SAFETY: `cmd` is recording outside a render pass (this function's contract); both
        // buffers hold `bytes` from 0, `staging` has TRANSFER_SRC and `table` TRANSFER_DST, and
        // the caller keeps both until the submission has finished.
        unsafe {
            let region = [vk::BufferCopy::default().size(bytes)];
            gpu.device
                .cmd_copy_buffer(cmd, staging.raw, table.raw, &region);
        }
        gpu.barrier(cmd);
        let pool = AoPool {
            words,
            table,
            slots,
            dims,
        };
        Ok((pool, staging))
    }

    /// Whether V_AO is stored whole, x fastest (no brick left out), its table [`AO_WHOLE`].
    pub fn whole(&self) -> bool {
        self.slots == [AO_WHOLE]
    }

    /// Bricks stored, of all.
    pub fn stored(&self) -> (usize, usize) {
        let all = bricks(self.dims).iter().product();
        if self.whole() {
            return (all, all);
        }
        (self.slots.iter().filter(|&&s| s != AO_NONE).count(), all)
    }

    /// V_AO read back whole, x fastest, as values in [0, 1] (1 where no brick is stored).
    pub fn read(&self) -> Result<Vec<f32>> {
        let bytes = self.words.read_back()?;
        let words: &[u16] = bytemuck::cast_slice(&bytes[..bytes.len() & !1]);
        let [nx, ny, nz] = self.dims;
        if self.whole() {
            return super::stored::read(&self.words, nx * ny * nz);
        }
        Ok((0..nx * ny * nz)
            .into_par_iter()
            .map(|i| {
                let v = [i % nx, (i / nx) % ny, i / (nx * ny)];
                index(&self.slots, self.dims, v).map_or(1.0, |j| super::stored::unpack(words[j]))
            })
            .collect())
    }
}

/// The one-word table of a V_AO stored whole ([`AO_WHOLE`]): what a precompute writes through.
pub fn whole_table(gpu: &Gpu) -> Result<Buffer> {
    Buffer::device_local(
        gpu,
        &[AO_WHOLE],
        vk::BufferUsageFlags::STORAGE_BUFFER,
        "ao-whole-table",
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    /// 20 x 9 x 17 voxels (3 x 2 x 3 bricks), V_PAO 1 everywhere, one opaque voxel.
    fn one_voxel(at: [usize; 3]) -> ([usize; 3], Vec<u8>, Vec<u8>) {
        let dims = [20, 9, 17];
        let n = dims.iter().product::<usize>();
        let mut o = vec![0u8; 2 * n];
        let i = at[0] + dims[0] * (at[1] + dims[1] * at[2]);
        o[2 * i] = 1;
        (dims, o, vec![0xFF; 2 * n])
    }

    #[test]
    fn a_brick_is_kept_within_reach_of_an_opaque_voxel_and_left_out_beyond() {
        let (dims, o, pao) = one_voxel([1, 1, 1]);
        let nb = bricks(dims);
        assert_eq!(nb, [3, 2, 3]);
        let kept = needed(dims, &o, 2, &pao, [0; 3]);
        assert_eq!(kept.iter().filter(|&&k| k).count(), 1, "{kept:?}");
        assert!(kept[0]);
        // Within 8 voxels: the next brick on each axis.
        let kept = needed(dims, &o, 2, &pao, [8, 0, 0]);
        assert_eq!(kept.iter().filter(|&&k| k).count(), 2);
        let kept = needed(dims, &o, 2, &pao, [9, 9, 9]);
        let at = |b: [usize; 3]| kept[b[0] + nb[0] * (b[1] + nb[1] * b[2])];
        assert!(at([2, 1, 2]) && at([1, 1, 1]));
        // A V_PAO below 1 keeps its brick, however far from anything opaque.
        let (dims, o, mut pao) = one_voxel([1, 1, 1]);
        let far = 19 + dims[0] * (8 + dims[1] * 16);
        pao[2 * far] = 0;
        let kept = needed(dims, &o, 2, &pao, [0; 3]);
        assert!(kept[0] && kept[2 + nb[0] * (1 + nb[1] * 2)]);
        assert_eq!(kept.iter().filter(|&&k| k).count(), 2);
        // f32 words: a positive density counts, a zero does not.
        let n = dims.iter().product::<usize>();
        let mut f = vec![0.0f32; n];
        f[5] = 0.25;
        let kept = needed(
            dims,
            bytemuck::cast_slice(&f),
            4,
            &vec![0xFF; 2 * n],
            [0; 3],
        );
        assert_eq!(kept.iter().filter(|&&k| k).count(), 1);
    }

    #[test]
    fn every_voxel_of_a_kept_brick_has_its_own_word() {
        let dims = [20, 9, 17];
        let nb = bricks(dims);
        let kept: Vec<bool> = (0..nb.iter().product::<usize>())
            .map(|b| b % 3 != 1)
            .collect();
        let slots = slots(&kept);
        let mut seen = std::collections::HashSet::new();
        for z in 0..dims[2] {
            for y in 0..dims[1] {
                for x in 0..dims[0] {
                    let b = (x / 8) + nb[0] * ((y / 8) + nb[1] * (z / 8));
                    match index(&slots, dims, [x, y, z]) {
                        Some(j) => {
                            assert!(kept[b]);
                            assert!(j < kept.iter().filter(|&&k| k).count() * BRICK_VOXELS);
                            assert!(seen.insert(j), "two voxels at word {j}");
                        }
                        None => assert!(!kept[b]),
                    }
                }
            }
        }
    }
}
