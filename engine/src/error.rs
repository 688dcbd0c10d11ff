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
    LoaderMissing {
        /// The name or path the loader was looked up by.
        library: String,
        /// Why loading failed.
        error: ash::LoadingError,
    },

    /// No device supports what the engine needs.
    #[error("no Vulkan device with Vulkan 1.2, a compute queue and vulkanMemoryModel was found{}", list_devices(.rejected))]
    NoDevice {
        /// Each device seen and what it lacks.
        rejected: Vec<String>,
    },

    /// `--device NAME` matched no device.
    #[error("no Vulkan device matches '{requested}'; available: {}", if .available.is_empty() { "none".to_string() } else { .available.join(", ") })]
    DeviceNotFound {
        /// The name asked for.
        requested: String,
        /// The names of the devices present.
        available: Vec<String>,
    },

    /// The host's device, handed over with [`crate::Context::from_raw`], lacks what the
    /// engine needs: `what` names the feature, extension or version.
    #[error(
        "the application's Vulkan device cannot run the engine: {what} is not enabled ({hint})"
    )]
    HostDeviceMissing {
        /// The feature, extension or version missing.
        what: &'static str,
        /// How the host enables it.
        hint: &'static str,
    },

    /// Validation was requested but the layer is not installed.
    #[error("validation was requested but VK_LAYER_KHRONOS_validation is not installed (Debian: apt-get install vulkan-validationlayers)")]
    ValidationLayerMissing,

    /// Device or host memory ran out while creating `what`.
    #[error("out of device memory allocating '{what}' ({bytes} bytes)")]
    OutOfDeviceMemory {
        /// The buffer or image being created.
        what: String,
        /// Its size.
        bytes: u64,
    },

    /// The device was lost; `pass` is the last pass whose breadcrumb was written.
    #[error("the Vulkan device was lost during pass '{pass}'")]
    DeviceLost {
        /// The last pass whose breadcrumb was written.
        pass: String,
    },

    /// An embedded SPIR-V module does not match the kernel manifest.
    #[error("shader/manifest mismatch for kernel '{kernel}': {detail} (rebuild with tools/shader-builder and commit shaders-rs/spirv)")]
    ShaderManifestMismatch {
        /// The kernel whose module disagrees.
        kernel: &'static str,
        /// What disagrees.
        detail: String,
    },

    /// A binding the device cannot take as the kernel declares it: a range bound where
    /// the kernel reads a texel buffer, or a texel binding's buffer made without texel
    /// usage or past `maxTexelBufferElements`. (Missing, unknown and wrongly accessed
    /// bindings do not compile: see [`crate::bindings`].)
    #[error("pass '{pass}': kernel '{kernel}', binding '{binding}': {problem}")]
    Binding {
        /// The pass being recorded.
        pass: String,
        /// The kernel it dispatches.
        kernel: &'static str,
        /// The binding by name.
        binding: String,
        /// What is wrong with it.
        problem: String,
    },

    /// A kernel needs a device feature the device lacks (callers pick a fallback).
    #[error("kernel '{kernel}' needs {feature}, which the device does not have")]
    MissingFeature {
        /// The kernel that needs the feature.
        kernel: &'static str,
        /// The feature, by its Vulkan name.
        feature: &'static str,
    },

    /// A size beyond what the engine or the device supports; `limit_name` says whose
    /// limit (a Vulkan device limit by its name, or the engine's own).
    #[error("{what}: {requested} is more than {limit_name} allows ({limit})")]
    TooLarge {
        /// What was too large.
        what: String,
        /// The size asked for.
        requested: u64,
        /// The largest size allowed.
        limit: u64,
        /// Whose limit: a Vulkan device limit by name, or the engine's own.
        limit_name: &'static str,
    },

    /// A backward was given the saved state of another forward pass: another renderer's,
    /// an earlier one (the renderer has rendered since), or one of another cloud.
    #[error("{op}: {problem}")]
    StaleForward {
        /// The backward op refusing the state.
        op: &'static str,
        /// Whose state it was given.
        problem: String,
    },

    /// A render or op setting outside what the kernels take (`what` names it).
    #[error("{what}: {problem}")]
    InvalidSetting {
        /// The setting, by its field name.
        what: &'static str,
        /// Why its value is refused.
        problem: String,
    },

    /// An image smaller than an op's stack of convolutions and pools allows (every
    /// stage must keep at least one pixel): the op, the image's size and the smallest
    /// square side it takes.
    #[error("{op} needs images of at least {min_side}x{min_side}; got {width}x{height}")]
    ImageTooSmall {
        /// The op.
        op: &'static str,
        /// The image's width.
        width: u32,
        /// The image's height.
        height: u32,
        /// The smallest square side the op takes.
        min_side: u32,
    },

    /// An op was given an empty input it has no value for.
    #[error("{what} is empty: {why}")]
    Empty {
        /// The input that is empty.
        what: &'static str,
        /// Why the op has no value for it.
        why: &'static str,
    },

    /// Any other Vulkan failure, with the call that returned it.
    #[error("{call} failed: {result}")]
    Vulkan {
        /// The Vulkan call that failed.
        call: &'static str,
        /// The result it returned.
        result: vk::Result,
    },

    /// A memory-allocator failure other than running out of memory.
    #[error("allocating '{what}': {detail}")]
    Allocation {
        /// The buffer or image being allocated.
        what: String,
        /// The allocator's message.
        detail: String,
    },
}

impl EngineError {
    /// [`EngineError::TooLarge`] for `what` (a count or a size, named with its unit).
    pub fn too_large(
        what: impl Into<String>,
        requested: u64,
        limit: u64,
        limit_name: &'static str,
    ) -> Self {
        Self::TooLarge {
            what: what.into(),
            requested,
            limit,
            limit_name,
        }
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
            EngineError::OutOfDeviceMemory {
                what: what.to_string(),
                bytes: 0,
            }
        }
        vk::Result::ERROR_DEVICE_LOST => EngineError::DeviceLost {
            pass: what.to_string(),
        },
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
