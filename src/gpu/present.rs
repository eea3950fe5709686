//! The window's presenter: an X11 surface and its swapchain, onto which one eye or both eyes of
//! a finished stereo target are blitted and presented (the desktop window and the headset's
//! mirror window both use it).

use super::{cmd_blit_color, cmd_image_barrier, Buffer, Gpu, GpuError, Result};
use ash::vk;
use winit::raw_window_handle::{
    HasDisplayHandle, HasWindowHandle, RawDisplayHandle, RawWindowHandle,
};
use winit::window::Window;

/// What the window showed: RGB rows, top down.
pub struct Screenshot {
    pub width: u32,
    pub height: u32,
    pub rgb: Vec<u8>,
}

/// Window surface and swapchain; destroyed before the device goes. Shared by the desktop
/// window and the headset's mirror.
pub struct Presenter {
    gpu: Gpu,
    surface_fn: ash::khr::surface::Instance,
    swapchain_fn: ash::khr::swapchain::Device,
    surface: vk::SurfaceKHR,
    swapchain: vk::SwapchainKHR,
    images: Vec<vk::Image>,
    format: vk::Format,
    extent: vk::Extent2D,
    fence: vk::Fence,
    /// Per swapchain image: signalled by the submission that blits into it, waited by its
    /// present. Reusable once the image is acquired again (its present has waited by then).
    rendered: Vec<vk::Semaphore>,
}

/// A swapchain image acquired for the next frame ([`Presenter::acquire`]).
pub struct Acquired {
    index: u32,
    /// The submission that blits into the image signals it; [`Presenter::queue_present`]
    /// waits on it.
    pub rendered: vk::Semaphore,
}

impl Presenter {
    /// # Safety
    /// `window` outlives the presenter, and `gpu` was created with [`super::GpuOptions::present`].
    pub unsafe fn new(gpu: &Gpu, window: &Window) -> Result<Presenter> {
        let err = |m: &str| GpuError::Other(m.to_string());
        let (RawWindowHandle::Xlib(w), RawDisplayHandle::Xlib(d)) = (
            window
                .window_handle()
                .map_err(|e| err(&e.to_string()))?
                .as_raw(),
            window
                .display_handle()
                .map_err(|e| err(&e.to_string()))?
                .as_raw(),
        ) else {
            return Err(err(
                "the desktop window needs X11 (set DISPLAY; Wayland is not supported)",
            ));
        };
        let display = d.display.ok_or_else(|| err("no X11 display"))?.as_ptr();
        let xlib = ash::khr::xlib_surface::Instance::new(&gpu.entry, &gpu.instance);
        let info = vk::XlibSurfaceCreateInfoKHR::default()
            .dpy(display as *mut vk::Display)
            .window(w.window as vk::Window);
        let surface = xlib
            .create_xlib_surface(&info, None)
            .map_err(GpuError::from)?;
        let surface_fn = ash::khr::surface::Instance::new(&gpu.entry, &gpu.instance);
        if !surface_fn
            .get_physical_device_surface_support(gpu.physical, gpu.queue_family, surface)
            .map_err(GpuError::from)?
        {
            surface_fn.destroy_surface(surface, None);
            return Err(err("the GPU's queue cannot present to this window"));
        }
        let swapchain_fn = ash::khr::swapchain::Device::new(&gpu.instance, &gpu.device);
        let fence = gpu
            .device
            .create_fence(&vk::FenceCreateInfo::default(), None)
            .map_err(GpuError::from)?;
        let mut p = Presenter {
            gpu: gpu.clone(),
            surface_fn,
            swapchain_fn,
            surface,
            swapchain: vk::SwapchainKHR::null(),
            images: Vec::new(),
            format: vk::Format::UNDEFINED,
            extent: vk::Extent2D::default(),
            fence,
            rendered: Vec::new(),
        };
        let size = window.inner_size();
        p.recreate(size.width, size.height)?;
        Ok(p)
    }

    /// A new swapchain for the window's new size (the old one is retired).
    ///
    /// # Safety
    /// No submitted work still uses the old swapchain's images (it waits for the device idle).
    pub unsafe fn recreate(&mut self, width: u32, height: u32) -> Result<()> {
        let _ = self.gpu.device.device_wait_idle();
        let caps = self
            .surface_fn
            .get_physical_device_surface_capabilities(self.gpu.physical, self.surface)
            .map_err(GpuError::from)?;
        let formats = self
            .surface_fn
            .get_physical_device_surface_formats(self.gpu.physical, self.surface)
            .map_err(GpuError::from)?;
        let format = formats
            .iter()
            .find(|f| {
                matches!(
                    f.format,
                    vk::Format::B8G8R8A8_UNORM | vk::Format::R8G8B8A8_UNORM
                )
            })
            .or(formats.first())
            .copied()
            .ok_or_else(|| GpuError::Other("the window offers no surface format".into()))?;
        let extent = if caps.current_extent.width != u32::MAX {
            caps.current_extent
        } else {
            vk::Extent2D {
                width: width.clamp(caps.min_image_extent.width, caps.max_image_extent.width),
                height: height.clamp(caps.min_image_extent.height, caps.max_image_extent.height),
            }
        };
        let count = if caps.max_image_count > 0 {
            (caps.min_image_count + 1).min(caps.max_image_count)
        } else {
            caps.min_image_count + 1
        };
        let old = self.swapchain;
        let info = vk::SwapchainCreateInfoKHR::default()
            .surface(self.surface)
            .min_image_count(count)
            .image_format(format.format)
            .image_color_space(format.color_space)
            .image_extent(extent)
            .image_array_layers(1)
            .image_usage(vk::ImageUsageFlags::TRANSFER_DST | vk::ImageUsageFlags::TRANSFER_SRC)
            .image_sharing_mode(vk::SharingMode::EXCLUSIVE)
            .pre_transform(caps.current_transform)
            .composite_alpha(vk::CompositeAlphaFlagsKHR::OPAQUE)
            .present_mode(vk::PresentModeKHR::FIFO)
            .clipped(true)
            .old_swapchain(old);
        self.swapchain = self
            .swapchain_fn
            .create_swapchain(&info, None)
            .map_err(GpuError::from)?;
        if old != vk::SwapchainKHR::null() {
            self.swapchain_fn.destroy_swapchain(old, None);
        }
        self.images = self
            .swapchain_fn
            .get_swapchain_images(self.swapchain)
            .map_err(GpuError::from)?;
        for s in self.rendered.drain(..) {
            self.gpu.device.destroy_semaphore(s, None);
        }
        for _ in &self.images {
            let s = self
                .gpu
                .device
                .create_semaphore(&vk::SemaphoreCreateInfo::default(), None)
                .map_err(GpuError::from)?;
            self.rendered.push(s);
        }
        self.format = format.format;
        self.extent = extent;
        Ok(())
    }

    /// Waits for the next swapchain image. None when the swapchain was out of date and has
    /// been recreated (nothing to present this time).
    ///
    /// # Safety
    /// As for [`Presenter::recreate`], which it may call.
    pub unsafe fn acquire(&mut self) -> Result<Option<Acquired>> {
        let d = &self.gpu.device;
        let index = match self.swapchain_fn.acquire_next_image(
            self.swapchain,
            u64::MAX,
            vk::Semaphore::null(),
            self.fence,
        ) {
            Ok((index, _)) => index,
            Err(vk::Result::ERROR_OUT_OF_DATE_KHR) => {
                self.recreate(self.extent.width, self.extent.height)?;
                return Ok(None);
            }
            Err(e) => return Err(GpuError::from(e)),
        };
        self.gpu.wait_fences(&[self.fence])?;
        d.reset_fences(&[self.fence]).map_err(GpuError::from)?;
        Ok(Some(Acquired {
            index,
            rendered: self.rendered[index as usize],
        }))
    }

    /// Records the blit of one eye (or both side by side) of `src`, a two-layer colour image
    /// in TRANSFER_SRC_OPTIMAL (the stereo target), into the acquired image, leaving it ready
    /// to present (or, with `capture`, copied into `capture` first).
    ///
    /// # Safety
    /// `cmd` is recording; `src` is a live image of this device, `src_w` x `src_h` with two
    /// layers, in TRANSFER_SRC_OPTIMAL when `cmd` reaches the blit.
    pub unsafe fn record_blit(
        &self,
        cmd: vk::CommandBuffer,
        target: &Acquired,
        src: vk::Image,
        (src_w, src_h): (u32, u32),
        both: bool,
        capture: Option<&Buffer>,
    ) {
        let d = &self.gpu.device;
        let image = self.images[target.index as usize];
        let range = vk::ImageSubresourceRange::default()
            .aspect_mask(vk::ImageAspectFlags::COLOR)
            .level_count(1)
            .layer_count(1);
        let (w, h) = (self.extent.width as i32, self.extent.height as i32);
        cmd_image_barrier(
            d,
            cmd,
            image,
            range,
            vk::ImageLayout::UNDEFINED,
            vk::ImageLayout::TRANSFER_DST_OPTIMAL,
        );
        let eyes = if both { 2 } else { 1 };
        for eye in 0..eyes {
            let x0 = w * eye / eyes;
            let x1 = w * (eye + 1) / eyes;
            let rect = [(x0, 0), (x1, h)];
            cmd_blit_color(d, cmd, src, (eye as u32, 1), (src_w, src_h), image, rect);
        }
        let mut last = vk::ImageLayout::TRANSFER_DST_OPTIMAL;
        if let Some(buf) = capture {
            cmd_image_barrier(
                d,
                cmd,
                image,
                range,
                last,
                vk::ImageLayout::TRANSFER_SRC_OPTIMAL,
            );
            let region = [vk::BufferImageCopy::default()
                .image_subresource(
                    vk::ImageSubresourceLayers::default()
                        .aspect_mask(vk::ImageAspectFlags::COLOR)
                        .layer_count(1),
                )
                .image_extent(vk::Extent3D {
                    width: w as u32,
                    height: h as u32,
                    depth: 1,
                })];
            d.cmd_copy_image_to_buffer(
                cmd,
                image,
                vk::ImageLayout::TRANSFER_SRC_OPTIMAL,
                buf.raw,
                &region,
            );
            last = vk::ImageLayout::TRANSFER_SRC_OPTIMAL;
        }
        cmd_image_barrier(d, cmd, image, range, last, vk::ImageLayout::PRESENT_SRC_KHR);
    }

    /// Presents the acquired image once the submission that blitted into it has signalled
    /// `target.rendered` (`wait`), or at once when the host already waited for it.
    ///
    /// # Safety
    /// With `wait`, a submitted (or about to be submitted, in queue order) command buffer
    /// signals `target.rendered`.
    pub unsafe fn queue_present(&mut self, target: Acquired, wait: bool) -> Result<()> {
        let swapchains = [self.swapchain];
        let indices = [target.index];
        let waits = [target.rendered];
        let mut info = vk::PresentInfoKHR::default()
            .swapchains(&swapchains)
            .image_indices(&indices);
        if wait {
            info = info.wait_semaphores(&waits);
        }
        let presented = {
            let _queue = self.gpu.queue_guard();
            self.swapchain_fn.queue_present(self.gpu.queue, &info)
        };
        match presented {
            Ok(_) | Err(vk::Result::ERROR_OUT_OF_DATE_KHR) | Err(vk::Result::SUBOPTIMAL_KHR) => {
                Ok(())
            }
            Err(e) => Err(GpuError::from(e)),
        }
    }

    /// Blits one eye (or both side by side) of `src` (as [`Presenter::record_blit`]) to the
    /// window in a submission of its own, waits for it and presents; with `capture`, also
    /// returns the presented pixels as RGB.
    ///
    /// # Safety
    /// `src` is a live image of this device, `src_w` x `src_h` with two layers, in
    /// TRANSFER_SRC_OPTIMAL, and no other work writes it meanwhile.
    pub unsafe fn present(
        &mut self,
        src: vk::Image,
        src_size: (u32, u32),
        both: bool,
        capture: bool,
    ) -> Result<Option<Screenshot>> {
        let Some(target) = self.acquire()? else {
            return Ok(None);
        };
        let (w, h) = (self.extent.width, self.extent.height);
        let readback = if capture {
            Some(Buffer::new(
                &self.gpu,
                w as u64 * h as u64 * 4,
                vk::BufferUsageFlags::TRANSFER_DST,
                gpu_allocator::MemoryLocation::GpuToCpu,
                "screenshot",
            )?)
        } else {
            None
        };
        let gpu = self.gpu.clone();
        gpu.submit_and_wait(|cmd| {
            self.record_blit(cmd, &target, src, src_size, both, readback.as_ref())
        })?;
        self.queue_present(target, false)?;
        let Some(buf) = readback else { return Ok(None) };
        let bgra =
            self.format == vk::Format::B8G8R8A8_UNORM || self.format == vk::Format::B8G8R8A8_SRGB;
        let px = buf.mapped()?;
        let rgb = px
            .chunks_exact(4)
            .flat_map(|p| {
                if bgra {
                    [p[2], p[1], p[0]]
                } else {
                    [p[0], p[1], p[2]]
                }
            })
            .collect();
        Ok(Some(Screenshot {
            width: w,
            height: h,
            rgb,
        }))
    }
}

impl Drop for Presenter {
    fn drop(&mut self) {
        // SAFETY: the idle wait ends every submission that blits into the swapchain or signals its
        // semaphores; fence, semaphores, swapchain and surface are this presenter's own, destroyed
        // once, the swapchain before its surface, while the window still exists (Presenter::new's
        // contract).
        unsafe {
            let _ = self.gpu.device.device_wait_idle();
            self.gpu.device.destroy_fence(self.fence, None);
            for s in &self.rendered {
                self.gpu.device.destroy_semaphore(*s, None);
            }
            self.swapchain_fn.destroy_swapchain(self.swapchain, None);
            self.surface_fn.destroy_surface(self.surface, None);
        }
    }
}
