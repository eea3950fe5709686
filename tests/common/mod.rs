//! Shared by the GPU tests: a validated Vulkan context, and a check that it stayed silent.
#![allow(dead_code)]

use cao_xr::gpu::{Gpu, GpuOptions};

/// A Vulkan context with the Khronos validation layer on (required: a missing layer fails).
pub fn gpu() -> Gpu {
    let opts = GpuOptions {
        present: false,
        validation: true,
        device_name: None,
    };
    Gpu::new(&opts)
        .expect("Vulkan with validation (install mesa-vulkan-drivers and vulkan-validationlayers)")
}

/// Fails the test if validation reported any warning or error.
pub fn assert_no_validation_messages(gpu: &Gpu) {
    let m = gpu.validation_messages();
    assert!(
        m.is_empty(),
        "{} validation message(s):\n{}",
        m.len(),
        m.join("\n")
    );
}
