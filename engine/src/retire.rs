//! Deferred destruction: the engine's submissions still on the GPU, and the buffers
//! freed while they may read them.
//!
//! Every [`crate::Submission`] registers its fence here with a serial number, in
//! submission order, and removes it once waited. A [`crate::Buffer`] dropped while
//! submissions are pending is not destroyed at once (nor waited for, which would stall
//! every frame in flight): it goes on the deferred list with the newest serial at the
//! time of its drop, and is destroyed once every submission up to that serial has
//! finished. The borrow checker keeps a waited-for or live [`crate::Submission`] from
//! outliving its buffers, so what the list guards against is work whose submission was
//! leaked or is still in a [`crate::FramesInFlight`] slot: the rule is conservative (any
//! submission pending at the drop may be the buffer's last use) and needs no per-binding
//! tracking.
//!
//! Finished work is found by polling fences (`vkGetFenceStatus`, no wait) when a buffer
//! is dropped and when a submission is made or waited for, so a leaked submission's
//! buffers are freed soon after its work ends rather than never. The device's drop waits
//! for what is left and destroys the rest.

use ash::vk;
use gpu_allocator::vulkan::Allocation;

/// The Vulkan objects of a dropped buffer, destroyed by [`DeferredBuffer::destroy`].
pub(crate) struct DeferredBuffer {
    pub raw: vk::Buffer,
    pub views: [Option<vk::BufferView>; 2],
    pub allocation: Option<Allocation>,
    pub name: String,
}

impl DeferredBuffer {
    /// Destroys the views and the buffer and frees the memory.
    ///
    /// # Safety
    /// No pending GPU work may use the buffer, and `raw` must be the device that made it.
    pub unsafe fn destroy(
        mut self,
        raw: &ash::Device,
        allocator: &std::sync::Mutex<gpu_allocator::vulkan::Allocator>,
    ) {
        // SAFETY: by the caller's contract the objects are unused; views go first.
        unsafe {
            for view in self.views.into_iter().flatten() {
                raw.destroy_buffer_view(view, None);
            }
            raw.destroy_buffer(self.raw, None);
        }
        if let Some(a) = self.allocation.take() {
            let mut alloc = allocator.lock().unwrap_or_else(|p| p.into_inner());
            if let Err(e) = alloc.free(a) {
                log::error!("freeing buffer '{}': {e}", self.name);
            }
        }
    }
}

/// The engine's pending submissions and the buffers waiting for them.
#[derive(Default)]
pub(crate) struct PendingWork {
    /// The serial the next submission gets.
    next_serial: u64,
    /// Pending submissions' (serial, fence), in increasing serial order.
    fences: Vec<(u64, vk::Fence)>,
    /// Dropped buffers with the newest serial submitted before their drop.
    deferred: Vec<(u64, DeferredBuffer)>,
    /// Buffers that went through the list (for tests and statistics).
    deferred_total: u64,
}

impl PendingWork {
    /// Registers a submitted fence.
    pub fn register(&mut self, fence: vk::Fence) {
        self.fences.push((self.next_serial, fence));
        self.next_serial += 1;
    }

    /// Removes a fence that was waited for (before the caller destroys it).
    pub fn unregister(&mut self, fence: vk::Fence) {
        self.fences.retain(|&(_, f)| f != fence);
    }

    /// Every registered fence, and forgets them (the device's drop waits for and
    /// destroys them).
    pub fn take_fences(&mut self) -> Vec<vk::Fence> {
        std::mem::take(&mut self.fences)
            .into_iter()
            .map(|(_, f)| f)
            .collect()
    }

    /// Every deferred buffer, whatever its work's state (for the device's drop, after it
    /// waited).
    pub fn take_deferred(&mut self) -> Vec<DeferredBuffer> {
        std::mem::take(&mut self.deferred)
            .into_iter()
            .map(|(_, b)| b)
            .collect()
    }

    /// A buffer to free: handed back when no submission is pending (the caller destroys
    /// it now), else kept until every submission pending now has finished.
    pub fn defer(&mut self, buffer: DeferredBuffer) -> Option<DeferredBuffer> {
        match self.fences.last() {
            None => Some(buffer),
            Some(&(newest, _)) => {
                self.deferred.push((newest, buffer));
                self.deferred_total += 1;
                None
            }
        }
    }

    /// Buffers on the list now.
    pub fn deferred_now(&self) -> usize {
        self.deferred.len()
    }

    /// Buffers that have gone through the list.
    pub fn deferred_total(&self) -> u64 {
        self.deferred_total
    }

    /// The deferred buffers whose submissions have all finished, taken off the list for
    /// the caller to destroy. Polls fences in serial order up to the first unfinished one.
    ///
    /// # Safety
    /// `raw` is the device of the registered fences; they are live (a fence is destroyed
    /// only after [`unregister`](Self::unregister), under the same lock as this call).
    pub unsafe fn take_finished(&mut self, raw: &ash::Device) -> Vec<DeferredBuffer> {
        if self.deferred.is_empty() {
            return Vec::new();
        }
        let newest_deferred = self.deferred.iter().map(|d| d.0).max().unwrap_or(0);
        let mut oldest_unfinished = u64::MAX;
        for &(serial, fence) in &self.fences {
            if serial > newest_deferred {
                break;
            }
            // SAFETY: a live fence of `raw` (the caller's contract). A lost device's work
            // will not run, so it counts as finished; any other error leaves the fence's
            // state unknown, so its buffers stay.
            match unsafe { raw.get_fence_status(fence) } {
                Ok(true) | Err(vk::Result::ERROR_DEVICE_LOST) => {}
                Ok(false) | Err(_) => {
                    oldest_unfinished = serial;
                    break;
                }
            }
        }
        let (done, kept) = std::mem::take(&mut self.deferred)
            .into_iter()
            .partition(|&(serial, _)| serial < oldest_unfinished);
        self.deferred = kept;
        done.into_iter().map(|(_, b)| b).collect()
    }
}
