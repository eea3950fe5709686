//! cao-xr: stereo CT/MRI volume rendering with (Contextual) Ambient Occlusion on Vulkan.
//!
//! The frame as data: input -> scene -> one GPU command buffer (clip + mask, ambient update,
//! stereo views) -> outputs. See README.md and docs/design.md.

pub mod ao;
pub mod app;
pub mod clip;
#[doc(hidden)]
pub mod fuzzing;
pub mod gpu;
pub mod input;
pub mod light;
pub mod render;
pub mod rng;
pub mod scene;
pub mod shader_constants;
pub mod space;
pub mod volume;
pub mod xr;
