//! Submission that does not block: a recording submitted with semaphores to wait on and
//! signal ([`Recording::submit`], returning a [`Submission`] to wait on or poll), a
//! recording emitted into a command buffer the host owns ([`Recording::record_into`]),
//! and a ring of per-frame resources for frames in flight ([`FramesInFlight`]).
//!
//! Barrier scopes for [`Recording::record_into`] (the engine's part of the host's command
//! buffer starts and ends without a barrier of its own to the host's commands):
//!
//! | where | source scope | destination scope |
//! | --- | --- | --- |
//! | before, if the host wrote a buffer the engine reads (or reads one it writes) | the host's writing stage and access | `COMPUTE_SHADER \| TRANSFER`, `SHADER_READ \| SHADER_WRITE \| TRANSFER_READ \| TRANSFER_WRITE` |
//! | before, for an image the engine copies into ([`Recording::copy_to_image`]) | the host's last access of the image, with the layout transition to `TRANSFER_DST_OPTIMAL` or `GENERAL` | `TRANSFER`, `TRANSFER_WRITE` |
//! | after, where the host reads what the engine wrote | `COMPUTE_SHADER \| TRANSFER`, `SHADER_WRITE \| TRANSFER_WRITE` | the host's reading stage and access |
//!
//! Every op records compute dispatches, buffer copies, fills and updates only, so the
//! table holds for each; inside its part the engine orders its own commands (see
//! [`crate::recorder`]).
//!
//! ```no_run
//! use drape_engine::ash::vk;
//! use drape_engine::ops::radix_sort::RadixSort;
//! use drape_engine::{Context, HostCommandBuffer, SubmitSync};
//! # fn f(ctx: &Context, timeline: vk::Semaphore, frame: u64, cmd: vk::CommandBuffer) -> drape_engine::Result<()> {
//! let keys = ctx.upload("keys", &[3u32, 1, 2])?;
//! let values = ctx.upload("values", &[0u32, 1, 2])?;
//! let sort = RadixSort::new(ctx, 3)?;
//!
//! // Submitted by the engine: wait for the host's work, signal the host's timeline.
//! let mut rec = ctx.record("sort")?;
//! sort.record(&mut rec, &keys, &values, 3, 32)?;
//! let sync = SubmitSync {
//!     wait: vec![(timeline, frame, vk::PipelineStageFlags::COMPUTE_SHADER)],
//!     signal: vec![(timeline, frame + 1)],
//! };
//! let submission = rec.submit(&sync)?; // returns at once
//! // ... the host's own work ...
//! let timings = submission.wait()?; // or poll submission.is_complete()
//!
//! // Recorded into the host's command buffer: the host submits it.
//! let mut rec = ctx.record("sort")?;
//! sort.record(&mut rec, &keys, &values, 3, 32)?;
//! // SAFETY: cmd is recording, of the context's queue family, and completes before
//! // `recorded` is dropped.
//! let host = unsafe { HostCommandBuffer::new(cmd, None) };
//! let recorded = rec.record_into(&host)?;
//! // ... the host ends, submits and waits for cmd ...
//! drop(recorded);
//! # Ok(()) }
//! ```

use std::time::Instant;

use ash::vk;

use crate::error::{EngineError, Result, VkResultExt};
use crate::recorder::{PassTimings, Recording};

/// Semaphores a submission waits on and signals. A timeline semaphore takes the value
/// given; a binary one ignores it (give 0). Timeline values need the device's
/// `timelineSemaphore` feature ([`crate::DeviceInfo::timeline_semaphore`]).
#[derive(Clone, Debug, Default)]
pub struct SubmitSync {
    /// (semaphore, value, the stages of this submission that wait for it).
    pub wait: Vec<(vk::Semaphore, u64, vk::PipelineStageFlags)>,
    /// (semaphore, value) signalled when the submission completes.
    pub signal: Vec<(vk::Semaphore, u64)>,
}

/// A submitted recording: [`wait`](Submission::wait) for it (one fence wait, counted by
/// [`crate::Context::fence_waits`]) or poll it with [`is_complete`](Submission::is_complete).
/// The buffers the recording bound stay borrowed until it is waited or dropped; dropping
/// it without a wait waits. Leaking it (`mem::forget`) leaks its pools and fence; buffers
/// dropped while its work may run are destroyed after it finishes, without a wait.
#[must_use = "dropping a submission waits for it"]
pub struct Submission<'a> {
    rec: Option<Recording<'a>>,
    fence: vk::Fence,
    started: Instant,
}

impl<'a> Recording<'a> {
    /// Ends the recording and submits it with `sync`'s semaphores, without waiting.
    pub fn submit(mut self, sync: &SubmitSync) -> Result<Submission<'a>> {
        self.end()?;
        let ctx = self.context().clone();
        let dev = &ctx.device.raw;
        let label = self.label().to_string();
        // SAFETY: a fence on a valid device.
        let fence = unsafe { dev.create_fence(&vk::FenceCreateInfo::default(), None) }
            .vk("vkCreateFence", &label)?;
        let cmds = [self.command_buffer()];
        let wait_semaphores: Vec<vk::Semaphore> = sync.wait.iter().map(|w| w.0).collect();
        let wait_values: Vec<u64> = sync.wait.iter().map(|w| w.1).collect();
        let wait_stages: Vec<vk::PipelineStageFlags> = sync.wait.iter().map(|w| w.2).collect();
        let signal_semaphores: Vec<vk::Semaphore> = sync.signal.iter().map(|s| s.0).collect();
        let signal_values: Vec<u64> = sync.signal.iter().map(|s| s.1).collect();
        let mut timeline = vk::TimelineSemaphoreSubmitInfo::default()
            .wait_semaphore_values(&wait_values)
            .signal_semaphore_values(&signal_values);
        let mut submit = vk::SubmitInfo::default()
            .command_buffers(&cmds)
            .wait_semaphores(&wait_semaphores)
            .wait_dst_stage_mask(&wait_stages)
            .signal_semaphores(&signal_semaphores);
        if !sync.wait.is_empty() || !sync.signal.is_empty() {
            submit = submit.push_next(&mut timeline);
        }
        ctx.device.counters.submitted();
        self.set_reusable(false);
        let result = {
            let queue = ctx.device.queue.lock().unwrap_or_else(|p| p.into_inner());
            // SAFETY: the queue is externally synchronised by the mutex (and, for a host's
            // queue, by the host: see `external`); the command buffer is executable and
            // every buffer it names is borrowed for 'a by the Submission.
            unsafe { dev.queue_submit(*queue, &[submit], fence) }
        };
        if let Err(e) = result {
            // SAFETY: the submission failed, so the fence is unused.
            unsafe { dev.destroy_fence(fence, None) };
            return Err(crate::error::vk_error("vkQueueSubmit", &label, e));
        }
        // Registered with the device, so that buffers dropped while it runs (a leaked
        // Submission's, a frame in flight's) are freed only after it (`crate::retire`).
        ctx.device
            .pending
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .register(fence);
        Ok(Submission {
            rec: Some(self),
            fence,
            started: Instant::now(),
        })
    }

    /// Ends recording, submits, waits, and returns the GPU time of every pass.
    pub fn submit_and_wait(self) -> Result<PassTimings> {
        self.submit(&SubmitSync::default())?.wait()
    }

    /// Emits the recording into the host's command buffer instead of submitting it; the
    /// host submits (and synchronises) it. See the module header for the barriers the
    /// host places around it. On an error the host's command buffer holds part of the
    /// recording: the host must reset or free it, not submit it.
    pub fn record_into(mut self, host: &HostCommandBuffer) -> Result<HostRecorded<'a>> {
        let HostCommandBuffer { cmd, timestamps } = *host;
        // From the first command emitted the host's buffer refers to our descriptor sets:
        // on an error below, the pools are destroyed (the host discards its buffer), not
        // reset for reuse.
        self.set_reusable(false);
        let dev = self.context().device.raw.clone();
        if let Some((pool, first)) = timestamps {
            // SAFETY: by HostCommandBuffer::new's contract, cmd is recording and the
            // pool has room.
            unsafe {
                dev.cmd_write_timestamp(cmd, vk::PipelineStageFlags::TOP_OF_PIPE, pool, first)
            };
        }
        self.emit_into(cmd)?;
        if let Some((pool, first)) = timestamps {
            // SAFETY: as above.
            unsafe {
                dev.cmd_write_timestamp(
                    cmd,
                    vk::PipelineStageFlags::BOTTOM_OF_PIPE,
                    pool,
                    first + 1,
                )
            };
        }
        // The host's command buffer holds our descriptor sets and query pools until it
        // completes: the pools stay out of reuse until the HostRecorded is dropped.
        Ok(HostRecorded { rec: Some(self) })
    }
}

/// The host's command buffer, for [`Recording::record_into`] and
/// [`FramesInFlight::record_into`].
#[derive(Clone, Copy, Debug)]
pub struct HostCommandBuffer {
    cmd: vk::CommandBuffer,
    timestamps: Option<(vk::QueryPool, u32)>,
}

impl HostCommandBuffer {
    /// Names the host's command buffer. With `timestamps` = (pool, first query), a
    /// timestamp is written into the host's pool before the engine's commands (first)
    /// and after them (first + 1); the host resets those queries before.
    ///
    /// # Safety
    /// `cmd` is a primary command buffer of the context's device in the recording
    /// state, from a pool of the context's queue family
    /// ([`crate::Context::queue_family`]); the host submits it, and the work completes
    /// before the [`HostRecorded`] is dropped or its timings read, before any buffer the
    /// work uses is dropped, and, through [`FramesInFlight::record_into`], before the
    /// ring records into the same slot again ([`FramesInFlight::len`] frames later),
    /// waits for all, or is dropped (if a recording into it fails, the host resets or
    /// frees `cmd` instead of submitting it); the query pool, if given, is a timestamp
    /// pool of the device with room for two queries from `first`, reset before.
    pub unsafe fn new(cmd: vk::CommandBuffer, timestamps: Option<(vk::QueryPool, u32)>) -> Self {
        Self { cmd, timestamps }
    }
}

impl<'a> Submission<'a> {
    /// Waits for the submission, and returns its passes' GPU times.
    pub fn wait(mut self) -> Result<PassTimings> {
        self.wait_inner()
    }

    /// Whether the submission has completed (no wait).
    pub fn is_complete(&self) -> Result<bool> {
        let rec = self.rec.as_ref().expect("present until waited");
        // SAFETY: the fence belongs to the device.
        unsafe { rec.context().device.raw.get_fence_status(self.fence) }
            .vk("vkGetFenceStatus", rec.label())
    }

    fn wait_inner(&mut self) -> Result<PassTimings> {
        let mut rec = self.rec.take().expect("waited once");
        let ctx = rec.context().clone();
        let dev = &ctx.device.raw;
        ctx.device.counters.waited();
        // SAFETY: the fence belongs to this device and was submitted with the recording;
        // only this submission destroys it.
        let waited = unsafe { dev.wait_for_fences(&[self.fence], true, u64::MAX) };
        if !matches!(waited, Ok(()) | Err(vk::Result::ERROR_DEVICE_LOST)) {
            // Completion unknown: the fence stays registered (buffers keep waiting for
            // it) and the pools are forgotten rather than reset under pending work.
            rec.leak_pools();
            return Err(crate::error::vk_error(
                "vkWaitForFences",
                rec.label(),
                waited.err().unwrap_or(vk::Result::ERROR_UNKNOWN),
            ));
        }
        {
            let mut pending = ctx.device.pending.lock().unwrap_or_else(|p| p.into_inner());
            pending.unregister(self.fence);
            // SAFETY: signalled, or the device is lost; either way it is unused now, and
            // no longer registered (removed under the lock retire_finished polls under).
            unsafe { dev.destroy_fence(self.fence, None) };
        }
        self.fence = vk::Fence::null();
        ctx.device.retire_finished();
        match waited {
            Ok(()) => rec.completed(self.started.elapsed().as_secs_f64() * 1e3),
            Err(vk::Result::ERROR_DEVICE_LOST) => Err(EngineError::DeviceLost {
                pass: rec.last_pass(),
            }),
            Err(e) => Err(crate::error::vk_error("vkWaitForFences", rec.label(), e)),
        }
    }

    /// Forgets the borrows of the recording's buffers. For [`FramesInFlight`] only,
    /// which keeps the resources the recording bound alive and unlent until it waits.
    fn into_static(self) -> Submission<'static> {
        // SAFETY: the two types differ only in the lifetime of the recording's borrows
        // (PhantomData); the caller (FramesInFlight) upholds them itself.
        unsafe { std::mem::transmute::<Submission<'a>, Submission<'static>>(self) }
    }
}

impl Drop for Submission<'_> {
    fn drop(&mut self) {
        if self.rec.is_some() {
            // A failed wait leaves the pools unreusable (the recording destroys them).
            let _ = self.wait_inner();
        }
    }
}

/// A recording emitted into the host's command buffer ([`Recording::record_into`]): keep
/// it until the host's submission completed; then drop it (its pools return to the
/// context) or read the passes' GPU times with [`timings`](HostRecorded::timings).
#[must_use = "the host's command buffer uses this recording's descriptor sets until it completes"]
pub struct HostRecorded<'a> {
    rec: Option<Recording<'a>>,
}

impl HostRecorded<'_> {
    /// After the host's submission completed: the GPU time of each pass.
    pub fn timings(mut self) -> Result<PassTimings> {
        let mut rec = self.rec.take().expect("present until consumed");
        rec.completed(0.0)
    }
}

impl Drop for HostRecorded<'_> {
    fn drop(&mut self) {
        if let Some(mut rec) = self.rec.take() {
            // By the contract of record_into the host's submission has completed.
            rec.set_reusable(true);
        }
    }
}

/// A ring of per-frame resources for frames in flight: frame `i` records into slot
/// `i mod k`, after waiting for the frame that last used the slot (if it is still in
/// flight), so over N frames the host waits N − k times and never for the device to go
/// idle. The recording of a frame may bind only its slot's resources or `'static` data
/// (the closure is generic over the slot's lifetime, and `T: 'static`), which is what
/// lets a slot's submission stay pending after the call returns.
pub struct FramesInFlight<T: 'static> {
    slots: Vec<Slot<T>>,
    next: usize,
}

struct Slot<T> {
    // Declared (so dropped) before the resources it borrows.
    pending: Option<Pending>,
    // Boxed: pending submissions borrow into it, so it must not move with the Vec.
    resources: Box<T>,
    last_timings: Option<PassTimings>,
}

/// A slot's frame in flight: the engine's submission, or the host's command buffer.
enum Pending {
    Engine(Submission<'static>),
    Host(HostRecorded<'static>),
}

impl Pending {
    /// Waits for an engine submission; a host frame has completed by the contract of
    /// [`FramesInFlight::record_into`].
    fn finish(self) -> Result<PassTimings> {
        match self {
            Pending::Engine(s) => s.wait(),
            Pending::Host(h) => h.timings(),
        }
    }
}

impl<T: 'static> FramesInFlight<T> {
    /// A ring of `resources.len()` frames in flight (at least 1).
    pub fn new(resources: Vec<T>) -> Self {
        assert!(
            !resources.is_empty(),
            "frames in flight need at least one slot"
        );
        let slots = resources
            .into_iter()
            .map(|r| Slot {
                pending: None,
                resources: Box::new(r),
                last_timings: None,
            })
            .collect();
        Self { slots, next: 0 }
    }

    /// Frames in flight at most.
    pub fn len(&self) -> usize {
        self.slots.len()
    }

    /// Always false (a ring has a slot).
    pub fn is_empty(&self) -> bool {
        false
    }

    /// The slot the next frame records into, after waiting for the frame that used it
    /// last (if pending): for host-side work between frames (reading that frame's
    /// results, growing buffers). Returns the slot's index and its last frame's times.
    pub fn next_slot(&mut self) -> Result<(usize, &mut T, Option<&PassTimings>)> {
        let i = self.next;
        let slot = &mut self.slots[i];
        if let Some(pending) = slot.pending.take() {
            slot.last_timings = Some(pending.finish()?);
        }
        Ok((i, &mut *slot.resources, slot.last_timings.as_ref()))
    }

    /// Records the next frame with `record` (given the slot's resources; it returns the
    /// recording), submits it with `sync` and moves on to the next slot, without waiting.
    pub fn submit<F>(&mut self, sync: &SubmitSync, record: F) -> Result<usize>
    where
        F: for<'r> FnOnce(&'r mut T) -> Result<Recording<'r>>,
    {
        self.record_next(record, |rec| {
            Ok(Pending::Engine(rec.submit(sync)?.into_static()))
        })
    }

    /// Records the next frame with `record` into the host's command buffer (see
    /// [`Recording::record_into`]; the frame must complete before the ring comes back to
    /// its slot, by [`HostCommandBuffer::new`]'s contract) and moves on to the next slot.
    pub fn record_into<F>(&mut self, host: &HostCommandBuffer, record: F) -> Result<usize>
    where
        F: for<'r> FnOnce(&'r mut T) -> Result<Recording<'r>>,
    {
        self.record_next(record, |rec| {
            let recorded = rec.record_into(host)?;
            // HostCommandBuffer::new's contract has the frame complete before the slot is
            // lent again or dropped.
            // SAFETY: the types differ only in the lifetime of the recording's borrows.
            Ok(Pending::Host(unsafe {
                std::mem::transmute::<HostRecorded<'_>, HostRecorded<'static>>(recorded)
            }))
        })
    }

    /// Records the next slot's frame with `record` and hands the recording to `pending`
    /// (which submits it or emits it into the host's buffer and keeps what stays in
    /// flight); then moves on. The pending work borrows the slot's boxed resources only
    /// (`record` is generic over their lifetime), which are lent out again only after
    /// `next_slot` finished it, and dropped only after Drop did.
    fn record_next<F>(
        &mut self,
        record: F,
        pending: impl for<'r> FnOnce(Recording<'r>) -> Result<Pending>,
    ) -> Result<usize>
    where
        F: for<'r> FnOnce(&'r mut T) -> Result<Recording<'r>>,
    {
        let (i, _, _) = self.next_slot()?;
        let slot = &mut self.slots[i];
        slot.pending = Some(pending(record(&mut slot.resources)?)?);
        self.next = (i + 1) % self.slots.len();
        Ok(i)
    }

    /// Waits for every frame in flight; then each slot's resources may be changed.
    pub fn wait_all(&mut self) -> Result<()> {
        for slot in &mut self.slots {
            if let Some(p) = slot.pending.take() {
                slot.last_timings = Some(p.finish()?);
            }
        }
        Ok(())
    }

    /// Every slot's resources, after waiting for every frame in flight.
    pub fn all_mut(&mut self) -> Result<impl Iterator<Item = &mut T>> {
        self.wait_all()?;
        Ok(self.slots.iter_mut().map(|s| &mut *s.resources))
    }

    /// Makes slot `i` the one the next frame records into (after waiting for it, as
    /// always): to render a frame again in the slot whose buffers just grew.
    pub fn set_next(&mut self, i: usize) {
        assert!(i < self.slots.len(), "slot {i} of {}", self.slots.len());
        self.next = i;
    }

    /// Gives up slot `i`'s frame recorded into the host's command buffer that the host
    /// will not submit (it failed to acquire an image, say, and resets or frees that
    /// command buffer instead): the recording's pools return to the context without its
    /// timestamps being read, which would wait for work that never runs. The host must
    /// not submit that command buffer afterwards. An engine frame in the slot was
    /// submitted already: it is waited for, as usual. Returns whether a host frame was
    /// given up.
    pub fn abandon(&mut self, i: usize) -> Result<bool> {
        assert!(i < self.slots.len(), "slot {i} of {}", self.slots.len());
        let slot = &mut self.slots[i];
        slot.last_timings = None;
        match slot.pending.take() {
            // Dropping it returns its pools, as after a completed host frame.
            Some(Pending::Host(host)) => {
                drop(host);
                Ok(true)
            }
            Some(engine) => {
                slot.last_timings = Some(engine.finish()?);
                Ok(false)
            }
            None => Ok(false),
        }
    }

    /// Whether slot `i` has a frame in flight.
    pub fn is_pending(&self, i: usize) -> bool {
        self.slots[i].pending.is_some()
    }
}

impl<T: 'static> Drop for FramesInFlight<T> {
    fn drop(&mut self) {
        // Pending submissions borrow the resources: wait for them before either goes.
        for slot in &mut self.slots {
            drop(slot.pending.take());
        }
    }
}
