//! XR_EXT_debug_utils: the OpenXR side's counterpart of the Vulkan validation messenger. With
//! the core validation layer enabled (XR_ENABLE_API_LAYERS=XR_APILAYER_LUNARG_core_validation)
//! its warnings and errors arrive here, are printed as `openxr validation: ...` and fail the
//! run, like a Vulkan validation message does.

use openxr as xr;
use std::ffi::{c_void, CStr};
use std::sync::Mutex;
use xr::sys;
use xr::sys::Handle as _;

/// Every warning and error the messenger saw.
#[derive(Default)]
pub struct XrLog(Mutex<Vec<String>>);

pub struct XrMessenger {
    destroy: sys::pfn::DestroyDebugUtilsMessengerEXT,
    handle: sys::DebugUtilsMessengerEXT,
    /// Boxed so its address, handed to the runtime as user data, stays put.
    log: Box<XrLog>,
}

unsafe extern "system" fn callback(
    severity: sys::DebugUtilsMessageSeverityFlagsEXT,
    _types: sys::DebugUtilsMessageTypeFlagsEXT,
    data: *const sys::DebugUtilsMessengerCallbackDataEXT,
    user: *mut c_void,
) -> sys::Bool32 {
    let text = |p: *const std::ffi::c_char| {
        if p.is_null() {
            String::new()
        } else {
            CStr::from_ptr(p).to_string_lossy().into_owned()
        }
    };
    let (id, func, msg) = if data.is_null() {
        (String::new(), String::new(), "(no message)".to_string())
    } else {
        (
            text((*data).message_id),
            text((*data).function_name),
            text((*data).message),
        )
    };
    let line = format!("[{severity:?}] {id} {func}: {msg}");
    eprintln!("openxr validation: {line}");
    if !user.is_null() {
        if let Ok(mut m) = (*(user as *const XrLog)).0.lock() {
            m.push(line);
        }
    }
    sys::FALSE
}

impl XrMessenger {
    /// A messenger for warnings and errors, or None when XR_EXT_debug_utils is not enabled.
    pub fn new(instance: &xr::Instance) -> Option<XrMessenger> {
        let ext = instance.exts().ext_debug_utils.as_ref()?;
        let log = Box::<XrLog>::default();
        let info = sys::DebugUtilsMessengerCreateInfoEXT {
            ty: sys::DebugUtilsMessengerCreateInfoEXT::TYPE,
            next: std::ptr::null(),
            message_severities: sys::DebugUtilsMessageSeverityFlagsEXT::WARNING
                | sys::DebugUtilsMessageSeverityFlagsEXT::ERROR,
            message_types: sys::DebugUtilsMessageTypeFlagsEXT::GENERAL
                | sys::DebugUtilsMessageTypeFlagsEXT::VALIDATION
                | sys::DebugUtilsMessageTypeFlagsEXT::PERFORMANCE
                | sys::DebugUtilsMessageTypeFlagsEXT::CONFORMANCE,
            user_callback: Some(callback),
            user_data: &*log as *const XrLog as *mut c_void,
        };
        let mut handle = sys::DebugUtilsMessengerEXT::NULL;
        let r =
            // SAFETY: `info` is a complete create info with no chain; `callback` has the PFN's
            // signature and reads `user` only as the XrLog boxed in `log`, which the messenger owns
            // and which stays put and outlives the handle (dropped after Drop destroys it).
            unsafe { (ext.create_debug_utils_messenger)(instance.as_raw(), &info, &mut handle) };
        if r.into_raw() < 0 {
            eprintln!("xr: no debug messenger ({r})");
            return None;
        }
        Some(XrMessenger {
            destroy: ext.destroy_debug_utils_messenger,
            handle,
            log,
        })
    }

    pub fn messages(&self) -> Vec<String> {
        self.log.0.lock().map(|m| m.clone()).unwrap_or_default()
    }
}

impl Drop for XrMessenger {
    fn drop(&mut self) {
        // SAFETY: `handle` is this messenger's own, destroyed once, on an instance that outlives it
        // (XrRuntime declares the messenger first).
        unsafe {
            (self.destroy)(self.handle);
        }
    }
}
