//! Vulkan context: instance, validation messenger, device choice, queue, allocator, one-shot
//! submissions and the small resource types (buffers, images, pipelines, timers) every pass uses.

pub mod pipeline;
pub mod present;
mod resources;
mod slabs;
mod timer;

pub use resources::{
    address_bytes, cmd_blit_color, cmd_image_barrier, push_set_layout, shader_module,
    sparse_set_layout, specialization_entries, Buffer, ComputePipeline, Image, ImageDesc, Reach,
};
pub use slabs::{SlabBuffer, MAX_BUFFER_ENV};
pub use timer::GpuTimer;

/// The most frames the frame loop keeps on the GPU at once (`--frames-in-flight`): the slots
/// of every resource a frame writes from the host or reads back (command buffers, fences,
/// timers, uniform buffers, CAO's tool table, clip maps and counters).
pub const MAX_FRAMES_IN_FLIGHT: usize = 2;

use ash::vk;
use gpu_allocator::vulkan::{Allocator, AllocatorCreateDesc};
use std::ffi::{c_void, CStr, CString};
use std::mem::ManuallyDrop;
use std::sync::{Arc, Mutex};

#[derive(Debug, thiserror::Error)]
pub enum GpuError {
    #[error("cannot load the Vulkan library (install libvulkan1 and a driver, e.g. mesa-vulkan-drivers): {0}")]
    Loader(#[from] ash::LoadingError),
    #[error("Vulkan call failed: {0}")]
    Vk(vk::Result),
    #[error("GPU memory allocation failed: {0}")]
    Alloc(#[from] gpu_allocator::AllocationError),
    #[error("{0}")]
    OutOfMemory(Box<OutOfMemory>),
    #[error("no usable Vulkan 1.3 device: {0}")]
    NoDevice(String),
    #[error("Vulkan validation layer VK_LAYER_KHRONOS_validation was asked for but is not installed (apt-get install vulkan-validationlayers)")]
    NoValidationLayer,
    #[error(
        "the GPU stopped answering: work submitted to it had not finished after {0:.1} s \
         (a hung or overloaded device; {GPU_TIMEOUT_ENV} sets the bound in seconds)"
    )]
    Stalled(f64),
    #[error(
        "the GPU device was lost (VK_ERROR_DEVICE_LOST: the driver reset it after a hang or \
         fault, or it was removed); restart cao-xr"
    )]
    DeviceLost,
    #[error("{0}")]
    Other(String),
}

pub type Result<T> = std::result::Result<T, GpuError>;

impl From<vk::Result> for GpuError {
    /// A lost device is told as such, whichever call noticed it.
    fn from(e: vk::Result) -> Self {
        match e {
            vk::Result::ERROR_DEVICE_LOST => GpuError::DeviceLost,
            e => GpuError::Vk(e),
        }
    }
}

/// Seconds a wait for the GPU may last before it is reported as [`GpuError::Stalled`]
/// (`Gpu::wait_fences`); unset: 60 s on a GPU (drivers reset a hung GPU well within), 30 min on
/// a CPU device (where one submission of a large volume's precompute takes minutes).
pub const GPU_TIMEOUT_ENV: &str = "CAO_XR_GPU_TIMEOUT_S";

/// Caps the GPU memory handed out through [`Buffer`] and [`Image`] at this many MiB, as if
/// other programs (or a smaller card) left only that much: simulates memory exhaustion.
pub const BUDGET_ENV: &str = "CAO_XR_GPU_BUDGET_MB";

/// An allocation the GPU (or the budget) could not hold, and what was in use when it failed.
#[derive(Debug, Clone)]
pub struct OutOfMemory {
    /// The buffer or image asked for.
    pub what: String,
    pub bytes: u64,
    /// Bytes held through Buffer and Image when it failed.
    pub in_use: u64,
    /// The sizes of the allocations held then.
    pub held: Vec<u64>,
    /// The budget, or the device-local heap.
    pub available: u64,
    /// Whether `available` is the [`BUDGET_ENV`] budget.
    pub budget: bool,
}

impl std::fmt::Display for OutOfMemory {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let mib = |b: u64| b as f64 / (1u64 << 20) as f64;
        write!(
            f,
            "out of GPU memory: {} needs {:.1} MiB while {:.1} MiB of the {:.1} MiB {} are in use",
            self.what,
            mib(self.bytes),
            mib(self.in_use),
            mib(self.available),
            if self.budget {
                "budget (CAO_XR_GPU_BUDGET_MB)"
            } else {
                "device-local heap"
            }
        )
    }
}

/// A size from environment variable `name`, a whole number of units (`unit`, 2^`shift` bytes)
/// above 0; None where it is unset.
fn env_bytes(name: &str, shift: u32, unit: &str) -> Result<Option<u64>> {
    let Ok(v) = std::env::var(name) else {
        return Ok(None);
    };
    match v.trim().parse::<u64>() {
        Ok(n) if n > 0 && n < 1 << 40 => Ok(Some(n << shift)),
        _ => Err(GpuError::Other(format!(
            "{name}={v}: expected a whole number of {unit} above 0"
        ))),
    }
}

/// Forces the z-slices of scratch volumes computed at once (the filters' box statistics; at
/// least the volume's: whole), to compare chunked and whole passes in a benchmark.
pub const SCRATCH_SLICES_ENV: &str = "CAO_XR_SCRATCH_SLICES";

/// The host's physical memory (`MemTotal` of /proc/meminfo), where the system says.
pub fn host_memory_bytes() -> Option<u64> {
    let info = std::fs::read_to_string("/proc/meminfo").ok()?;
    parse_mem_total(&info)
}

fn parse_mem_total(meminfo: &str) -> Option<u64> {
    let line = meminfo.lines().find(|l| l.starts_with("MemTotal:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib << 10)
}

/// GPU memory held through Buffer and Image: allocation id -> bytes.
#[derive(Default)]
struct MemoryUse {
    next: u64,
    held: std::collections::BTreeMap<u64, u64>,
    total: u64,
    /// The most `total` has been since `reset_memory_peak`.
    peak: u64,
    /// The most `total` has been since the device was opened.
    session_peak: u64,
    /// The [`BUDGET_ENV`] cap, in bytes.
    budget: Option<u64>,
}

impl MemoryUse {
    /// Refuses `bytes` more for `what` beyond the budget.
    fn room(&self, what: &str, bytes: u64) -> Result<()> {
        match self.budget {
            Some(budget) if self.total + bytes > budget => {
                Err(GpuError::OutOfMemory(Box::new(OutOfMemory {
                    what: what.to_string(),
                    bytes,
                    in_use: self.total,
                    held: self.held.values().copied().collect(),
                    available: budget,
                    budget: true,
                })))
            }
            _ => Ok(()),
        }
    }
}

/// Fails the build unless a `#[repr(C)]` struct that a shader reads has the size and field
/// offsets of its GLSL block (std140 for uniform blocks, std430 for push constants and storage
/// buffers), written next to the struct from the GLSL declaration:
/// `glsl_layout!(Push, 36, dims: 0, rays: 16, steps: 20);` (in a pass that reaches buffers by
/// address, offsets count from the end of the addresses: [`address_bytes`]).
macro_rules! glsl_layout {
    ($t:ty, $size:expr, $($field:ident: $offset:expr),+ $(,)?) => {
        const _: () = {
            assert!(std::mem::size_of::<$t>() == $size, "size differs from the GLSL block");
            $(assert!(
                std::mem::offset_of!($t, $field) == $offset,
                concat!("offset of ", stringify!($field), " differs from the GLSL block")
            );)+
        };
    };
}
pub(crate) use glsl_layout;

/// How to create the context.
#[derive(Clone, Debug)]
pub struct GpuOptions {
    /// Khronos validation with a messenger that records every warning and error.
    pub validation: bool,
    /// Pick the first device whose name contains this (case-insensitive).
    pub device_name: Option<String>,
    /// Enable presenting to X11 windows (VK_KHR_surface, xlib surface, swapchain).
    pub present: bool,
}

impl Default for GpuOptions {
    fn default() -> Self {
        let env_on = std::env::var("CAO_XR_VALIDATION").map(|v| v != "0");
        Self {
            validation: env_on.unwrap_or(cfg!(debug_assertions)),
            device_name: std::env::var("CAO_XR_DEVICE").ok(),
            present: false,
        }
    }
}

/// The shared Vulkan context. Cheap to clone; resources keep it alive until they are dropped.
#[derive(Clone)]
pub struct Gpu(Arc<Core>);

impl std::ops::Deref for Gpu {
    type Target = Core;
    fn deref(&self) -> &Core {
        &self.0
    }
}

pub struct Core {
    pub entry: ash::Entry,
    pub instance: ash::Instance,
    debug: Option<(ash::ext::debug_utils::Instance, vk::DebugUtilsMessengerEXT)>,
    log: Arc<ValidationLog>,
    pub physical: vk::PhysicalDevice,
    pub device: ash::Device,
    pub push_descriptor: ash::khr::push_descriptor::Device,
    /// The one queue. Vulkan wants its use externally synchronised: submit through
    /// [`Core::submit`], and hold [`Core::queue_guard`] around anything else that may use it
    /// (a present, an OpenXR runtime's swapchain calls).
    pub queue: vk::Queue,
    queue_lock: Mutex<()>,
    pub queue_family: u32,
    pub allocator: Mutex<ManuallyDrop<Allocator>>,
    cmd_pool: Mutex<vk::CommandPool>,
    memory: Mutex<MemoryUse>,
    /// The largest slab of a [`SlabBuffer`] ([`MAX_BUFFER_ENV`], or less for a test); 0: the
    /// device's largest buffer.
    slab_limit: std::sync::atomic::AtomicU64,
    /// Z-slices of scratch volumes computed at once (the filters' box statistics), forced by
    /// [`SCRATCH_SLICES_ENV`] or a test; 0: each method's own choice.
    scratch_slices: std::sync::atomic::AtomicU64,
    pub device_name: String,
    pub device_type: vk::PhysicalDeviceType,
    /// Whether the context can present to windows (GpuOptions::present).
    pub present: bool,
    /// Nanoseconds per timestamp tick.
    pub timestamp_period: f32,
    pub limits: vk::PhysicalDeviceLimits,
    /// Whether fragment shaders may write storage (fragmentStoresAndAtomics): the first eye's
    /// record that the second eye reprojects ([`crate::render::RenderSettings::reproject`]).
    pub fragment_stores: bool,
}

/// What [`Core::memory_in_use`] reports.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct GpuMemory {
    /// Bytes held by live allocations.
    pub allocated_bytes: u64,
    /// Bytes of the memory blocks the allocator holds (allocated or not).
    pub capacity_bytes: u64,
    /// Live allocations.
    pub allocations: usize,
}

/// Every validation warning and error seen by the messenger, in order.
#[derive(Default)]
pub struct ValidationLog {
    messages: Mutex<Vec<String>>,
}

unsafe extern "system" fn debug_callback(
    severity: vk::DebugUtilsMessageSeverityFlagsEXT,
    _types: vk::DebugUtilsMessageTypeFlagsEXT,
    data: *const vk::DebugUtilsMessengerCallbackDataEXT<'_>,
    user: *mut c_void,
) -> vk::Bool32 {
    let msg = if data.is_null() || (*data).p_message.is_null() {
        "(no message)".to_string()
    } else {
        CStr::from_ptr((*data).p_message)
            .to_string_lossy()
            .into_owned()
    };
    let line = format!("[{severity:?}] {msg}");
    eprintln!("vulkan validation: {line}");
    if !user.is_null() {
        let log = &*(user as *const ValidationLog);
        if let Ok(mut m) = log.messages.lock() {
            m.push(line);
        }
    }
    vk::FALSE
}

const VALIDATION_LAYER: &CStr = c"VK_LAYER_KHRONOS_validation";

/// Who creates the Vulkan instance and device. [`Gpu::new`] creates them itself; an OpenXR
/// session must have them created through the runtime (XR_KHR_vulkan_enable2:
/// xrCreateVulkanInstanceKHR / xrCreateVulkanDeviceKHR), which adds the extensions the compositor
/// needs and picks the physical device that drives the headset. [`Gpu::with_factory`] takes such
/// a factory; everything else (layers, messenger, features, queue, allocator) stays the same.
pub trait VulkanFactory {
    /// Creates the instance from the info the renderer wants (layers, extensions, API version).
    ///
    /// # Safety
    /// `info` must be valid; the returned instance must have been created from it.
    unsafe fn create_instance(
        &mut self,
        entry: &ash::Entry,
        info: &vk::InstanceCreateInfo<'_>,
    ) -> Result<ash::Instance>;

    /// The physical device to use, or `None` to let [`Gpu`] pick one by its usual rules.
    ///
    /// # Safety
    /// `instance` must be the one this factory created.
    unsafe fn physical_device(
        &mut self,
        instance: &ash::Instance,
    ) -> Result<Option<vk::PhysicalDevice>>;

    /// Creates the device from the info the renderer wants (queue, extensions, features).
    ///
    /// # Safety
    /// `info` must be valid for `physical`.
    unsafe fn create_device(
        &mut self,
        instance: &ash::Instance,
        physical: vk::PhysicalDevice,
        info: &vk::DeviceCreateInfo<'_>,
    ) -> Result<ash::Device>;
}

/// Plain Vulkan: the instance and device are created directly.
struct DirectFactory;

impl VulkanFactory for DirectFactory {
    unsafe fn create_instance(
        &mut self,
        entry: &ash::Entry,
        info: &vk::InstanceCreateInfo<'_>,
    ) -> Result<ash::Instance> {
        Ok(entry.create_instance(info, None)?)
    }
    unsafe fn physical_device(&mut self, _: &ash::Instance) -> Result<Option<vk::PhysicalDevice>> {
        Ok(None)
    }
    unsafe fn create_device(
        &mut self,
        instance: &ash::Instance,
        physical: vk::PhysicalDevice,
        info: &vk::DeviceCreateInfo<'_>,
    ) -> Result<ash::Device> {
        Ok(instance.create_device(physical, info, None)?)
    }
}

impl Gpu {
    pub fn new(opts: &GpuOptions) -> Result<Gpu> {
        // SAFETY: DirectFactory creates the instance and device from exactly the infos `create`
        // hands it, which is all `create` asks of a factory.
        unsafe { Self::create(opts, &mut DirectFactory) }
    }

    /// Like [`Gpu::new`], but the instance and device come from `factory` (the OpenXR path).
    ///
    /// # Safety
    /// The factory must honour the create infos it is given.
    pub unsafe fn with_factory(opts: &GpuOptions, factory: &mut dyn VulkanFactory) -> Result<Gpu> {
        Self::create(opts, factory)
    }

    unsafe fn create(opts: &GpuOptions, factory: &mut dyn VulkanFactory) -> Result<Gpu> {
        let slab_limit = env_bytes(MAX_BUFFER_ENV, 10, "KiB")?.unwrap_or(0);
        let scratch_slices = env_bytes(SCRATCH_SLICES_ENV, 0, "slices")?.unwrap_or(0);
        let budget = env_bytes(BUDGET_ENV, 20, "MiB")?;
        let entry = ash::Entry::load()?;
        let log = Arc::new(ValidationLog::default());

        let mut layers: Vec<*const i8> = Vec::new();
        let mut exts: Vec<*const i8> = Vec::new();
        if opts.validation {
            let available = entry.enumerate_instance_layer_properties()?;
            if !available
                .iter()
                .any(|l| l.layer_name_as_c_str() == Ok(VALIDATION_LAYER))
            {
                return Err(GpuError::NoValidationLayer);
            }
            layers.push(VALIDATION_LAYER.as_ptr());
            exts.push(ash::ext::debug_utils::NAME.as_ptr());
        }
        if opts.present {
            exts.push(ash::khr::surface::NAME.as_ptr());
            exts.push(ash::khr::xlib_surface::NAME.as_ptr());
        }
        let severity = vk::DebugUtilsMessageSeverityFlagsEXT::WARNING
            | vk::DebugUtilsMessageSeverityFlagsEXT::ERROR;
        let types = vk::DebugUtilsMessageTypeFlagsEXT::GENERAL
            | vk::DebugUtilsMessageTypeFlagsEXT::VALIDATION
            | vk::DebugUtilsMessageTypeFlagsEXT::PERFORMANCE;
        let mut messenger_info = vk::DebugUtilsMessengerCreateInfoEXT::default()
            .message_severity(severity)
            .message_type(types)
            .pfn_user_callback(Some(debug_callback))
            .user_data(Arc::as_ptr(&log) as *mut c_void);

        let app_name = CString::new("cao-xr").unwrap();
        let app = vk::ApplicationInfo::default()
            .application_name(&app_name)
            .engine_name(&app_name)
            .api_version(vk::API_VERSION_1_3);
        let mut info = vk::InstanceCreateInfo::default()
            .application_info(&app)
            .enabled_layer_names(&layers)
            .enabled_extension_names(&exts);
        if opts.validation {
            // Chained so instance creation and destruction are validated too.
            info = info.push_next(&mut messenger_info);
        }
        let instance = factory.create_instance(&entry, &info)?;
        let debug = if opts.validation {
            let du = ash::ext::debug_utils::Instance::new(&entry, &instance);
            let m = du.create_debug_utils_messenger(&messenger_info, None)?;
            Some((du, m))
        } else {
            None
        };

        let only = match factory.physical_device(&instance) {
            Ok(p) => p,
            Err(e) => {
                if let Some((du, m)) = &debug {
                    du.destroy_debug_utils_messenger(*m, None);
                }
                instance.destroy_instance(None);
                return Err(e);
            }
        };
        let (physical, queue_family) = match pick_device(&instance, opts, only) {
            Ok(p) => p,
            Err(e) => {
                if let Some((du, m)) = &debug {
                    du.destroy_debug_utils_messenger(*m, None);
                }
                instance.destroy_instance(None);
                return Err(e);
            }
        };
        let props = instance.get_physical_device_properties(physical);
        let fragment_stores = instance
            .get_physical_device_features(physical)
            .fragment_stores_and_atomics
            != 0;

        let priorities = [1.0f32];
        let queue_info = [vk::DeviceQueueCreateInfo::default()
            .queue_family_index(queue_family)
            .queue_priorities(&priorities)];
        let mut dev_exts = vec![ash::khr::push_descriptor::NAME.as_ptr()];
        if opts.present {
            dev_exts.push(ash::khr::swapchain::NAME.as_ptr());
        }
        let mut f13 = vk::PhysicalDeviceVulkan13Features::default()
            .dynamic_rendering(true)
            .synchronization2(true);
        // Buffer device addresses: the volume passes reach buffers past maxStorageBufferRange.
        // Its own struct, not Vulkan12Features: an OpenXR runtime creating the device (Monado)
        // chains Vulkan 1.2 feature structs of its own, which Vulkan12Features may not join.
        let mut bda =
            vk::PhysicalDeviceBufferDeviceAddressFeatures::default().buffer_device_address(true);
        // 16-bit storage: V_AO and V_PAO hold AO as 16-bit unorm (`crate::ao::stored`).
        let mut f16 =
            vk::PhysicalDevice16BitStorageFeatures::default().storage_buffer16_bit_access(true);
        // shaderInt16: a 16-bit word written as a constant (AO_OPEN) or chosen by a select.
        let mut f2 = vk::PhysicalDeviceFeatures2::default()
            .features(
                vk::PhysicalDeviceFeatures::default()
                    .shader_int16(true)
                    .fragment_stores_and_atomics(fragment_stores),
            )
            .push_next(&mut f13)
            .push_next(&mut bda)
            .push_next(&mut f16);
        let dinfo = vk::DeviceCreateInfo::default()
            .queue_create_infos(&queue_info)
            .enabled_extension_names(&dev_exts)
            .push_next(&mut f2);
        let device = factory.create_device(&instance, physical, &dinfo)?;
        let queue = device.get_device_queue(queue_family, 0);
        let push_descriptor = ash::khr::push_descriptor::Device::new(&instance, &device);

        let allocator = Allocator::new(&AllocatorCreateDesc {
            instance: instance.clone(),
            device: device.clone(),
            physical_device: physical,
            debug_settings: Default::default(),
            buffer_device_address: true,
            allocation_sizes: Default::default(),
        })?;
        let cmd_pool = device.create_command_pool(
            &vk::CommandPoolCreateInfo::default()
                .queue_family_index(queue_family)
                .flags(vk::CommandPoolCreateFlags::RESET_COMMAND_BUFFER),
            None,
        )?;
        let device_name = props
            .device_name_as_c_str()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_default();
        Ok(Gpu(Arc::new(Core {
            entry,
            instance,
            debug,
            log,
            physical,
            device,
            push_descriptor,
            queue,
            queue_lock: Mutex::new(()),
            queue_family,
            allocator: Mutex::new(ManuallyDrop::new(allocator)),
            cmd_pool: Mutex::new(cmd_pool),
            memory: Mutex::new(MemoryUse {
                budget,
                ..MemoryUse::default()
            }),
            slab_limit: std::sync::atomic::AtomicU64::new(slab_limit),
            scratch_slices: std::sync::atomic::AtomicU64::new(scratch_slices),
            device_name,
            device_type: props.device_type,
            present: opts.present,
            timestamp_period: props.limits.timestamp_period,
            limits: props.limits,
            fragment_stores,
        })))
    }
}

/// Prefers a discrete GPU, then integrated, virtual, and finally a CPU device (lavapipe).
/// With `only`, that device is checked by the same rules and used if it passes.
unsafe fn pick_device(
    instance: &ash::Instance,
    opts: &GpuOptions,
    only: Option<vk::PhysicalDevice>,
) -> Result<(vk::PhysicalDevice, u32)> {
    let mut best: Option<(u32, vk::PhysicalDevice, u32)> = None;
    let mut rejected = Vec::new();
    let candidates = match only {
        Some(pd) => vec![pd],
        None => instance.enumerate_physical_devices()?,
    };
    for pd in candidates {
        let props = instance.get_physical_device_properties(pd);
        let name = props
            .device_name_as_c_str()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_default();
        if let (Some(want), None) = (&opts.device_name, only) {
            if !name.to_lowercase().contains(&want.to_lowercase()) {
                continue;
            }
        }
        if props.api_version < vk::API_VERSION_1_3 {
            rejected.push(format!("{name}: Vulkan < 1.3"));
            continue;
        }
        let exts = instance.enumerate_device_extension_properties(pd)?;
        if !exts
            .iter()
            .any(|e| e.extension_name_as_c_str() == Ok(ash::khr::push_descriptor::NAME))
        {
            rejected.push(format!("{name}: no VK_KHR_push_descriptor"));
            continue;
        }
        let mut f13 = vk::PhysicalDeviceVulkan13Features::default();
        let mut f12 = vk::PhysicalDeviceVulkan12Features::default();
        let mut f11 = vk::PhysicalDeviceVulkan11Features::default();
        let mut f2 = vk::PhysicalDeviceFeatures2::default()
            .push_next(&mut f13)
            .push_next(&mut f12)
            .push_next(&mut f11);
        instance.get_physical_device_features2(pd, &mut f2);
        let int16 = f2.features.shader_int16;
        if f13.dynamic_rendering == 0
            || f13.synchronization2 == 0
            || f12.buffer_device_address == 0
            || f11.storage_buffer16_bit_access == 0
            || int16 == 0
        {
            rejected.push(format!(
                "{name}: lacks dynamicRendering/synchronization2/bufferDeviceAddress/\
                 storageBuffer16BitAccess/shaderInt16"
            ));
            continue;
        }
        let want = vk::QueueFlags::GRAPHICS | vk::QueueFlags::COMPUTE;
        let family = instance
            .get_physical_device_queue_family_properties(pd)
            .iter()
            .position(|q| q.queue_flags.contains(want) && q.timestamp_valid_bits > 0);
        let Some(family) = family else {
            rejected.push(format!("{name}: no graphics+compute queue with timestamps"));
            continue;
        };
        let score = match props.device_type {
            vk::PhysicalDeviceType::DISCRETE_GPU => 4,
            vk::PhysicalDeviceType::INTEGRATED_GPU => 3,
            vk::PhysicalDeviceType::VIRTUAL_GPU => 2,
            vk::PhysicalDeviceType::CPU => 1,
            _ => 0,
        };
        if best.is_none_or(|b| score > b.0) {
            best = Some((score, pd, family as u32));
        }
    }
    best.map(|(_, pd, f)| (pd, f)).ok_or_else(|| {
        GpuError::NoDevice(if rejected.is_empty() {
            "no Vulkan device found (apt-get install mesa-vulkan-drivers for lavapipe)".into()
        } else {
            rejected.join("; ")
        })
    })
}

impl Core {
    /// Size in bytes of the largest device-local memory heap (where volumes and their AO live).
    /// The largest buffer the device makes: the smaller of `maxMemoryAllocationSize` and
    /// `maxBufferSize`.
    pub fn max_buffer_bytes(&self) -> u64 {
        let mut p11 = vk::PhysicalDeviceVulkan11Properties::default();
        let mut p13 = vk::PhysicalDeviceVulkan13Properties::default();
        let mut p2 = vk::PhysicalDeviceProperties2::default()
            .push_next(&mut p11)
            .push_next(&mut p13);
        // SAFETY: `physical` was enumerated from `instance`, both live as long as `self`; `p11` and
        // `p13`, chained into `p2`, are locals that outlive the call.
        unsafe {
            self.instance
                .get_physical_device_properties2(self.physical, &mut p2)
        };
        p11.max_memory_allocation_size.min(p13.max_buffer_size)
    }

    /// The largest buffer one slab of a [`SlabBuffer`] may be.
    pub fn max_slab_bytes(&self) -> u64 {
        let device = self.max_buffer_bytes();
        match self.slab_limit.load(std::sync::atomic::Ordering::Relaxed) {
            0 => device,
            forced => forced.min(device),
        }
    }

    /// Splits every [`SlabBuffer`] made from now on into slabs of at most `bytes` (tests compare
    /// a split volume with one buffer).
    pub fn set_max_slab_bytes(&self, bytes: u64) {
        self.slab_limit
            .store(bytes.max(1), std::sync::atomic::Ordering::Relaxed);
    }

    /// Makes every scratch volume made from now on (the filters' box statistics) computed
    /// `slices` z-slices at a time (tests compare a chunked volume with a whole one).
    pub fn set_scratch_slices(&self, slices: usize) {
        self.scratch_slices
            .store(slices.max(1) as u64, std::sync::atomic::Ordering::Relaxed);
    }

    /// The z-slices of a scratch volume computed at once, where a test forced it.
    pub fn forced_scratch_slices(&self) -> Option<usize> {
        match self
            .scratch_slices
            .load(std::sync::atomic::Ordering::Relaxed)
        {
            0 => None,
            n => Some(n as usize),
        }
    }

    /// The largest device-local heap. A CPU device's memory is the host's: Mesa 22's lavapipe
    /// reports a fixed 2 GiB heap whatever the machine has (later Mesa reports the host's
    /// physical memory, as this does for every CPU device).
    pub fn device_local_heap_bytes(&self) -> u64 {
        // SAFETY: `physical` was enumerated from `instance`, both live as long as `self`.
        let mem = unsafe {
            self.instance
                .get_physical_device_memory_properties(self.physical)
        };
        let heap = mem
            .memory_heaps_as_slice()
            .iter()
            .filter(|h| h.flags.contains(vk::MemoryHeapFlags::DEVICE_LOCAL))
            .map(|h| h.size)
            .max()
            .unwrap_or(0);
        if self.is_cpu() {
            heap.max(host_memory_bytes().unwrap_or(0))
        } else {
            heap
        }
    }

    /// Bytes of GPU memory held through [`Buffer`] and [`Image`].
    pub fn memory_in_use(&self) -> u64 {
        self.memory.lock().map_or(0, |m| m.total)
    }

    /// Bytes the budget ([`BUDGET_ENV`]) leaves beside what is held; None without a budget.
    pub fn budget_left(&self) -> Option<u64> {
        let m = self.memory.lock().ok()?;
        m.budget.map(|b| b.saturating_sub(m.total))
    }

    /// Caps the GPU memory held through Buffer and Image at `budget` bytes from now on, as
    /// [`BUDGET_ENV`] does from the start (a test's budget, without the environment).
    pub fn set_memory_budget(&self, budget: Option<u64>) {
        if let Ok(mut m) = self.memory.lock() {
            m.budget = budget;
        }
    }

    /// The most GPU memory held through Buffer and Image at once since
    /// `reset_memory_peak` (or the start).
    pub fn memory_peak(&self) -> u64 {
        self.memory.lock().map_or(0, |m| m.peak)
    }

    /// The most GPU memory held through Buffer and Image at once since the device was opened,
    /// whatever was reset (what a command tells the user it needed).
    pub fn session_memory_peak(&self) -> u64 {
        self.memory.lock().map_or(0, |m| m.session_peak)
    }

    /// Starts `Gpu::memory_peak` again from what is held now (a benchmark measures one set-up
    /// after another; the fit of a downsample and an inset measures each try).
    pub fn reset_memory_peak(&self) {
        if let Ok(mut m) = self.memory.lock() {
            m.peak = m.total;
        }
    }

    /// Whether the budget leaves room for `bytes` more for `what` beside what is held (always,
    /// without a budget): refused as an allocation beyond it would be, and counted nowhere,
    /// so the peaks stay what was allocated.
    pub fn check_room(&self, what: &str, bytes: u64) -> Result<()> {
        self.memory.lock().unwrap().room(what, bytes)
    }

    /// Counts `bytes` for `what` before they are allocated; refused beyond the budget. The
    /// id returned is given back with [`Core::release`].
    pub(crate) fn reserve(&self, what: &str, bytes: u64) -> Result<u64> {
        let mut m = self.memory.lock().unwrap();
        m.room(what, bytes)?;
        let id = m.next;
        m.next += 1;
        m.held.insert(id, bytes);
        m.total += bytes;
        m.peak = m.peak.max(m.total);
        m.session_peak = m.session_peak.max(m.total);
        Ok(id)
    }

    /// Gives back what [`Core::reserve`] counted.
    pub(crate) fn release(&self, id: u64) {
        if let Ok(mut m) = self.memory.lock() {
            if let Some(b) = m.held.remove(&id) {
                m.total -= b;
            }
        }
    }

    /// The allocator's error for `what` (already released): the device's own exhaustion says
    /// what was in use, like the budget's.
    pub(crate) fn allocation_failed(
        &self,
        what: &str,
        bytes: u64,
        e: gpu_allocator::AllocationError,
    ) -> GpuError {
        if !matches!(e, gpu_allocator::AllocationError::OutOfMemory) {
            return e.into();
        }
        let m = self.memory.lock().unwrap();
        GpuError::OutOfMemory(Box::new(OutOfMemory {
            what: what.to_string(),
            bytes,
            in_use: m.total,
            held: m.held.values().copied().collect(),
            available: self.device_local_heap_bytes(),
            budget: false,
        }))
    }

    /// Device memory in use through the allocator (gpu-allocator's report): what its live
    /// allocations hold, the blocks it has taken from the driver, and how many allocations.
    pub fn allocator_memory(&self) -> GpuMemory {
        let report = self.allocator.lock().unwrap().generate_report();
        GpuMemory {
            allocated_bytes: report.total_allocated_bytes,
            capacity_bytes: report.total_capacity_bytes,
            allocations: report.allocations.len(),
        }
    }

    /// Validation warnings and errors reported so far (empty when validation is off).
    pub fn validation_messages(&self) -> Vec<String> {
        self.log
            .messages
            .lock()
            .map(|m| m.clone())
            .unwrap_or_default()
    }

    pub fn validation_enabled(&self) -> bool {
        self.debug.is_some()
    }

    pub fn is_cpu(&self) -> bool {
        self.device_type == vk::PhysicalDeviceType::CPU
    }

    /// How long `Gpu::wait_fences` waits ([`GPU_TIMEOUT_ENV`]).
    pub fn timeout(&self) -> std::time::Duration {
        let default = if self.is_cpu() { 1800.0 } else { 60.0 };
        let s = std::env::var(GPU_TIMEOUT_ENV)
            .ok()
            .and_then(|v| v.trim().parse::<f64>().ok())
            .filter(|s| s.is_finite() && *s > 0.0)
            .unwrap_or(default);
        std::time::Duration::from_secs_f64(s)
    }

    /// Waits for all of `fences`, within `Gpu::timeout`: a device that stops answering is an
    /// error ([`GpuError::Stalled`], [`GpuError::DeviceLost`]), not a silent freeze.
    pub fn wait_fences(&self, fences: &[vk::Fence]) -> Result<()> {
        self.wait_fences_within(fences, self.timeout())
    }

    /// `Gpu::wait_fences` with the bound given.
    pub fn wait_fences_within(
        &self,
        fences: &[vk::Fence],
        bound: std::time::Duration,
    ) -> Result<()> {
        let ns = u64::try_from(bound.as_nanos()).unwrap_or(u64::MAX);
        // SAFETY: the fences belong to this device and outlive the call.
        match unsafe { self.device.wait_for_fences(fences, true, ns) } {
            Ok(()) => Ok(()),
            Err(vk::Result::TIMEOUT) => Err(GpuError::Stalled(bound.as_secs_f64())),
            Err(e) => Err(e.into()),
        }
    }

    /// Records commands into a fresh command buffer, submits it and waits for completion. The
    /// shared command pool is locked while the buffer is allocated, recorded, submitted and
    /// freed, not during the wait: a worker thread's long submission (the local histograms'
    /// clustering beside the frames) holds up no other thread's.
    pub fn submit_and_wait<R>(&self, record: impl FnOnce(vk::CommandBuffer) -> R) -> Result<R> {
        // SAFETY: the pool lock is held while `cmd` is allocated, recorded, submitted and
        // freed, so no other caller uses the pool meanwhile (the frame loop's slots have pools
        // of their own); while it waits, `cmd` is pending and nothing on the host touches it.
        // `cmd` is begun before `record` gets it and ended after; it and the fence are freed
        // only once the wait returned (after a stall they stay in use: leaked). Whatever
        // `record` names outlives this call, which waits.
        unsafe {
            let (cmd, fence, r, submitted) = {
                let pool = self.cmd_pool.lock().unwrap();
                let cmd = self.device.allocate_command_buffers(
                    &vk::CommandBufferAllocateInfo::default()
                        .command_pool(*pool)
                        .level(vk::CommandBufferLevel::PRIMARY)
                        .command_buffer_count(1),
                )?[0];
                self.device.begin_command_buffer(
                    cmd,
                    &vk::CommandBufferBeginInfo::default()
                        .flags(vk::CommandBufferUsageFlags::ONE_TIME_SUBMIT),
                )?;
                let r = record(cmd);
                self.device.end_command_buffer(cmd)?;
                let fence = self
                    .device
                    .create_fence(&vk::FenceCreateInfo::default(), None)?;
                let cmds = [vk::CommandBufferSubmitInfo::default().command_buffer(cmd)];
                let submit = [vk::SubmitInfo2::default().command_buffer_infos(&cmds)];
                (cmd, fence, r, self.submit(&submit, fence))
            };
            let res = submitted.and_then(|_| self.wait_fences(&[fence]));
            if matches!(res, Err(GpuError::Stalled(_))) {
                // Still in use by a device that stopped answering: leaked, not destroyed.
                return res.map(|_| r);
            }
            self.device.destroy_fence(fence, None);
            let pool = self.cmd_pool.lock().unwrap();
            self.device.free_command_buffers(*pool, &[cmd]);
            res?;
            Ok(r)
        }
    }

    /// Submits to the queue, holding its lock.
    ///
    /// # Safety
    /// As `vkQueueSubmit2`: the command buffers are recorded and not in use elsewhere, and
    /// everything they and `fence` reference lives until the fence signals.
    pub unsafe fn submit(&self, submits: &[vk::SubmitInfo2], fence: vk::Fence) -> Result<()> {
        let _queue = self.queue_guard();
        Ok(self.device.queue_submit2(self.queue, submits, fence)?)
    }

    /// The queue's lock, for a use of it other than [`Core::submit`].
    pub fn queue_guard(&self) -> std::sync::MutexGuard<'_, ()> {
        // A panic while holding it cannot leave the queue inconsistent.
        self.queue_lock
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// A full memory barrier between passes (compute/graphics/transfer all read-after-write).
    pub fn barrier(&self, cmd: vk::CommandBuffer) {
        self.memory_barrier(
            cmd,
            (
                vk::PipelineStageFlags2::ALL_COMMANDS,
                vk::AccessFlags2::MEMORY_WRITE,
            ),
            (
                vk::PipelineStageFlags2::ALL_COMMANDS,
                vk::AccessFlags2::MEMORY_READ | vk::AccessFlags2::MEMORY_WRITE,
            ),
        );
    }

    /// Records a global memory barrier: what `src` (stages, accesses) wrote, visible to `dst`.
    pub fn memory_barrier(
        &self,
        cmd: vk::CommandBuffer,
        src: (vk::PipelineStageFlags2, vk::AccessFlags2),
        dst: (vk::PipelineStageFlags2, vk::AccessFlags2),
    ) {
        let mb = [vk::MemoryBarrier2::default()
            .src_stage_mask(src.0)
            .src_access_mask(src.1)
            .dst_stage_mask(dst.0)
            .dst_access_mask(dst.1)];
        // SAFETY: `cmd` is a command buffer of this device in the recording state (the contract of
        // every cmd_* helper here); a global memory barrier names no resource.
        unsafe {
            self.device
                .cmd_pipeline_barrier2(cmd, &vk::DependencyInfo::default().memory_barriers(&mb));
        }
    }
}

impl Drop for Core {
    fn drop(&mut self) {
        // SAFETY: every Buffer, Image, pipeline, timer and presenter holds a Gpu clone, so this
        // runs after all of them are gone; the idle wait ends any submitted work first; then
        // children go before parents (pool and allocator's memory, device, messenger, instance).
        // `log`, the messenger's user data, is a field and drops after this body.
        unsafe {
            let _ = self.device.device_wait_idle();
            self.device
                .destroy_command_pool(*self.cmd_pool.get_mut().unwrap(), None);
            ManuallyDrop::drop(self.allocator.get_mut().unwrap());
            self.device.destroy_device(None);
            if let Some((du, m)) = &self.debug {
                du.destroy_debug_utils_messenger(*m, None);
            }
            self.instance.destroy_instance(None);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::parse_mem_total;

    #[test]
    fn host_memory_is_mem_total_in_bytes() {
        let info = "MemFree:  100 kB\nMemTotal:       24576000 kB\nMemAvailable: 5 kB\n";
        assert_eq!(parse_mem_total(info), Some(24_576_000 << 10));
        assert_eq!(parse_mem_total("MemFree: 1 kB\n"), None);
        assert_eq!(parse_mem_total("MemTotal: lots kB\n"), None);
    }
}
