//! The pools a recording records with (command, descriptor and query pools) and the
//! device's store of them between recordings: reset, not destroyed, so a frame loop
//! creates none per frame. A leaf: it knows `ash::Device`, not the engine's device or
//! recordings.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Mutex;

use ash::vk;

use crate::error::{Result, VkResultExt};

/// Most sets of pools the device keeps for reuse (more recordings alive at once make
/// their own and destroy them).
const RECYCLED_POOLS: usize = 8;

/// The Vulkan objects one recording records with.
pub(crate) struct RecordingPools {
    pub(crate) command_pool: vk::CommandPool,
    pub(crate) cmd: vk::CommandBuffer,
    pub(crate) descriptor_pools: Vec<vk::DescriptorPool>,
    pub(crate) query_pools: Vec<vk::QueryPool>,
}

impl RecordingPools {
    /// A command pool on `queue_family` with one primary command buffer; no descriptor
    /// or query pool yet (the recording adds them as it needs them).
    fn create(dev: &ash::Device, queue_family: u32, label: &str) -> Result<Self> {
        let pool_info = vk::CommandPoolCreateInfo::default()
            .queue_family_index(queue_family)
            .flags(vk::CommandPoolCreateFlags::TRANSIENT);
        // SAFETY: valid device and create info.
        let command_pool = unsafe { dev.create_command_pool(&pool_info, None) }
            .vk("vkCreateCommandPool", label)?;
        let alloc = vk::CommandBufferAllocateInfo::default()
            .command_pool(command_pool)
            .level(vk::CommandBufferLevel::PRIMARY)
            .command_buffer_count(1);
        // SAFETY: the pool was just created on this device.
        let cmd = match unsafe { dev.allocate_command_buffers(&alloc) } {
            Ok(c) => c[0],
            Err(e) => {
                // SAFETY: created above, unused.
                unsafe { dev.destroy_command_pool(command_pool, None) };
                return Err(crate::error::vk_error("vkAllocateCommandBuffers", label, e));
            }
        };
        Ok(RecordingPools {
            command_pool,
            cmd,
            descriptor_pools: Vec::new(),
            query_pools: Vec::new(),
        })
    }

    /// No objects: what a recording holds once its pools were returned or forgotten.
    pub(crate) fn empty() -> Self {
        RecordingPools {
            command_pool: vk::CommandPool::null(),
            cmd: vk::CommandBuffer::null(),
            descriptor_pools: Vec::new(),
            query_pools: Vec::new(),
        }
    }

    pub(crate) fn destroy(self, dev: &ash::Device) {
        // SAFETY: called by the owner when no command buffer of these pools is pending.
        unsafe {
            for pool in self.query_pools {
                dev.destroy_query_pool(pool, None);
            }
            for pool in self.descriptor_pools {
                dev.destroy_descriptor_pool(pool, None);
            }
            dev.destroy_command_pool(self.command_pool, None);
        }
    }
}

/// The device's pools of finished recordings, for the next ones.
#[derive(Default)]
pub(crate) struct PoolRecycler {
    recycled: Mutex<Vec<RecordingPools>>,
    /// Command pools created so far (`Context::command_pools_created`).
    created: AtomicU64,
}

impl PoolRecycler {
    /// A finished recording's pools, or new ones when none is kept.
    pub(crate) fn take(
        &self,
        dev: &ash::Device,
        queue_family: u32,
        label: &str,
    ) -> Result<RecordingPools> {
        let recycled = self
            .recycled
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .pop();
        match recycled {
            Some(p) => Ok(p),
            None => {
                let pools = RecordingPools::create(dev, queue_family, label)?;
                self.created.fetch_add(1, Ordering::Relaxed);
                Ok(pools)
            }
        }
    }

    /// Resets `pools` and keeps them for the next recording, or destroys them when the
    /// reset fails or enough are kept.
    ///
    /// # Safety
    /// The pools' command buffer was never submitted or its submission was waited for,
    /// so nothing of them is in use; `dev` made them.
    pub(crate) unsafe fn recycle(&self, dev: &ash::Device, pools: RecordingPools) {
        // SAFETY: nothing of the pools is in use (the caller's contract); resetting
        // returns the command buffer to its initial state and frees every set.
        let reset = unsafe {
            dev.reset_command_pool(pools.command_pool, vk::CommandPoolResetFlags::empty())
                .and_then(|()| {
                    pools.descriptor_pools.iter().try_for_each(|&p| {
                        dev.reset_descriptor_pool(p, vk::DescriptorPoolResetFlags::empty())
                    })
                })
        };
        let mut recycled = self.recycled.lock().unwrap_or_else(|p| p.into_inner());
        if reset.is_ok() && recycled.len() < RECYCLED_POOLS {
            recycled.push(pools);
            return;
        }
        drop(recycled);
        pools.destroy(dev);
    }

    /// How many command pools [`PoolRecycler::take`] has created.
    pub(crate) fn created(&self) -> u64 {
        self.created.load(Ordering::Relaxed)
    }

    /// Destroys every kept set of pools (the device's drop, when no recording is left).
    pub(crate) fn destroy_all(&self, dev: &ash::Device) {
        for pools in std::mem::take(&mut *self.recycled.lock().unwrap_or_else(|p| p.into_inner())) {
            pools.destroy(dev);
        }
    }
}
