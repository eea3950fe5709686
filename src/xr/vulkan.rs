//! XR_KHR_vulkan_enable2: the renderer's Vulkan instance and device are created by the runtime
//! (xrCreateVulkanInstanceKHR / xrCreateVulkanDeviceKHR), which adds what its compositor needs
//! to the extensions and features the renderer asks for, and names the physical device that
//! drives the headset. [`Gpu::with_factory`](crate::gpu::Gpu::with_factory) does the rest.

use crate::gpu::{GpuError, VulkanFactory};
use ash::vk::{self, Handle};
use openxr as xr;

pub struct XrVulkanFactory<'a> {
    pub instance: &'a xr::Instance,
    pub system: xr::SystemId,
    /// vkGetInstanceProcAddr of the loader the instance came from, kept for the device.
    pub gipa: Option<vk::PFN_vkGetInstanceProcAddr>,
}

fn xr_err(what: &str, e: xr::sys::Result) -> GpuError {
    GpuError::Other(format!("OpenXR {what} failed: {e}"))
}

impl VulkanFactory for XrVulkanFactory<'_> {
    unsafe fn create_instance(
        &mut self,
        entry: &ash::Entry,
        info: &vk::InstanceCreateInfo<'_>,
    ) -> Result<ash::Instance, GpuError> {
        self.gipa = Some(entry.static_fn().get_instance_proc_addr);
        #[allow(clippy::missing_transmute_annotations)]
        let gipa = std::mem::transmute(entry.static_fn().get_instance_proc_addr);
        let raw = self
            .instance
            .create_vulkan_instance(self.system, gipa, info as *const _ as *const _)
            .map_err(|e| xr_err("xrCreateVulkanInstanceKHR", e))?
            .map_err(vk::Result::from_raw)?;
        Ok(ash::Instance::load(
            entry.static_fn(),
            vk::Instance::from_raw(raw as _),
        ))
    }

    unsafe fn physical_device(
        &mut self,
        instance: &ash::Instance,
    ) -> Result<Option<vk::PhysicalDevice>, GpuError> {
        let raw = self
            .instance
            .vulkan_graphics_device(self.system, instance.handle().as_raw() as _)
            .map_err(|e| xr_err("xrGetVulkanGraphicsDevice2KHR", e))?;
        Ok(Some(vk::PhysicalDevice::from_raw(raw as _)))
    }

    unsafe fn create_device(
        &mut self,
        instance: &ash::Instance,
        physical: vk::PhysicalDevice,
        info: &vk::DeviceCreateInfo<'_>,
    ) -> Result<ash::Device, GpuError> {
        let entry_gipa = self
            .gipa
            .ok_or_else(|| GpuError::Other("device before instance".into()))?;
        #[allow(clippy::missing_transmute_annotations)]
        let gipa = std::mem::transmute(entry_gipa);
        let raw = self
            .instance
            .create_vulkan_device(
                self.system,
                gipa,
                physical.as_raw() as _,
                info as *const _ as *const _,
            )
            .map_err(|e| xr_err("xrCreateVulkanDeviceKHR", e))?
            .map_err(vk::Result::from_raw)?;
        Ok(ash::Device::load(
            instance.fp_v1_0(),
            vk::Device::from_raw(raw as _),
        ))
    }
}
