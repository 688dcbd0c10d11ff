//! RAII buffers: each is named (debug utils), owns its allocation and the texel views
//! made of it on first use, frees them in `Drop`, and holds the device alive. With
//! poisoning on, a new buffer is filled with
//! [`crate::context::POISON_WORD`] before anyone sees it.

use std::sync::{Arc, OnceLock};

use ash::vk;
use gpu_allocator::vulkan::{Allocation, AllocationCreateDesc, AllocationScheme};
use gpu_allocator::MemoryLocation;

use crate::context::{Context, Device, POISON_WORD};
use crate::error::{EngineError, Result, VkResultExt};

/// What kind of buffer to make.
#[derive(Clone, Copy, Debug)]
pub struct BufferDesc {
    /// Bytes the caller will use (a zero-length buffer still gets 4 bytes: Vulkan
    /// forbids empty buffers, and ops bind them even when there is nothing to do).
    pub size: u64,
    /// Vulkan usage flags.
    pub usage: vk::BufferUsageFlags,
    /// Where the memory lives: device-local, or host-visible for uploads and read-backs.
    pub location: MemoryLocation,
}

impl BufferDesc {
    /// A storage buffer kernels read and write, also usable for copies and fills and
    /// readable as a uniform texel buffer of `f32` (see [`BindingDecl::texel`](crate::kernels::BindingDecl::texel)).
    pub fn gpu_only(size: u64) -> Self {
        Self {
            size,
            usage: vk::BufferUsageFlags::STORAGE_BUFFER
                | vk::BufferUsageFlags::UNIFORM_TEXEL_BUFFER
                | vk::BufferUsageFlags::TRANSFER_SRC
                | vk::BufferUsageFlags::TRANSFER_DST,
            location: MemoryLocation::GpuOnly,
        }
    }

    /// A storage buffer the host rewrites often and kernels only read (a frame's
    /// transforms, target image, ...): host-visible (device-local too where the device
    /// offers such memory), so [`Context::write_buffer`] is a copy into its mapping, with
    /// no staging buffer and no submission. A staged write would cost a staging buffer,
    /// a submission and a wait, several times a training step (docs/performance.md has
    /// the figures).
    /// The caller must not write it while a submission that reads it is in flight.
    pub fn host_written(size: u64) -> Self {
        Self {
            size,
            usage: vk::BufferUsageFlags::STORAGE_BUFFER
                | vk::BufferUsageFlags::UNIFORM_TEXEL_BUFFER
                | vk::BufferUsageFlags::TRANSFER_SRC
                | vk::BufferUsageFlags::TRANSFER_DST,
            location: MemoryLocation::CpuToGpu,
        }
    }

    /// A host-visible buffer to copy data into the device.
    pub fn upload(size: u64) -> Self {
        Self {
            size,
            usage: vk::BufferUsageFlags::TRANSFER_SRC,
            location: MemoryLocation::CpuToGpu,
        }
    }

    /// A host-visible buffer to copy results back (also the breadcrumb).
    pub fn readback(size: u64) -> Self {
        Self {
            size,
            usage: vk::BufferUsageFlags::TRANSFER_DST | vk::BufferUsageFlags::STORAGE_BUFFER,
            location: MemoryLocation::GpuToCpu,
        }
    }
}

/// A Vulkan buffer with its memory.
///
/// Its fields are private: the handle and the size are what `Drop` destroys and what every
/// copy is bounded by, so safe code reads them and cannot change them.
///
/// ```compile_fail
/// fn grow(b: &mut drape_engine::Buffer) {
///     b.size = u64::MAX; // private: a copy past the allocation is not expressible
/// }
/// ```
///
/// ```compile_fail
/// fn swap(b: &mut drape_engine::Buffer, other: drape_engine::ash::vk::Buffer) {
///     b.raw = other; // private: Drop destroys only the handle the buffer owns
/// }
/// ```
pub struct Buffer {
    pub(crate) raw: vk::Buffer,
    pub(crate) size: u64,
    allocation: Option<Allocation>,
    /// Whether the host may map this buffer's memory (see `ContextDesc::force_staging`).
    host_access: bool,
    usage: vk::BufferUsageFlags,
    /// The whole buffer as `R32_SFLOAT` texels, made the first time a texel binding
    /// reads the buffer and destroyed with it.
    texel_view: OnceLock<vk::BufferView>,
    /// The whole buffer as `R32G32B32A32_SFLOAT` texels (4 floats a texel), made the
    /// first time a 4-float texel binding reads it.
    texel4_view: OnceLock<vk::BufferView>,
    name: String,
    /// Used by one recording only (its breadcrumbs), dropped after it completed: no
    /// other submission can use it, so its drop need not wait for any.
    pub(crate) private_to_recording: bool,
    device: Arc<Device>,
}

impl Buffer {
    /// The Vulkan handle, for hosts that record their own commands on it.
    pub fn raw(&self) -> vk::Buffer {
        self.raw
    }

    /// Bytes the caller asked for (the allocation may be larger).
    pub fn size(&self) -> u64 {
        self.size
    }

    /// The buffer's debug name (as `VK_EXT_debug_utils` shows it).
    pub fn name(&self) -> &str {
        &self.name
    }

    /// Whether host reads and writes reach this buffer's memory directly (mapped and
    /// coherent); otherwise they go through a staging buffer and a copy.
    pub fn host_mapped(&mut self) -> bool {
        self.coherent_mapping().is_some()
    }

    /// Bytes actually bound to `raw`: see [`vk_bytes`].
    pub(crate) fn vk_size(&self) -> u64 {
        vk_bytes(self.size)
    }

    /// Whether a texel binding can read this buffer: made with `UNIFORM_TEXEL_BUFFER`
    /// usage and holding at most `max_texels` `f32`s (ops choose a texel kernel only
    /// then).
    pub fn texel_readable(&self, max_texels: u64) -> bool {
        self.usage
            .contains(vk::BufferUsageFlags::UNIFORM_TEXEL_BUFFER)
            && self.vk_size() / 4 <= max_texels
    }

    /// The buffer's `R32_SFLOAT` view for texel bindings, made on first use. Callers
    /// check [`texel_readable`](Self::texel_readable) first (the recorder does, and
    /// names the pass and binding when it does not hold).
    pub(crate) fn texel_view(&self) -> Result<vk::BufferView> {
        self.view_of(&self.texel_view, vk::Format::R32_SFLOAT, 4)
    }

    /// The buffer's `R32G32B32A32_SFLOAT` view (whole texels of 16 bytes), made on first use.
    pub(crate) fn texel4_view(&self) -> Result<vk::BufferView> {
        self.view_of(&self.texel4_view, vk::Format::R32G32B32A32_SFLOAT, 16)
    }

    fn view_of(
        &self,
        slot: &OnceLock<vk::BufferView>,
        format: vk::Format,
        texel_bytes: u64,
    ) -> Result<vk::BufferView> {
        if let Some(&view) = slot.get() {
            return Ok(view);
        }
        // The callers' check, kept here because the view's validity rests on it.
        assert!(
            self.usage
                .contains(vk::BufferUsageFlags::UNIFORM_TEXEL_BUFFER),
            "texel view of '{}', made without texel usage",
            self.name
        );
        let texels = self.vk_size() / texel_bytes;
        let info = vk::BufferViewCreateInfo::default()
            .buffer(self.raw)
            .format(format)
            .offset(0)
            .range(texels * texel_bytes);
        // SAFETY: a buffer of this device made with UNIFORM_TEXEL_BUFFER usage; the range
        // lies inside it; R32_SFLOAT and R32G32B32A32_SFLOAT uniform texel buffers are
        // required of every device.
        let view = unsafe { self.device.raw.create_buffer_view(&info, None) }
            .vk("vkCreateBufferView", &self.name)?;
        if let Err(ours) = slot.set(view) {
            // Another thread made one first: keep its view.
            // SAFETY: ours was never used.
            unsafe { self.device.raw.destroy_buffer_view(ours, None) };
        }
        Ok(*slot.get().expect("set above"))
    }

    /// The mapped bytes, when the memory is host-visible and coherent (so no flush or
    /// invalidate is needed around host access).
    pub(crate) fn coherent_mapping(&mut self) -> Option<&mut [u8]> {
        if !self.host_access {
            return None;
        }
        let a = self.allocation.as_mut()?;
        if !a
            .memory_properties()
            .contains(vk::MemoryPropertyFlags::HOST_COHERENT)
        {
            return None;
        }
        let size = self.size as usize;
        a.mapped_slice_mut().map(|s| &mut s[..size])
    }
}

impl Drop for Buffer {
    fn drop(&mut self) {
        let freed = crate::retire::DeferredBuffer {
            raw: self.raw,
            views: [
                self.texel_view.get().copied(),
                self.texel4_view.get().copied(),
            ],
            allocation: self.allocation.take(),
            name: std::mem::take(&mut self.name),
        };
        if self.private_to_recording {
            // SAFETY: used by one recording only, which has completed (see the field).
            unsafe { freed.destroy(&self.device.raw, &self.device.allocator) };
        } else {
            // Submissions still pending (leaked, or frames in flight) may read it: freed
            // once they finish, without waiting for them here (`crate::retire`).
            self.device.free_buffer(freed);
        }
    }
}

impl Context {
    /// Creates a named buffer. A size past the device's `maxMemoryAllocationSize` is
    /// [`EngineError::TooLarge`] naming the buffer, the size and the limit; binding more
    /// than `maxStorageBufferRange` of it is refused by the recorder the same way.
    pub fn create_buffer(&self, name: &str, desc: BufferDesc) -> Result<Buffer> {
        // (maxStorageBufferRange limits a binding, not a buffer: the recorder checks it.)
        let limits = self.info();
        if desc.size > limits.max_memory_allocation_size {
            return Err(EngineError::too_large(
                format!("bytes of buffer '{name}'"),
                desc.size,
                limits.max_memory_allocation_size,
                "the device's maxMemoryAllocationSize",
            ));
        }
        let dev = &self.device.raw;
        let info = vk::BufferCreateInfo::default()
            .size(vk_bytes(desc.size))
            .usage(desc.usage)
            .sharing_mode(vk::SharingMode::EXCLUSIVE);
        // SAFETY: valid device and create info.
        let raw = unsafe { dev.create_buffer(&info, None) }.map_err(|r| match r {
            vk::Result::ERROR_OUT_OF_DEVICE_MEMORY | vk::Result::ERROR_OUT_OF_HOST_MEMORY => {
                EngineError::OutOfDeviceMemory {
                    what: name.to_string(),
                    bytes: desc.size,
                }
            }
            r => crate::error::vk_error("vkCreateBuffer", name, r),
        })?;
        // SAFETY: raw is a buffer of this device.
        let requirements = unsafe { dev.get_buffer_memory_requirements(raw) };
        let allocated = self
            .device
            .allocator
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .allocate(&AllocationCreateDesc {
                name,
                requirements,
                location: desc.location,
                linear: true,
                allocation_scheme: AllocationScheme::GpuAllocatorManaged,
            });
        let allocation = match allocated {
            Ok(a) => a,
            Err(e) => {
                // SAFETY: unbound, unused buffer.
                unsafe { dev.destroy_buffer(raw, None) };
                return Err(match e {
                    gpu_allocator::AllocationError::OutOfMemory => EngineError::OutOfDeviceMemory {
                        what: name.to_string(),
                        bytes: desc.size,
                    },
                    e => EngineError::Allocation {
                        what: name.to_string(),
                        detail: e.to_string(),
                    },
                });
            }
        };
        // Staging and readback buffers are always mapped; forcing staging only stops
        // the host from reaching into device buffers.
        let host_access =
            !(self.device.buffers.force_staging && desc.location == MemoryLocation::GpuOnly);
        let mut buffer = Buffer {
            raw,
            size: desc.size,
            allocation: Some(allocation),
            host_access,
            usage: desc.usage,
            texel_view: OnceLock::new(),
            texel4_view: OnceLock::new(),
            name: name.to_string(),
            private_to_recording: false,
            device: self.device.clone(),
        };
        let a = buffer.allocation.as_ref().expect("just allocated");
        // SAFETY: memory and offset come from an allocation made for these requirements.
        unsafe { dev.bind_buffer_memory(raw, a.memory(), a.offset()) }
            .vk("vkBindBufferMemory", name)?;
        self.set_name(raw, name);
        if self.device.buffers.poison {
            self.poison(&mut buffer)?;
        }
        Ok(buffer)
    }

    fn poison(&self, buffer: &mut Buffer) -> Result<()> {
        if let Some(bytes) = buffer.coherent_mapping() {
            for (i, b) in bytes.iter_mut().enumerate() {
                *b = POISON_WORD.to_le_bytes()[i % 4];
            }
            return Ok(());
        }
        let mut rec = self.record("poison")?;
        rec.fill(buffer, POISON_WORD);
        rec.submit_and_wait().map(|_| ())
    }

    /// A new device buffer holding `data`.
    pub fn upload<T: bytemuck::Pod>(&self, name: &str, data: &[T]) -> Result<Buffer> {
        let bytes: &[u8] = bytemuck::cast_slice(data);
        let mut buffer = self.create_buffer(name, BufferDesc::gpu_only(bytes.len() as u64))?;
        self.write_buffer(&mut buffer, data)?;
        Ok(buffer)
    }

    /// Copies `data` to the start of `buffer` (which must be large enough).
    pub fn write_buffer<T: bytemuck::Pod>(&self, buffer: &mut Buffer, data: &[T]) -> Result<()> {
        let bytes: &[u8] = bytemuck::cast_slice(data);
        assert!(
            bytes.len() as u64 <= buffer.size,
            "writing {} bytes into '{}' of {} bytes",
            bytes.len(),
            buffer.name,
            buffer.size
        );
        if bytes.is_empty() {
            return Ok(());
        }
        if let Some(mapped) = buffer.coherent_mapping() {
            mapped[..bytes.len()].copy_from_slice(bytes);
            return Ok(());
        }
        let mut staging = self.create_buffer(
            &format!("{} (upload)", buffer.name),
            BufferDesc::upload(bytes.len() as u64),
        )?;
        let staging_name = staging.name.clone();
        staging
            .coherent_mapping()
            .ok_or(EngineError::Allocation {
                what: staging_name,
                detail: "upload memory is not host-coherent".into(),
            })?
            .copy_from_slice(bytes);
        let mut rec = self.record("upload")?;
        rec.copy(&staging, buffer, bytes.len() as u64);
        rec.submit_and_wait().map(|_| ())
    }

    /// Reads the first `count` elements of `buffer`.
    pub fn read_buffer<T: bytemuck::Pod>(
        &self,
        buffer: &mut Buffer,
        count: usize,
    ) -> Result<Vec<T>> {
        self.read_buffer_at(buffer, 0, count)
    }

    /// Reads `count` elements of `buffer` starting at element `first` (only those
    /// bytes cross to the host).
    pub fn read_buffer_at<T: bytemuck::Pod>(
        &self,
        buffer: &mut Buffer,
        first: usize,
        count: usize,
    ) -> Result<Vec<T>> {
        let size = std::mem::size_of::<T>();
        let (start, len) = (first * size, count * size);
        assert!(
            (start + len) as u64 <= buffer.size,
            "reading {len} bytes at {start} from '{}' of {} bytes",
            buffer.name,
            buffer.size
        );
        let mut out = vec![T::zeroed(); count];
        if len == 0 {
            return Ok(out);
        }
        if let Some(mapped) = buffer.coherent_mapping() {
            bytemuck::cast_slice_mut(&mut out).copy_from_slice(&mapped[start..start + len]);
            return Ok(out);
        }
        let mut staging = self.create_buffer(
            &format!("{} (readback)", buffer.name),
            BufferDesc::readback(len as u64),
        )?;
        let mut rec = self.record("readback")?;
        rec.copy_from(buffer, start as u64, &staging, len as u64);
        rec.submit_and_wait()?;
        let staging_name = staging.name.clone();
        let mapped = staging.coherent_mapping().ok_or(EngineError::Allocation {
            what: staging_name,
            detail: "readback memory is not host-coherent".into(),
        })?;
        bytemuck::cast_slice_mut(&mut out).copy_from_slice(&mapped[..len]);
        Ok(out)
    }
}

/// The bytes a buffer of `size` requested bytes is made with: at least 4, and whole
/// 16-byte texels, so a 4-float texel view (`BindingDecl::texel4`) reaches its last
/// float (the padding is never written or read as data).
fn vk_bytes(size: u64) -> u64 {
    size.max(4).next_multiple_of(16)
}
