//! Every integration test in one binary, a module per topic: each test binary links the whole
//! crate, so one binary instead of thirteen saves most of the suite's link time. The GPU tests
//! run on lavapipe with the Khronos validation layer on (`common::gpu`).

mod common;

mod cao;
mod cli;
mod clip_gpu;
mod desktop;
mod dicom;
mod filtered;
mod foreign;
mod gpu_memory;
mod histogram;
mod inset;
mod labels;
mod lao;
mod large;
mod overlay;
mod render;
mod sh;
mod sh_lighting;
mod shading;
mod soak;
mod tf_switch;
mod xr;
