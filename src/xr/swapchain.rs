//! The runtime's swapchains (one two-layer array for colour, one for depth when the runtime
//! takes XR_KHR_composition_layer_depth) and the copies that fill them at the end of a frame's
//! command buffer.

use super::{Result, XrError};
use crate::gpu::{cmd_blit_color, cmd_image_barrier};
use crate::render::StereoTarget;
use ash::vk::{self, Handle};
use openxr as xr;

/// The runtime's swapchain: one image array with a layer per eye.
pub struct Swapchain {
    pub handle: xr::Swapchain<xr::Vulkan>,
    pub images: Vec<vk::Image>,
    pub extent: (u32, u32),
    pub format: vk::Format,
}

pub fn create_swapchain(
    session: &xr::Session<xr::Vulkan>,
    extent: (u32, u32),
) -> Result<Swapchain> {
    let offered: Vec<vk::Format> = session
        .enumerate_swapchain_formats()?
        .into_iter()
        .map(|f| vk::Format::from_raw(f as i32))
        .collect();
    let format = [
        vk::Format::R8G8B8A8_UNORM,
        vk::Format::B8G8R8A8_UNORM,
        vk::Format::R8G8B8A8_SRGB,
        vk::Format::B8G8R8A8_SRGB,
    ]
    .into_iter()
    .find(|f| offered.contains(f))
    .ok_or_else(|| {
        XrError::Runtime(format!(
            "the runtime offers no 8-bit RGBA swapchain format (offered: {offered:?})"
        ))
    })?;
    two_layer_swapchain(
        session,
        format,
        xr::SwapchainUsageFlags::COLOR_ATTACHMENT,
        extent,
    )
}

/// A two-layer array swapchain (layer 0 = left eye) that the frame's copy writes into.
fn two_layer_swapchain(
    session: &xr::Session<xr::Vulkan>,
    format: vk::Format,
    attachment: xr::SwapchainUsageFlags,
    extent: (u32, u32),
) -> Result<Swapchain> {
    let handle = session.create_swapchain(&xr::SwapchainCreateInfo {
        create_flags: xr::SwapchainCreateFlags::EMPTY,
        usage_flags: xr::SwapchainUsageFlags::TRANSFER_DST | attachment,
        format: format.as_raw() as _,
        sample_count: 1,
        width: extent.0,
        height: extent.1,
        face_count: 1,
        array_size: 2,
        mip_count: 1,
    })?;
    let images = handle
        .enumerate_images()?
        .into_iter()
        .map(vk::Image::from_raw)
        .collect();
    Ok(Swapchain {
        handle,
        images,
        extent,
        format,
    })
}

/// The depth swapchain for XR_KHR_composition_layer_depth: two layers like the colour one, in
/// the renderer's own depth format so the eyes' depth goes over with a plain copy (a depth
/// image cannot be blitted into another format). None when the runtime does not offer it.
pub fn create_depth_swapchain(
    session: &xr::Session<xr::Vulkan>,
    extent: (u32, u32),
) -> Result<Option<Swapchain>> {
    let format = crate::render::DEPTH_FORMAT;
    let offered = session.enumerate_swapchain_formats()?;
    if !offered.contains(&(format.as_raw() as _)) {
        return Ok(None);
    }
    two_layer_swapchain(
        session,
        format,
        xr::SwapchainUsageFlags::DEPTH_STENCIL_ATTACHMENT,
        extent,
    )
    .map(Some)
}

/// The part of each swapchain image of size `(w, h)` a frame fills, from the top-left corner:
/// all of it, or under a render scale below 1 the same share of it as the target's drawn part.
pub fn layer_rect(src: &StereoTarget, (w, h): (u32, u32)) -> (u32, u32) {
    let (dw, dh) = src.drawn();
    let share = |d: u32, of: u32, n: u32| ((d as u64 * n as u64) / of as u64).max(1) as u32;
    (share(dw, src.width, w), share(dh, src.height, h))
}

/// Records the copy of both eyes (the stereo target's colour, in TRANSFER_SRC_OPTIMAL) into the
/// acquired swapchain image, one blit region for both layers. Under a render scale below 1 the
/// drawn part goes into the same part of the image, which the layer's image rectangle names
/// ([`layer_rect`]), and the compositor enlarges it.
///
/// # Safety
/// `cmd` is recording on `d`, `image` is the waited swapchain image.
pub unsafe fn record_blit(
    d: &ash::Device,
    cmd: vk::CommandBuffer,
    src: &StereoTarget,
    image: vk::Image,
    (w, h): (u32, u32),
) {
    let range = vk::ImageSubresourceRange::default()
        .aspect_mask(vk::ImageAspectFlags::COLOR)
        .level_count(1)
        .layer_count(2);
    // The runtime hands images over in COLOR_ATTACHMENT_OPTIMAL and wants them back so
    // (XR_KHR_vulkan_enable); the old contents are not needed.
    cmd_image_barrier(
        d,
        cmd,
        image,
        range,
        vk::ImageLayout::UNDEFINED,
        vk::ImageLayout::TRANSFER_DST_OPTIMAL,
    );
    let (rw, rh) = layer_rect(src, (w, h));
    let rect = [(0, 0), (rw as i32, rh as i32)];
    cmd_blit_color(d, cmd, src.color.raw, (0, 2), src.drawn(), image, rect);
    cmd_image_barrier(
        d,
        cmd,
        image,
        range,
        vk::ImageLayout::TRANSFER_DST_OPTIMAL,
        vk::ImageLayout::COLOR_ATTACHMENT_OPTIMAL,
    );
}

/// Records the copy of both eyes' depth (the stereo target's, D32_SFLOAT in TRANSFER_SRC_OPTIMAL)
/// into the acquired depth swapchain image, which goes back to the runtime in
/// DEPTH_STENCIL_ATTACHMENT_OPTIMAL (XR_KHR_vulkan_enable).
///
/// # Safety
/// `cmd` is recording on `d`, `image` is the waited depth swapchain image.
pub unsafe fn record_depth_copy(
    d: &ash::Device,
    cmd: vk::CommandBuffer,
    src: &StereoTarget,
    image: vk::Image,
    (w, h): (u32, u32),
) {
    let range = vk::ImageSubresourceRange::default()
        .aspect_mask(vk::ImageAspectFlags::DEPTH)
        .level_count(1)
        .layer_count(2);
    cmd_image_barrier(
        d,
        cmd,
        image,
        range,
        vk::ImageLayout::UNDEFINED,
        vk::ImageLayout::TRANSFER_DST_OPTIMAL,
    );
    let layers = vk::ImageSubresourceLayers::default()
        .aspect_mask(vk::ImageAspectFlags::DEPTH)
        .layer_count(2);
    let region = [vk::ImageCopy::default()
        .src_subresource(layers)
        .dst_subresource(layers)
        .extent({
            let ((rw, rh), (dw, dh)) = (layer_rect(src, (w, h)), src.drawn());
            vk::Extent3D {
                width: rw.min(dw),
                height: rh.min(dh),
                depth: 1,
            }
        })];
    d.cmd_copy_image(
        cmd,
        src.depth.raw,
        vk::ImageLayout::TRANSFER_SRC_OPTIMAL,
        image,
        vk::ImageLayout::TRANSFER_DST_OPTIMAL,
        &region,
    );
    cmd_image_barrier(
        d,
        cmd,
        image,
        range,
        vk::ImageLayout::TRANSFER_DST_OPTIMAL,
        vk::ImageLayout::DEPTH_STENCIL_ATTACHMENT_OPTIMAL,
    );
}
