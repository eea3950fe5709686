//! Ambient occlusion: LAO directions and parameters, the GPU precompute, and a CPU reference.

pub mod cao;
pub mod cpu;
pub mod lao;
pub mod progressive;
pub mod sh;

pub use lao::{directions, LaoGpu, LaoParams};
