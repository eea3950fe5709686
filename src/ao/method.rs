//! The AO method behind CAO (docs/design.md, "AO methods"): what every method's passes read and
//! write, by role.

use crate::gpu::Buffer;

/// The volumes a method's pass over voxel boxes reads and writes, by role. Where a pass reads
/// no mask or no V_PAO (a precompute), any buffer stands in.
#[derive(Clone, Copy)]
pub struct MethodBuffers<'a> {
    /// The density the method reads: O_c (laid out by [`super::cao::Cao::clipped_stride`]), or
    /// for a precompute the unclipped O (for the local histograms q, for the filters their
    /// density).
    pub density: &'a Buffer,
    /// CAO's voxel categories (shaders/include/mask.glsl).
    pub mask: &'a Buffer,
    /// V_PAO: the method's AO of the unclipped volume.
    pub pre_a: &'a Buffer,
    /// Where the pass writes its AO: V_AO, or V_PAO for a precompute.
    pub out_a: &'a Buffer,
}

impl<'a> MethodBuffers<'a> {
    /// A precompute's roles: `density` read, `out` written, nothing else read.
    pub fn precompute(density: &'a Buffer, out: &'a Buffer) -> MethodBuffers<'a> {
        MethodBuffers {
            density,
            mask: density,
            pre_a: out,
            out_a: out,
        }
    }
}
