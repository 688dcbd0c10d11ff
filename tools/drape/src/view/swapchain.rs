//! The swapchain and the frames in flight: the swapchain (made again when the window
//! changes) with one `present_ready` semaphore per swapchain image, and per frame in
//! flight an `R32G32B32A32_SFLOAT` image the engine renders into, its memory, a command
//! buffer, a fence and two binary semaphores (`render_done`, `acquired`), all of one
//! command pool; their creation ([`Presenter::new`]) and teardown (its `Drop`), and the
//! per-frame Vulkan work on them: acquiring a swapchain image, and the blit of a frame's
//! image into it followed by the present (the order of these is `frame`'s header).
//!
//! A frame's image is in `TRANSFER_DST_OPTIMAL` between frames (the layout the engine's
//! `ImageTarget` copies into); the blit moves it to `TRANSFER_SRC_OPTIMAL` and back.
#![allow(unsafe_code)]

use anyhow::{anyhow, bail, Context as _};
use drape_engine::ash::{self, vk};

use super::device::Gpu;

/// One frame in flight's objects (see the module header).
pub(super) struct Slot {
    pub(super) image: vk::Image,
    memory: vk::DeviceMemory,
    cmd: vk::CommandBuffer,
    pub(super) fence: vk::Fence,
    pub(super) render_done: vk::Semaphore,
    acquired: vk::Semaphore,
}

struct Swapchain {
    raw: vk::SwapchainKHR,
    images: Vec<vk::Image>,
    /// One per swapchain image: signalled by the blit, waited by the present.
    present_ready: Vec<vk::Semaphore>,
    extent: vk::Extent2D,
}

/// The swapchain and the frames in flight (see the module header), on the Gpu's device.
pub(super) struct Presenter {
    /// The Gpu's device (a clone of its function table; the Gpu destroys it, after this).
    device: ash::Device,
    queue: vk::Queue,
    swapchain_fn: ash::khr::swapchain::Device,
    swapchain: Option<Swapchain>,
    /// The window changed or a present reported the swapchain out of date or
    /// suboptimal: it is made again before the next frame.
    pub(super) stale: bool,
    pub(super) format: vk::SurfaceFormatKHR,
    pub(super) present_mode: vk::PresentModeKHR,
    pool: vk::CommandPool,
    pub(super) slots: Vec<Slot>,
    /// The size of the frames' images: the render's.
    pub(super) width: u32,
    pub(super) height: u32,
}

impl Presenter {
    /// Chooses the swapchain's format and present mode, and creates the `k` frames in
    /// flight at `width` x `height`, their images moved to `TRANSFER_DST_OPTIMAL`. The
    /// swapchain itself comes with the first [`recreate_swapchain`](Self::recreate_swapchain).
    pub(super) fn new(gpu: &Gpu, k: usize, width: u32, height: u32) -> anyhow::Result<Self> {
        let (instance, physical, device_label) = (&gpu.instance, gpu.physical, &gpu.label);
        // The blit's formats.
        // SAFETY: a query on the chosen physical device.
        let rgba_props = unsafe {
            instance
                .get_physical_device_format_properties(physical, vk::Format::R32G32B32A32_SFLOAT)
        };
        anyhow::ensure!(
            rgba_props
                .optimal_tiling_features
                .contains(vk::FormatFeatureFlags::BLIT_SRC | vk::FormatFeatureFlags::TRANSFER_DST),
            "{device_label}: R32G32B32A32_SFLOAT images cannot be blitted from"
        );
        // SAFETY: surface queries on the chosen device and the viewer's surface.
        let formats = unsafe {
            gpu.surface_fn
                .get_physical_device_surface_formats(physical, gpu.surface)
        }
        .context("vkGetPhysicalDeviceSurfaceFormatsKHR")?;
        let blit_dst = |fmt: vk::Format| {
            // SAFETY: as above.
            unsafe { instance.get_physical_device_format_properties(physical, fmt) }
                .optimal_tiling_features
                .contains(vk::FormatFeatureFlags::BLIT_DST)
        };
        // UNORM first: the window then shows the render's values as they are (the test
        // compares them with the library's render at 8 bits).
        let format = [
            vk::Format::B8G8R8A8_UNORM,
            vk::Format::R8G8B8A8_UNORM,
            vk::Format::A8B8G8R8_UNORM_PACK32,
        ]
        .iter()
        .find_map(|want| {
            formats
                .iter()
                .find(|f| f.format == *want && blit_dst(f.format))
                .copied()
        })
        .or_else(|| formats.iter().find(|f| blit_dst(f.format)).copied())
        .ok_or_else(|| anyhow!("{device_label}: no swapchain format the blit can write"))?;
        // SAFETY: as above.
        let modes = unsafe {
            gpu.surface_fn
                .get_physical_device_surface_present_modes(physical, gpu.surface)
        }
        .context("vkGetPhysicalDeviceSurfacePresentModesKHR")?;
        let present_mode = [vk::PresentModeKHR::MAILBOX, vk::PresentModeKHR::IMMEDIATE]
            .into_iter()
            .find(|m| modes.contains(m))
            .unwrap_or(vk::PresentModeKHR::FIFO);

        // From here on the Presenter holds what is made, and its Drop undoes it if a
        // later step fails.
        let device = gpu.device.clone();
        let mut presenter = Self {
            swapchain_fn: ash::khr::swapchain::Device::new(instance, &device),
            device,
            queue: gpu.queue,
            swapchain: None,
            stale: false,
            format,
            present_mode,
            pool: vk::CommandPool::null(),
            slots: Vec::with_capacity(k),
            width,
            height,
        };
        let (device, queue) = (&gpu.device, gpu.queue);
        // Per frame in flight.
        let pool_info = vk::CommandPoolCreateInfo::default()
            .queue_family_index(gpu.queue_family)
            .flags(vk::CommandPoolCreateFlags::RESET_COMMAND_BUFFER);
        // SAFETY: a pool on the live device.
        let pool = unsafe { device.create_command_pool(&pool_info, None) }
            .context("vkCreateCommandPool")?;
        presenter.pool = pool;
        let alloc = vk::CommandBufferAllocateInfo::default()
            .command_pool(pool)
            .level(vk::CommandBufferLevel::PRIMARY)
            .command_buffer_count(k as u32 + 1);
        // SAFETY: the pool is live; the buffers are freed with it.
        let cmds = unsafe { device.allocate_command_buffers(&alloc) }
            .context("vkAllocateCommandBuffers")?;
        // SAFETY: a query on the chosen physical device.
        let mem_props = unsafe { instance.get_physical_device_memory_properties(physical) };
        for &cmd in &cmds[..k] {
            let slot = create_slot(device, &mem_props, width, height, cmd)?;
            presenter.slots.push(slot);
        }
        // The images start UNDEFINED: one submission moves them to TRANSFER_DST_OPTIMAL,
        // the layout they keep between frames.
        let init = cmds[k];
        // SAFETY: a fresh primary command buffer of the pool; the barriers name the
        // slots' live images; the submission is waited for before anything else uses them.
        unsafe {
            device.begin_command_buffer(
                init,
                &vk::CommandBufferBeginInfo::default()
                    .flags(vk::CommandBufferUsageFlags::ONE_TIME_SUBMIT),
            )?;
            let barriers: Vec<_> = presenter
                .slots
                .iter()
                .map(|s| {
                    image_barrier(
                        s.image,
                        vk::ImageLayout::UNDEFINED,
                        vk::ImageLayout::TRANSFER_DST_OPTIMAL,
                        vk::AccessFlags::empty(),
                        vk::AccessFlags::TRANSFER_WRITE,
                    )
                })
                .collect();
            device.cmd_pipeline_barrier(
                init,
                vk::PipelineStageFlags::TOP_OF_PIPE,
                vk::PipelineStageFlags::TRANSFER,
                vk::DependencyFlags::empty(),
                &[],
                &[],
                &barriers,
            );
            device.end_command_buffer(init)?;
            let cb = [init];
            let submit = vk::SubmitInfo::default().command_buffers(&cb);
            device.queue_submit(queue, &[submit], vk::Fence::null())?;
            device.queue_wait_idle(queue)?;
        }
        Ok(presenter)
    }

    /// (Re)creates the swapchain at the surface's size (the render is blitted to fit).
    pub(super) fn recreate_swapchain(&mut self, gpu: &Gpu) -> anyhow::Result<()> {
        // SAFETY: waits for the viewer's and the engine's work on the device's only queue
        // to finish before the old swapchain and its semaphores go.
        unsafe { self.device.device_wait_idle() }.context("vkDeviceWaitIdle")?;
        // SAFETY: a query on the viewer's surface.
        let caps = unsafe {
            gpu.surface_fn
                .get_physical_device_surface_capabilities(gpu.physical, gpu.surface)
        }
        .context("vkGetPhysicalDeviceSurfaceCapabilitiesKHR")?;
        anyhow::ensure!(
            caps.supported_usage_flags
                .contains(vk::ImageUsageFlags::TRANSFER_DST),
            "{}: swapchain images cannot be transfer destinations (needed by the blit)",
            gpu.label
        );
        let extent = if caps.current_extent.width == u32::MAX {
            vk::Extent2D {
                width: self.width,
                height: self.height,
            }
        } else {
            caps.current_extent
        };
        self.stale = false;
        if extent.width == 0 || extent.height == 0 {
            return Ok(()); // minimised: keep the old one (or none) until it has a size.
        }
        let mut count = caps.min_image_count.max(self.slots.len() as u32 + 1);
        if caps.max_image_count > 0 {
            count = count.min(caps.max_image_count);
        }
        let alpha = [
            vk::CompositeAlphaFlagsKHR::OPAQUE,
            vk::CompositeAlphaFlagsKHR::INHERIT,
            vk::CompositeAlphaFlagsKHR::PRE_MULTIPLIED,
            vk::CompositeAlphaFlagsKHR::POST_MULTIPLIED,
        ]
        .into_iter()
        .find(|a| caps.supported_composite_alpha.contains(*a))
        .unwrap_or(vk::CompositeAlphaFlagsKHR::OPAQUE);
        let old = self
            .swapchain
            .as_ref()
            .map_or(vk::SwapchainKHR::null(), |s| s.raw);
        let info = vk::SwapchainCreateInfoKHR::default()
            .surface(gpu.surface)
            .min_image_count(count)
            .image_format(self.format.format)
            .image_color_space(self.format.color_space)
            .image_extent(extent)
            .image_array_layers(1)
            .image_usage(vk::ImageUsageFlags::TRANSFER_DST)
            .image_sharing_mode(vk::SharingMode::EXCLUSIVE)
            .pre_transform(caps.current_transform)
            .composite_alpha(alpha)
            .present_mode(self.present_mode)
            .clipped(true)
            .old_swapchain(old);
        // SAFETY: the surface is live; the old swapchain (if any) is idle (waited above).
        let raw = unsafe { self.swapchain_fn.create_swapchain(&info, None) }
            .context("vkCreateSwapchainKHR")?;
        self.destroy_swapchain();
        // SAFETY: the swapchain was just created.
        let images = unsafe { self.swapchain_fn.get_swapchain_images(raw) }
            .context("vkGetSwapchainImagesKHR")?;
        let mut present_ready = Vec::with_capacity(images.len());
        for _ in &images {
            // SAFETY: a binary semaphore on the live device.
            present_ready.push(
                unsafe {
                    self.device
                        .create_semaphore(&vk::SemaphoreCreateInfo::default(), None)
                }
                .context("vkCreateSemaphore")?,
            );
        }
        self.swapchain = Some(Swapchain {
            raw,
            images,
            present_ready,
            extent,
        });
        Ok(())
    }

    fn destroy_swapchain(&mut self) {
        if let Some(s) = self.swapchain.take() {
            // SAFETY: callers wait for the device to go idle first, so no submission or
            // present uses the semaphores or the swapchain's images.
            unsafe {
                for sem in s.present_ready {
                    self.device.destroy_semaphore(sem, None);
                }
                self.swapchain_fn.destroy_swapchain(s.raw, None);
            }
        }
    }

    /// Waits for every frame in flight: each slot's image is then idle and in
    /// TRANSFER_DST_OPTIMAL.
    pub(super) fn wait_all(&self) -> anyhow::Result<()> {
        let fences: Vec<_> = self.slots.iter().map(|s| s.fence).collect();
        // SAFETY: the slots' fences, each submitted or created signalled.
        unsafe { self.device.wait_for_fences(&fences, true, u64::MAX) }
            .context("vkWaitForFences")?;
        Ok(())
    }

    /// Waits for slot `s`'s fence: its command buffer of K frames ago has completed.
    pub(super) fn wait_slot(&self, s: usize) -> anyhow::Result<()> {
        let slot_fence = self.slots[s].fence;
        // SAFETY: the fence is the slot's, submitted with its previous command buffer
        // (or created signalled).
        unsafe { self.device.wait_for_fences(&[slot_fence], true, u64::MAX) }
            .context("vkWaitForFences")?;
        Ok(())
    }

    /// Whether there is a swapchain to present to (none while the window has no size).
    pub(super) fn has_swapchain(&self) -> bool {
        self.swapchain.is_some()
    }

    /// Acquires the next swapchain image into slot `s`'s semaphore and resets the slot's
    /// fence; None (after recreating the swapchain) if it is out of date.
    pub(super) fn acquire(&mut self, gpu: &Gpu, s: usize) -> anyhow::Result<Option<u32>> {
        let sc = self.swapchain.as_ref().expect("created before a frame");
        // SAFETY: the semaphore is unsignalled with no pending operation: the slot's
        // fence (waited by the caller) covers the submission that waited on it.
        let r = unsafe {
            self.swapchain_fn.acquire_next_image(
                sc.raw,
                u64::MAX,
                self.slots[s].acquired,
                vk::Fence::null(),
            )
        };
        match r {
            Ok((i, suboptimal)) => {
                if suboptimal {
                    self.stale = true;
                }
                // SAFETY: the fence was waited for by the caller and is not in use.
                unsafe { self.device.reset_fences(&[self.slots[s].fence]) }
                    .context("vkResetFences")?;
                Ok(Some(i))
            }
            Err(vk::Result::ERROR_OUT_OF_DATE_KHR) => {
                self.recreate_swapchain(gpu)?;
                Ok(None)
            }
            Err(e) => Err(anyhow!("vkAcquireNextImageKHR: {e}")),
        }
    }

    /// Records and submits slot `s`'s command buffer that blits `src_slot`'s image into
    /// swapchain image `image_index` and presents it; waits on the slot's `acquired`
    /// semaphore and, with `wait_render`, on its `render_done` (see `frame`'s header).
    pub(super) fn blit_and_present(
        &mut self,
        s: usize,
        src_slot: usize,
        image_index: u32,
        wait_render: bool,
    ) -> anyhow::Result<()> {
        let sc = self.swapchain.as_ref().expect("created before a frame");
        let dev = &self.device;
        let slot = &self.slots[s];
        let src = self.slots[src_slot].image;
        let dst = sc.images[image_index as usize];
        let (w, h) = (self.width as i32, self.height as i32);
        let (dw, dh) = (sc.extent.width as i32, sc.extent.height as i32);
        // SAFETY: the slot's command buffer is not pending (its fence was waited for);
        // every image named is live; the layouts are those the module header describes.
        unsafe {
            dev.begin_command_buffer(
                slot.cmd,
                &vk::CommandBufferBeginInfo::default()
                    .flags(vk::CommandBufferUsageFlags::ONE_TIME_SUBMIT),
            )
            .context("vkBeginCommandBuffer")?;
            let before = [
                image_barrier(
                    src,
                    vk::ImageLayout::TRANSFER_DST_OPTIMAL,
                    vk::ImageLayout::TRANSFER_SRC_OPTIMAL,
                    vk::AccessFlags::TRANSFER_WRITE,
                    vk::AccessFlags::TRANSFER_READ,
                ),
                image_barrier(
                    dst,
                    vk::ImageLayout::UNDEFINED,
                    vk::ImageLayout::TRANSFER_DST_OPTIMAL,
                    vk::AccessFlags::empty(),
                    vk::AccessFlags::TRANSFER_WRITE,
                ),
            ];
            dev.cmd_pipeline_barrier(
                slot.cmd,
                vk::PipelineStageFlags::TRANSFER,
                vk::PipelineStageFlags::TRANSFER,
                vk::DependencyFlags::empty(),
                &[],
                &[],
                &before,
            );
            let layers = vk::ImageSubresourceLayers::default()
                .aspect_mask(vk::ImageAspectFlags::COLOR)
                .layer_count(1);
            let blit = vk::ImageBlit::default()
                .src_subresource(layers)
                .src_offsets([vk::Offset3D::default(), vk::Offset3D { x: w, y: h, z: 1 }])
                .dst_subresource(layers)
                .dst_offsets([vk::Offset3D::default(), vk::Offset3D { x: dw, y: dh, z: 1 }]);
            dev.cmd_blit_image(
                slot.cmd,
                src,
                vk::ImageLayout::TRANSFER_SRC_OPTIMAL,
                dst,
                vk::ImageLayout::TRANSFER_DST_OPTIMAL,
                &[blit],
                vk::Filter::NEAREST,
            );
            let to_present = [image_barrier(
                dst,
                vk::ImageLayout::TRANSFER_DST_OPTIMAL,
                vk::ImageLayout::PRESENT_SRC_KHR,
                vk::AccessFlags::TRANSFER_WRITE,
                vk::AccessFlags::empty(),
            )];
            dev.cmd_pipeline_barrier(
                slot.cmd,
                vk::PipelineStageFlags::TRANSFER,
                vk::PipelineStageFlags::BOTTOM_OF_PIPE,
                vk::DependencyFlags::empty(),
                &[],
                &[],
                &to_present,
            );
            let back = [image_barrier(
                src,
                vk::ImageLayout::TRANSFER_SRC_OPTIMAL,
                vk::ImageLayout::TRANSFER_DST_OPTIMAL,
                vk::AccessFlags::TRANSFER_READ,
                vk::AccessFlags::TRANSFER_WRITE,
            )];
            dev.cmd_pipeline_barrier(
                slot.cmd,
                vk::PipelineStageFlags::TRANSFER,
                vk::PipelineStageFlags::TRANSFER,
                vk::DependencyFlags::empty(),
                &[],
                &[],
                &back,
            );
            dev.end_command_buffer(slot.cmd)
                .context("vkEndCommandBuffer")?;
        }
        let mut waits = vec![slot.acquired];
        if wait_render {
            waits.push(slot.render_done);
        }
        let stages = vec![vk::PipelineStageFlags::TRANSFER; waits.len()];
        let cmds = [slot.cmd];
        let signal = [sc.present_ready[image_index as usize]];
        let submit = vk::SubmitInfo::default()
            .wait_semaphores(&waits)
            .wait_dst_stage_mask(&stages)
            .command_buffers(&cmds)
            .signal_semaphores(&signal);
        // SAFETY: the queue is used from this thread only (the engine submits from the
        // same thread, inside player calls); the fence was reset in `acquire`.
        unsafe { dev.queue_submit(self.queue, &[submit], slot.fence) }
            .context("vkQueueSubmit (blit)")?;
        let swapchains = [sc.raw];
        let indices = [image_index];
        let present = vk::PresentInfoKHR::default()
            .wait_semaphores(&signal)
            .swapchains(&swapchains)
            .image_indices(&indices);
        // SAFETY: the image was acquired and its blit submitted, signalling `signal`.
        match unsafe { self.swapchain_fn.queue_present(self.queue, &present) } {
            Ok(false) => {}
            Ok(true) | Err(vk::Result::ERROR_OUT_OF_DATE_KHR) => self.stale = true,
            Err(e) => bail!("vkQueuePresentKHR: {e}"),
        }
        Ok(())
    }
}

fn image_barrier(
    image: vk::Image,
    old: vk::ImageLayout,
    new: vk::ImageLayout,
    src: vk::AccessFlags,
    dst: vk::AccessFlags,
) -> vk::ImageMemoryBarrier<'static> {
    vk::ImageMemoryBarrier::default()
        .src_access_mask(src)
        .dst_access_mask(dst)
        .old_layout(old)
        .new_layout(new)
        .src_queue_family_index(vk::QUEUE_FAMILY_IGNORED)
        .dst_queue_family_index(vk::QUEUE_FAMILY_IGNORED)
        .image(image)
        .subresource_range(
            vk::ImageSubresourceRange::default()
                .aspect_mask(vk::ImageAspectFlags::COLOR)
                .level_count(1)
                .layer_count(1),
        )
}

fn create_slot(
    device: &ash::Device,
    mem_props: &vk::PhysicalDeviceMemoryProperties,
    width: u32,
    height: u32,
    cmd: vk::CommandBuffer,
) -> anyhow::Result<Slot> {
    let info = vk::ImageCreateInfo::default()
        .image_type(vk::ImageType::TYPE_2D)
        .format(vk::Format::R32G32B32A32_SFLOAT)
        .extent(vk::Extent3D {
            width,
            height,
            depth: 1,
        })
        .mip_levels(1)
        .array_layers(1)
        .samples(vk::SampleCountFlags::TYPE_1)
        .tiling(vk::ImageTiling::OPTIMAL)
        .usage(vk::ImageUsageFlags::TRANSFER_DST | vk::ImageUsageFlags::TRANSFER_SRC)
        .sharing_mode(vk::SharingMode::EXCLUSIVE)
        .initial_layout(vk::ImageLayout::UNDEFINED);
    // SAFETY: creation on the live device; on any later failure the objects made so far
    // are destroyed below before returning.
    unsafe {
        let image = device.create_image(&info, None).context("vkCreateImage")?;
        let req = device.get_image_memory_requirements(image);
        let types =
            (0..mem_props.memory_type_count).filter(|&i| req.memory_type_bits & (1 << i) != 0);
        let local = types.clone().find(|&i| {
            mem_props.memory_types[i as usize]
                .property_flags
                .contains(vk::MemoryPropertyFlags::DEVICE_LOCAL)
        });
        let Some(type_index) = local.or_else(|| types.clone().next()) else {
            device.destroy_image(image, None);
            bail!("no memory type for the render image");
        };
        let memory = match device.allocate_memory(
            &vk::MemoryAllocateInfo::default()
                .allocation_size(req.size)
                .memory_type_index(type_index),
            None,
        ) {
            Ok(m) => m,
            Err(e) => {
                device.destroy_image(image, None);
                bail!("vkAllocateMemory (render image): {e}");
            }
        };
        let slot = Slot {
            image,
            memory,
            cmd,
            fence: vk::Fence::null(),
            render_done: vk::Semaphore::null(),
            acquired: vk::Semaphore::null(),
        };
        let mut slot = slot;
        let made = (|| -> Result<(), vk::Result> {
            device.bind_image_memory(image, memory, 0)?;
            slot.fence = device.create_fence(
                &vk::FenceCreateInfo::default().flags(vk::FenceCreateFlags::SIGNALED),
                None,
            )?;
            slot.render_done =
                device.create_semaphore(&vk::SemaphoreCreateInfo::default(), None)?;
            slot.acquired = device.create_semaphore(&vk::SemaphoreCreateInfo::default(), None)?;
            Ok(())
        })();
        if let Err(e) = made {
            destroy_slot(device, &slot);
            bail!("render image / sync objects: {e}");
        }
        Ok(slot)
    }
}

fn destroy_slot(device: &ash::Device, s: &Slot) {
    // SAFETY: callers wait for the device to go idle first; null handles are ignored by
    // the destroy calls.
    unsafe {
        device.destroy_semaphore(s.acquired, None);
        device.destroy_semaphore(s.render_done, None);
        device.destroy_fence(s.fence, None);
        device.destroy_image(s.image, None);
        device.free_memory(s.memory, None);
    }
}

impl Drop for Presenter {
    fn drop(&mut self) {
        // SAFETY: once the device is idle nothing uses the swapchain or the slots; the
        // engine's frames are done too (the player and the context drop first).
        unsafe {
            let _ = self.device.device_wait_idle();
        }
        self.destroy_swapchain();
        for s in &self.slots {
            destroy_slot(&self.device, s);
        }
        // SAFETY: as above; the pool's command buffers go with it (a null pool, left by
        // a failed `new`, is ignored).
        unsafe {
            self.device.destroy_command_pool(self.pool, None);
        }
    }
}
