//! Validation-layer messages: a debug-utils messenger whose callback appends every
//! validation or performance warning/error to a [`ValidationSink`]. Tests drain the
//! sink and fail on any message, so each test is charged with what it caused.

use std::ffi::{c_void, CStr};
use std::sync::{Arc, Mutex};

use ash::vk;

/// Where the messenger collects messages. Shared (`Arc`) so a test can still read it
/// after the context, and with it the instance's last messages, is gone.
#[derive(Debug, Default)]
pub struct ValidationSink {
    messages: Mutex<Vec<String>>,
}

impl ValidationSink {
    /// Takes every message collected so far.
    pub fn drain(&self) -> Vec<String> {
        std::mem::take(&mut *self.messages.lock().unwrap_or_else(|p| p.into_inner()))
    }

    fn push(&self, message: String) {
        self.messages
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .push(message);
    }
}

/// A messenger create-info that collects into `sink` (the host application's instance
/// can use it too; keep `sink` alive until the messenger is destroyed).
///
/// The messenger's severities and types. GENERAL is left out on purpose: the loader
/// reports there, e.g. that a GPU driver found no GPU, which is not a validation error.
pub fn messenger_info(sink: &Arc<ValidationSink>) -> vk::DebugUtilsMessengerCreateInfoEXT<'static> {
    vk::DebugUtilsMessengerCreateInfoEXT::default()
        .message_severity(
            vk::DebugUtilsMessageSeverityFlagsEXT::WARNING
                | vk::DebugUtilsMessageSeverityFlagsEXT::ERROR,
        )
        .message_type(
            vk::DebugUtilsMessageTypeFlagsEXT::VALIDATION
                | vk::DebugUtilsMessageTypeFlagsEXT::PERFORMANCE,
        )
        .pfn_user_callback(Some(on_message))
        .user_data(Arc::as_ptr(sink) as *mut c_void)
}

/// # Safety
/// Called by the Vulkan loader with a valid callback-data pointer; `user_data` is the
/// `ValidationSink` the context keeps alive until after the instance is destroyed.
unsafe extern "system" fn on_message(
    severity: vk::DebugUtilsMessageSeverityFlagsEXT,
    kind: vk::DebugUtilsMessageTypeFlagsEXT,
    data: *const vk::DebugUtilsMessengerCallbackDataEXT<'_>,
    user_data: *mut c_void,
) -> vk::Bool32 {
    // SAFETY: the loader passes a valid pointer for the duration of the call.
    let text = unsafe { data.as_ref() }
        .and_then(|d| (!d.p_message.is_null()).then_some(d.p_message))
        // SAFETY: p_message is a nul-terminated string valid during the call.
        .map(|p| unsafe { CStr::from_ptr(p) }.to_string_lossy().into_owned())
        .unwrap_or_default();
    let message = format!("[{severity:?} {kind:?}] {text}");
    eprintln!("vulkan validation: {message}");
    // SAFETY: user_data is `Arc::as_ptr` of a sink that outlives the messenger.
    if let Some(sink) = unsafe { (user_data as *const ValidationSink).as_ref() } {
        sink.push(message);
    }
    vk::FALSE
}
