//! The engine's error type: what a caller cannot foresee. Programmer mistakes (a buffer
//! too small for the op it is passed to, a copy past a buffer's end) are asserts, not
//! errors. The one file format the engine reads, LPIPS weights, has its own type
//! (`ops::lpips::WeightsError`), naming the file.

use ash::vk;

/// Errors of the Vulkan runtime and its ops.
#[derive(Debug, thiserror::Error)]
pub enum EngineError {
    /// The Vulkan loader could not be loaded: `library` is the name or path it was
    /// looked up by (`libvulkan.so.1`, or `DRAPE_VULKAN_LOADER`), `error` why (the
    /// library is not there, or lacks `vkGetInstanceProcAddr`). A failed `dlopen` names
    /// the library in its own text, so the message shows `error` alone.
    #[error("the Vulkan loader could not be loaded ({error}); install it (Debian: apt-get install libvulkan1 mesa-vulkan-drivers)")]
    LoaderMissing { library: String, error: ash::LoadingError },

    /// No device supports what the engine needs.
    #[error("no Vulkan device with Vulkan 1.2, a compute queue and vulkanMemoryModel was found{}", list_devices(.rejected))]
    NoDevice { rejected: Vec<String> },

    /// `--device NAME` matched no device.
    #[error("no Vulkan device matches '{requested}'; available: {}", if .available.is_empty() { "none".to_string() } else { .available.join(", ") })]
    DeviceNotFound { requested: String, available: Vec<String> },

    /// The host's device, handed over with [`crate::Context::from_raw`], lacks what the
    /// engine needs: `what` names the feature, extension or version.
    #[error("the application's Vulkan device cannot run the engine: {what} is not enabled ({hint})")]
    HostDeviceMissing { what: &'static str, hint: &'static str },

    /// Validation was requested but the layer is not installed.
    #[error("validation was requested but VK_LAYER_KHRONOS_validation is not installed (Debian: apt-get install vulkan-validationlayers)")]
    ValidationLayerMissing,

    /// Device or host memory ran out while creating `what`.
    #[error("out of device memory allocating '{what}' ({bytes} bytes)")]
    OutOfDeviceMemory { what: String, bytes: u64 },

    /// The device was lost; `pass` is the last pass whose breadcrumb was written.
    #[error("the Vulkan device was lost during pass '{pass}'")]
    DeviceLost { pass: String },

    /// An embedded SPIR-V module does not match the kernel manifest.
    #[error("shader/manifest mismatch for kernel '{kernel}': {detail} (rebuild with tools/shader-builder and commit shaders-rs/spirv)")]
    ShaderManifestMismatch { kernel: &'static str, detail: String },

    /// A pass binds its buffers against what the kernel's SPIR-V declares: a name the
    /// kernel lacks, a binding left unbound or bound twice, or an access that disagrees
    /// with the declaration (writing through a `NonWritable` binding).
    #[error("pass '{pass}': kernel '{kernel}', binding '{binding}': {problem}")]
    Binding { pass: String, kernel: &'static str, binding: String, problem: String },

    /// A kernel needs a device feature the device lacks (callers pick a fallback).
    #[error("kernel '{kernel}' needs {feature}, which the device does not have")]
    MissingFeature { kernel: &'static str, feature: &'static str },

    /// A size beyond what the engine or the device supports; `limit_name` says whose
    /// limit (a Vulkan device limit by its name, or the engine's own).
    #[error("{what}: {requested} is more than {limit_name} allows ({limit})")]
    TooLarge { what: String, requested: u64, limit: u64, limit_name: &'static str },

    /// A backward was given the saved state of another forward pass: another renderer's,
    /// an earlier one (the renderer has rendered since), or one of another cloud.
    #[error("{op}: {problem}")]
    StaleForward { op: &'static str, problem: String },

    /// A render or op setting outside what the kernels take (`what` names it).
    #[error("{what}: {problem}")]
    InvalidSetting { what: &'static str, problem: String },

    /// An image smaller than an op's stack of convolutions and pools allows (every
    /// stage must keep at least one pixel): the op, the image's size and the smallest
    /// square side it takes.
    #[error("{op} needs images of at least {min_side}x{min_side}; got {width}x{height}")]
    ImageTooSmall { op: &'static str, width: u32, height: u32, min_side: u32 },

    /// An op was given an empty input it has no value for.
    #[error("{what} is empty: {why}")]
    Empty { what: &'static str, why: &'static str },

    /// Any other Vulkan failure, with the call that returned it.
    #[error("{call} failed: {result}")]
    Vulkan { call: &'static str, result: vk::Result },

    /// A memory-allocator failure other than running out of memory.
    #[error("allocating '{what}': {detail}")]
    Allocation { what: String, detail: String },
}

impl EngineError {
    /// [`EngineError::TooLarge`] for `what` (a count or a size, named with its unit).
    pub fn too_large(what: impl Into<String>, requested: u64, limit: u64, limit_name: &'static str) -> Self {
        Self::TooLarge { what: what.into(), requested, limit, limit_name }
    }
}

fn list_devices(rejected: &[String]) -> String {
    if rejected.is_empty() {
        " (the loader reports no devices; install mesa-vulkan-drivers for lavapipe)".to_string()
    } else {
        format!("; rejected: {}", rejected.join("; "))
    }
}

/// Result with [`EngineError`].
pub type Result<T, E = EngineError> = std::result::Result<T, E>;

/// Maps a Vulkan result of `call` to an [`EngineError`], keeping the typed cases.
pub(crate) fn vk_error(call: &'static str, what: &str, result: vk::Result) -> EngineError {
    match result {
        vk::Result::ERROR_OUT_OF_DEVICE_MEMORY | vk::Result::ERROR_OUT_OF_HOST_MEMORY => {
            EngineError::OutOfDeviceMemory { what: what.to_string(), bytes: 0 }
        }
        vk::Result::ERROR_DEVICE_LOST => EngineError::DeviceLost { pass: what.to_string() },
        result => EngineError::Vulkan { call, result },
    }
}

/// `?`-friendly conversion: `.vk("vkCreateBuffer", name)?`.
pub(crate) trait VkResultExt<T> {
    fn vk(self, call: &'static str, what: &str) -> Result<T>;
}

impl<T> VkResultExt<T> for std::result::Result<T, vk::Result> {
    fn vk(self, call: &'static str, what: &str) -> Result<T> {
        self.map_err(|r| vk_error(call, what, r))
    }
}
