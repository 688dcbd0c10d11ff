//! Command recording: named compute passes bound through typed bindings, barriers
//! derived from the kernels' declared accesses, copies and fills, per-pass GPU
//! timestamps, and a breadcrumb written as each pass starts so that a lost device
//! reports the pass that was running.
//!
//! A pass names its kernel's bindings struct (generated from the manifest, see
//! [`crate::bindings`]), its push constants and its grid:
//! `rec.dispatch("sort.scatter", kernels::radix_sort::Scatter { keys_in: keys.read(), keys_out: out.write(), .. }, &params, [groups, 1, 1])?`.
//! A binding left out, one the kernel lacks, a read-only buffer where the kernel writes
//! and push constants of another type do not compile; a kernel chosen at run time among
//! variants with the same bindings goes through [`Recording::dispatch_as`].
//!
//! Barriers are not placed by hand. Commands (dispatches, copies, fills, updates) are
//! collected with the buffers they read and write, and each is scheduled into the first
//! *wave* after every earlier command it conflicts with: one that wrote a buffer it
//! reads or writes, or read a buffer it writes (a dispatch's accesses are its
//! bindings' declared ones). At submission the waves are recorded in order with one
//! barrier between consecutive waves. So no dependency can be forgotten, commands that
//! share only read-only data never wait for each other, and independent chains of
//! passes (three renders of one frame) interleave wave by wave and overlap. The
//! barrier is a global compute+transfer memory barrier. Buffers
//! are borrowed for the recording's lifetime `'a`, so none can be dropped while the
//! GPU may still use it.

use std::collections::{BTreeMap, HashMap};
use std::marker::PhantomData;

use ash::vk;

use crate::bindings::{Bindings, Bound};
use crate::buffer::{Buffer, BufferDesc};
use crate::context::Context;
use crate::error::{EngineError, Result, VkResultExt};
use crate::kernels::{Kernel, PUSH_CONSTANT_BYTES};
use crate::pools::RecordingPools;

/// Descriptor sets per descriptor pool; another pool is made when one fills up.
const SETS_PER_POOL: u32 = 64;
/// Most bindings a kernel may have.
pub const MAX_BINDINGS: u32 = 16;
/// Storage-buffer and texel-buffer descriptors per pool, each (enough for every set at
/// the maximum).
const BUFFERS_PER_POOL: u32 = SETS_PER_POOL * MAX_BINDINGS;
/// Breadcrumb slots per breadcrumb buffer.
const BREADCRUMB_SLOTS: u32 = 1024;
/// Timestamp queries per query pool (two per pass).
const QUERIES_PER_POOL: u32 = 256;

/// Workgroups for `invocations` one-per-element invocations in groups of 256: one row
/// of groups while that fits the 65,535 every device allows per dimension, else a 2-D
/// grid; kernels dispatched this way index `id.y * num_workgroups.x * 256 + id.x`.
pub fn flat_grid(invocations: u32) -> [u32; 3] {
    // In u64: `invocations + 255` must not wrap for counts near 2^32.
    let groups = (u64::from(invocations).div_ceil(256)) as u32;
    if groups <= 65_535 {
        [groups, 1, 1]
    } else {
        [65_535, groups.div_ceil(65_535), 1]
    }
}

/// GPU time of each pass of one submission, in recording order.
#[derive(Clone, Debug, Default)]
pub struct PassTimings {
    /// (pass name, milliseconds). Empty when the queue has no timestamps.
    pub passes: Vec<(String, f64)>,
    /// Each pass's scope ([`Recording::set_scope`]: the layer or render it belongs to;
    /// empty for none), in the order of `passes`.
    pub scopes: Vec<String>,
    /// Each pass's (start, end) in milliseconds from the submission's first timestamp,
    /// in the order of `passes`. Passes the recorder left free to overlap have
    /// overlapping intervals.
    pub intervals: Vec<(f64, f64)>,
}

impl PassTimings {
    /// Milliseconds per pass name, summed over passes of the same name.
    pub fn by_name(&self) -> BTreeMap<String, f64> {
        let mut out = BTreeMap::new();
        for (name, ms) in &self.passes {
            *out.entry(name.clone()).or_insert(0.0) += ms;
        }
        out
    }

    /// GPU time per scope ([`Recording::set_scope`]; unscoped passes left out): the
    /// union of the scope's passes' intervals, so passes of one scope that ran side by
    /// side are not counted twice (scopes that ran side by side each count the time).
    pub fn by_scope(&self) -> BTreeMap<String, f64> {
        let mut spans: BTreeMap<&str, Vec<(f64, f64)>> = BTreeMap::new();
        for (scope, &interval) in self.scopes.iter().zip(&self.intervals) {
            if !scope.is_empty() {
                spans.entry(scope.as_str()).or_default().push(interval);
            }
        }
        spans
            .into_iter()
            .map(|(scope, s)| (scope.to_string(), union_ms(s)))
            .collect()
    }

    /// Sum over all passes (counts time twice where passes overlapped).
    pub fn total_ms(&self) -> f64 {
        self.passes.iter().map(|(_, ms)| ms).sum()
    }

    /// GPU time during which at least one pass ran: the union of the passes'
    /// intervals, so passes that overlapped are not counted twice.
    pub fn busy_ms(&self) -> f64 {
        union_ms(self.intervals.clone())
    }

    /// Appends another submission's passes (its intervals after this one's).
    pub fn extend(&mut self, other: PassTimings) {
        let offset = self.intervals.iter().map(|i| i.1).fold(0.0, f64::max);
        self.passes.extend(other.passes);
        self.scopes.extend(other.scopes);
        self.intervals.extend(
            other
                .intervals
                .into_iter()
                .map(|(s, e)| (s + offset, e + offset)),
        );
    }
}

/// The length of the union of `spans` (start, end), in their unit.
fn union_ms(mut spans: Vec<(f64, f64)>) -> f64 {
    spans.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut busy = 0.0;
    let mut current: Option<(f64, f64)> = None;
    for (start, end) in spans {
        current = match current {
            Some((s, e)) if start <= e => Some((s, e.max(end))),
            Some((s, e)) => {
                busy += e - s;
                Some((start, end))
            }
            None => Some((start, end)),
        };
    }
    busy + current.map_or(0.0, |(s, e)| e - s)
}

/// One command buffer being recorded.
pub struct Recording<'a> {
    ctx: Context,
    label: String,
    pools: RecordingPools,
    cmd: vk::CommandBuffer,
    descriptor_pools_used: usize,
    sets_left: u32,
    query_pools_used: usize,
    /// False from submission until its wait succeeded: a failed submission's pools
    /// are destroyed, not reused.
    reusable: bool,
    /// The pools were forgotten ([`Recording::leak_pools`]): nothing to return.
    leaked: bool,
    passes: Vec<String>,
    /// Each emitted pass's scope, in the order of `passes`.
    pass_scopes: Vec<String>,
    /// The scope passes recorded now get ([`Recording::set_scope`]).
    scope: String,
    /// One 4-byte slot per pass, set to 1 when the pass starts (slots, not one shared
    /// word, so that passes free to overlap do not race on it).
    breadcrumbs: Vec<Buffer>,
    /// Commands in program order with the wave each was scheduled into (see
    /// [`Recording::schedule`]); emitted wave by wave at submission.
    commands: Vec<(u32, Command)>,
    /// Per buffer (and host image), the last wave that wrote it and the last wave that
    /// read it.
    last_write: HashMap<Resource, u32>,
    last_read: HashMap<Resource, u32>,
    _buffers: PhantomData<&'a Buffer>,
}

impl Context {
    /// Starts a command buffer; `label` names it in errors.
    pub fn record<'a>(&self, label: &str) -> Result<Recording<'a>> {
        let dev = &self.device.raw;
        let pools = self
            .device
            .pools
            .take(dev, self.device.queue_family, label)?;
        let cmd = pools.cmd;
        let rec = Recording {
            ctx: self.clone(),
            label: label.to_string(),
            pools,
            cmd,
            descriptor_pools_used: 0,
            sets_left: 0,
            query_pools_used: 0,
            reusable: true,
            leaked: false,
            passes: Vec::new(),
            pass_scopes: Vec::new(),
            scope: String::new(),
            breadcrumbs: Vec::new(),
            commands: Vec::new(),
            last_write: HashMap::new(),
            last_read: HashMap::new(),
            _buffers: PhantomData,
        };
        let begin = vk::CommandBufferBeginInfo::default()
            .flags(vk::CommandBufferUsageFlags::ONE_TIME_SUBMIT);
        // SAFETY: a fresh primary command buffer, or one whose pool was reset.
        unsafe { dev.begin_command_buffer(rec.cmd, &begin) }.vk("vkBeginCommandBuffer", label)?;
        self.set_name(rec.cmd, label);
        Ok(rec)
    }
}

/// An image the host owns that a recording copies into ([`Recording::copy_to_image`]).
///
/// Barriers on the host's side (the engine orders only its own buffers): before the
/// engine's work, the image must be in `layout` (`TRANSFER_DST_OPTIMAL` or `GENERAL`)
/// with its earlier accesses made available to `VK_PIPELINE_STAGE_TRANSFER_BIT` /
/// `VK_ACCESS_TRANSFER_WRITE_BIT`; after it, the host's reads need a barrier from
/// `TRANSFER` / `TRANSFER_WRITE` (for an engine submission, a semaphore it signals and
/// the host waits on at `TRANSFER` or later does that).
#[derive(Clone, Copy, Debug)]
pub struct ImageTarget {
    image: vk::Image,
    layout: vk::ImageLayout,
    width: u32,
    height: u32,
    texel_bytes: u32,
}

impl ImageTarget {
    /// Names the host's image.
    ///
    /// # Safety
    /// `image` is a live image of the context's device, made with `TRANSFER_DST` usage,
    /// at least `width` x `height`, with texels of `texel_bytes` bytes, in `layout` when
    /// the work that copies into it runs, and alive until that work completed.
    pub unsafe fn new(
        image: vk::Image,
        layout: vk::ImageLayout,
        width: u32,
        height: u32,
        texel_bytes: u32,
    ) -> Self {
        Self {
            image,
            layout,
            width,
            height,
            texel_bytes,
        }
    }

    /// Width and height in texels.
    pub fn size(&self) -> (u32, u32) {
        (self.width, self.height)
    }
}

/// What the wave scheduler tracks: a buffer, or a host image a copy writes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
enum Resource {
    Buffer(vk::Buffer),
    Image(vk::Image),
}

/// A command waiting in a recording for its wave.
enum Command {
    Dispatch {
        name: String,
        scope: String,
        pipeline: vk::Pipeline,
        layout: vk::PipelineLayout,
        set: vk::DescriptorSet,
        push: Vec<u8>,
        groups: [u32; 3],
    },
    Copy {
        src: vk::Buffer,
        dst: vk::Buffer,
        region: vk::BufferCopy,
    },
    Update {
        buffer: vk::Buffer,
        data: Vec<u8>,
    },
    Fill {
        buffer: vk::Buffer,
        word: u32,
    },
    CopyToImage {
        src: vk::Buffer,
        image: vk::Image,
        layout: vk::ImageLayout,
        region: vk::BufferImageCopy,
    },
}

impl<'a> Recording<'a> {
    /// The context this recording belongs to.
    pub fn context(&self) -> &Context {
        &self.ctx
    }

    /// Names the scope (a layer, a render of a composite: any group of passes) that the
    /// passes recorded from now on belong to, for GPU time per scope
    /// ([`PassTimings::by_scope`], the profile's `gpu_scopes`); "" ends it. Pass names
    /// are unchanged.
    pub fn set_scope(&mut self, scope: &str) {
        self.scope = scope.to_string();
    }

    /// Records the compute pass `name`: `bindings`' kernel (see [`crate::bindings`])
    /// dispatched as `groups` workgroups with push constants `params` (nothing for an
    /// empty grid), after a barrier when one is needed (see [`Recording`]).
    ///
    /// The bindings are checked by the compiler; left to run time are the device's
    /// limits (a range's offset alignment, `maxStorageBufferRange`,
    /// `maxComputeWorkGroupCount`, a texel buffer's usage and size), each an error or a
    /// panic naming the pass.
    pub fn dispatch<B: Bindings<'a>>(
        &mut self,
        name: &str,
        bindings: B,
        params: &B::Params,
        groups: [u32; 3],
    ) -> Result<()> {
        let list = bindings.into_list();
        self.checked_dispatch(
            name,
            B::KERNEL,
            list.as_ref(),
            bytemuck::bytes_of(params),
            groups,
        )
    }

    /// [`dispatch`](Self::dispatch) for a kernel chosen at run time among the variants
    /// that share `bindings`' struct ([`Bindings::Kernels`]: the same binding names,
    /// accesses and push constants, so any of them is checked by the compiler).
    pub fn dispatch_as<B: Bindings<'a>>(
        &mut self,
        name: &str,
        kernel: B::Kernels,
        bindings: B,
        params: &B::Params,
        groups: [u32; 3],
    ) -> Result<()> {
        let kernel: Kernel = kernel.into();
        let list = bindings.into_list();
        self.checked_dispatch(
            name,
            kernel,
            list.as_ref(),
            bytemuck::bytes_of(params),
            groups,
        )
    }

    /// The run-time checks of a pass whose bindings are complete and of the declared
    /// accesses, then its recording.
    fn checked_dispatch(
        &mut self,
        name: &str,
        kernel: Kernel,
        buffers: &[Bound<'_>],
        push: &[u8],
        groups: [u32; 3],
    ) -> Result<()> {
        let rec = self;
        assert!(
            buffers.len() as u32 <= MAX_BINDINGS,
            "pass '{name}': more than {MAX_BINDINGS} bindings"
        );
        assert!(
            push.len() as u32 <= PUSH_CONSTANT_BYTES,
            "pass '{name}': push constants over {PUSH_CONSTANT_BYTES} bytes"
        );
        let align = rec.ctx.info().min_storage_buffer_offset_alignment;
        for (b, decl) in buffers.iter().zip(kernel.bindings()) {
            assert!(
                b.offset % align == 0,
                "pass '{name}': offset {} into '{}' is not a multiple of {align}",
                b.offset,
                b.buffer.name()
            );
            if decl.texel && !b.is_whole() {
                return Err(EngineError::Binding {
                    pass: name.to_string(),
                    kernel: kernel.entry_point(),
                    binding: decl.name.to_string(),
                    problem: format!("a texel binding reads the whole buffer through its view; bind '{}' whole, not a range", b.buffer.name()),
                });
            }
        }
        // A grid past the device's limit is a size the caller could not foresee (an op
        // sized by its input), so it is an error naming the pass, not a panic.
        let max = rec.ctx.info().max_compute_workgroup_count;
        // Likewise a binding past what one storage-buffer descriptor may cover.
        // (A texel binding's limit, maxTexelBufferElements, is checked with its view.)
        let range_limit = rec.ctx.info().max_storage_buffer_range;
        if let Some((b, _)) = buffers
            .iter()
            .zip(kernel.bindings())
            .find(|(b, decl)| !decl.texel && b.range > range_limit)
        {
            let what = format!(
                "bytes bound of buffer '{}' in pass '{name}'",
                b.buffer.name()
            );
            return Err(EngineError::too_large(
                what,
                b.range,
                range_limit,
                "the device's maxStorageBufferRange",
            ));
        }
        if let Some(axis) = (0..3).find(|&a| groups[a] > max[a]) {
            let what = format!(
                "workgroups along {} in pass '{name}' (grid {groups:?})",
                ["x", "y", "z"][axis]
            );
            return Err(EngineError::too_large(
                what,
                u64::from(groups[axis]),
                u64::from(max[axis]),
                "the device's maxComputeWorkGroupCount",
            ));
        }
        if groups.contains(&0) {
            return Ok(());
        }
        rec.record_dispatch(name, kernel, buffers, push, groups)
    }

    /// Number of pipeline barriers the recording will have: one between consecutive
    /// waves (for tests and profiles).
    pub fn barrier_count(&self) -> u32 {
        self.commands.iter().map(|c| c.0).max().unwrap_or(0)
    }

    /// Places a command that accesses `accesses` (buffer, writes) in the first wave
    /// after every wave holding an earlier command it conflicts with: one that wrote a
    /// buffer it reads or writes, or read a buffer it writes. Commands of one wave are
    /// therefore independent, and a barrier between waves orders every dependency; a
    /// chain of passes that shares only read-only data with another chain runs beside
    /// it, wave for wave, instead of after it.
    fn schedule(&mut self, accesses: &[(Resource, bool)], command: Command) {
        let mut wave = 0;
        for &(buffer, writes) in accesses {
            if let Some(&w) = self.last_write.get(&buffer) {
                wave = wave.max(w + 1);
            }
            if writes {
                if let Some(&r) = self.last_read.get(&buffer) {
                    wave = wave.max(r + 1);
                }
            }
        }
        for &(buffer, writes) in accesses {
            let last = if writes {
                &mut self.last_write
            } else {
                &mut self.last_read
            };
            let w = last.entry(buffer).or_insert(wave);
            *w = (*w).max(wave);
        }
        self.commands.push((wave, command));
    }

    /// Makes every earlier compute or transfer write visible to every later compute or
    /// transfer access, and orders every earlier access before every later one.
    fn emit_barrier(&self) {
        self.ctx.device.counters.barrier();
        let stages = vk::PipelineStageFlags::COMPUTE_SHADER | vk::PipelineStageFlags::TRANSFER;
        let barrier = vk::MemoryBarrier::default()
            .src_access_mask(vk::AccessFlags::SHADER_WRITE | vk::AccessFlags::TRANSFER_WRITE)
            .dst_access_mask(
                vk::AccessFlags::SHADER_READ
                    | vk::AccessFlags::SHADER_WRITE
                    | vk::AccessFlags::TRANSFER_READ
                    | vk::AccessFlags::TRANSFER_WRITE,
            );
        // SAFETY: recording command buffer; a global memory barrier has no handles.
        unsafe {
            self.ctx.device.raw.cmd_pipeline_barrier(
                self.cmd,
                stages,
                stages,
                vk::DependencyFlags::empty(),
                &[barrier],
                &[],
                &[],
            )
        };
    }

    /// Copies the first `bytes` bytes of `src` to `dst`.
    pub fn copy(&mut self, src: &'a Buffer, dst: &'a Buffer, bytes: u64) {
        self.copy_from(src, 0, dst, bytes);
    }

    /// Copies `bytes` bytes of `src` starting at `src_offset` to the start of `dst`.
    pub fn copy_from(&mut self, src: &'a Buffer, src_offset: u64, dst: &'a Buffer, bytes: u64) {
        self.copy_region(src, src_offset, dst, 0, bytes);
    }

    /// Copies `bytes` bytes of `src` at `src_offset` to `dst` at `dst_offset`.
    pub fn copy_region(
        &mut self,
        src: &'a Buffer,
        src_offset: u64,
        dst: &'a Buffer,
        dst_offset: u64,
        bytes: u64,
    ) {
        assert!(
            src_offset + bytes <= src.size && dst_offset + bytes <= dst.size,
            "copy of {bytes} bytes at {src_offset} from '{}' to '{}' at {dst_offset}",
            src.name(),
            dst.name()
        );
        if bytes == 0 {
            return;
        }
        let region = vk::BufferCopy::default()
            .src_offset(src_offset)
            .dst_offset(dst_offset)
            .size(bytes);
        self.schedule(
            &[
                (Resource::Buffer(src.raw), false),
                (Resource::Buffer(dst.raw), true),
            ],
            Command::Copy {
                src: src.raw,
                dst: dst.raw,
                region,
            },
        );
    }

    /// Writes `data` (at most 65,536 bytes, a multiple of 4) to the start of `buffer`
    /// from the command buffer itself (`vkCmdUpdateBuffer`): small per-frame parameters
    /// without a staging copy or a submission of their own.
    pub fn update<T: bytemuck::Pod>(&mut self, buffer: &'a Buffer, data: &[T]) {
        let bytes: &[u8] = bytemuck::cast_slice(data);
        assert!(
            bytes.len() <= 65_536 && bytes.len() % 4 == 0 && bytes.len() as u64 <= buffer.size,
            "update of {} bytes into '{}' of {} bytes (at most 65,536, a multiple of 4)",
            bytes.len(),
            buffer.name(),
            buffer.size
        );
        if bytes.is_empty() {
            return;
        }
        self.schedule(
            &[(Resource::Buffer(buffer.raw), true)],
            Command::Update {
                buffer: buffer.raw,
                data: bytes.to_vec(),
            },
        );
    }

    /// Fills the whole of `buffer` with the 32-bit `word`.
    pub fn fill(&mut self, buffer: &'a Buffer, word: u32) {
        self.schedule(
            &[(Resource::Buffer(buffer.raw), true)],
            Command::Fill {
                buffer: buffer.raw,
                word,
            },
        );
    }

    /// Copies `src` (tightly packed texels, row-major from the top row, in the image's
    /// format: 16 bytes a pixel for `R32G32B32A32_SFLOAT`) into mip 0, layer 0 of the
    /// host's image (see [`ImageTarget`] for the barriers the host places around it).
    pub fn copy_to_image(&mut self, src: &'a Buffer, target: &ImageTarget) {
        assert!(
            src.size
                >= u64::from(target.width)
                    * u64::from(target.height)
                    * u64::from(target.texel_bytes),
            "copy of '{}' ({} bytes) into a {}x{} image of {}-byte texels",
            src.name(),
            src.size,
            target.width,
            target.height,
            target.texel_bytes
        );
        let region = vk::BufferImageCopy::default()
            .image_subresource(
                vk::ImageSubresourceLayers::default()
                    .aspect_mask(vk::ImageAspectFlags::COLOR)
                    .layer_count(1),
            )
            .image_extent(vk::Extent3D {
                width: target.width,
                height: target.height,
                depth: 1,
            });
        self.schedule(
            &[
                (Resource::Buffer(src.raw), false),
                (Resource::Image(target.image), true),
            ],
            Command::CopyToImage {
                src: src.raw,
                image: target.image,
                layout: target.layout,
                region,
            },
        );
    }

    fn record_dispatch(
        &mut self,
        name: &str,
        kernel: Kernel,
        buffers: &[Bound<'_>],
        push: &[u8],
        groups: [u32; 3],
    ) -> Result<()> {
        let pipeline = self.ctx.pipeline(kernel)?;
        let max_texels = self.ctx.info().max_texel_buffer_elements;
        let views: Vec<[vk::BufferView; 1]> = buffers
            .iter()
            .zip(kernel.bindings())
            .map(|(b, decl)| {
                if !decl.texel {
                    return Ok([vk::BufferView::null()]);
                }
                if !b.buffer.texel_readable(max_texels) {
                    let texels = b.buffer.vk_size() / 4;
                    let problem = if texels > max_texels {
                        format!("'{}' holds {texels} f32s, past the device's maxTexelBufferElements ({max_texels})", b.buffer.name())
                    } else {
                        format!("'{}' was not made for texel reads (it needs UNIFORM_TEXEL_BUFFER usage: BufferDesc::gpu_only or host_written)", b.buffer.name())
                    };
                    return Err(EngineError::Binding { pass: name.to_string(), kernel: kernel.entry_point(), binding: decl.name.to_string(), problem });
                }
                if decl.texel4 && b.buffer.vk_size() % 16 != 0 {
                    // A 4-float view covers whole texels: the tail would read as zeros.
                    let problem = format!("'{}' holds {} bytes, not a whole number of 16-byte texels", b.buffer.name(), b.buffer.vk_size());
                    return Err(EngineError::Binding { pass: name.to_string(), kernel: kernel.entry_point(), binding: decl.name.to_string(), problem });
                }
                if decl.texel4 { b.buffer.texel4_view() } else { b.buffer.texel_view() }.map(|v| [v])
            })
            .collect::<Result<_>>()?;
        let set = self.allocate_set(pipeline.set_layout)?;
        let infos: Vec<[vk::DescriptorBufferInfo; 1]> = buffers
            .iter()
            .map(|b| {
                [vk::DescriptorBufferInfo::default()
                    .buffer(b.buffer.raw)
                    .offset(b.offset)
                    .range(b.range)]
            })
            .collect();
        let writes: Vec<vk::WriteDescriptorSet> = infos
            .iter()
            .zip(&views)
            .zip(kernel.bindings())
            .enumerate()
            .map(|(i, ((info, view), decl))| {
                let write = vk::WriteDescriptorSet::default()
                    .dst_set(set)
                    .dst_binding(i as u32)
                    .descriptor_type(decl.descriptor_type());
                if decl.texel {
                    write.texel_buffer_view(view)
                } else {
                    write.buffer_info(info)
                }
            })
            .collect();
        // SAFETY: the set is freshly allocated and not in use by any command buffer.
        unsafe { self.ctx.device.raw.update_descriptor_sets(&writes, &[]) };
        let accesses: Vec<(Resource, bool)> = buffers
            .iter()
            .zip(kernel.bindings())
            .map(|(b, decl)| (Resource::Buffer(b.buffer.raw), !decl.read_only))
            .collect();
        let command = Command::Dispatch {
            name: name.to_string(),
            scope: self.scope.clone(),
            pipeline: pipeline.raw,
            layout: pipeline.layout,
            set,
            push: push.to_vec(),
            groups,
        };
        self.schedule(&accesses, command);
        Ok(())
    }

    /// Records the scheduled commands into the command buffer, wave by wave with a
    /// barrier between waves (program order within a wave), each dispatch with its
    /// breadcrumb and timestamps.
    fn emit(&mut self) -> Result<()> {
        let mut commands = std::mem::take(&mut self.commands);
        // Stable: commands of one wave keep their program order.
        commands.sort_by_key(|c| c.0);
        let dispatches = commands
            .iter()
            .filter(|c| matches!(c.1, Command::Dispatch { .. }))
            .count() as u32;
        for index in 0..dispatches {
            self.timestamp_slot(index)?;
        }
        self.ctx.device.counters.dispatched(dispatches);
        let mut wave = 0;
        for (w, command) in commands {
            if w != wave {
                self.emit_barrier();
                wave = w;
            }
            let dev = self.ctx.device.raw.clone();
            match command {
                Command::Dispatch {
                    name,
                    scope,
                    pipeline,
                    layout,
                    set,
                    push,
                    groups,
                } => {
                    let index = self.passes.len() as u32;
                    self.write_breadcrumb(index)?;
                    let query = self.timestamp_slot(index)?;
                    // SAFETY: recording command buffer; pipeline, layout and set are alive
                    // (the pipeline is cached by the device, the set by this recording's
                    // pools), and every buffer the set names is borrowed for 'a.
                    unsafe {
                        if let Some((pool, q)) = query {
                            dev.cmd_write_timestamp(
                                self.cmd,
                                vk::PipelineStageFlags::TOP_OF_PIPE,
                                pool,
                                q,
                            );
                        }
                        dev.cmd_bind_pipeline(self.cmd, vk::PipelineBindPoint::COMPUTE, pipeline);
                        dev.cmd_bind_descriptor_sets(
                            self.cmd,
                            vk::PipelineBindPoint::COMPUTE,
                            layout,
                            0,
                            &[set],
                            &[],
                        );
                        if !push.is_empty() {
                            dev.cmd_push_constants(
                                self.cmd,
                                layout,
                                vk::ShaderStageFlags::COMPUTE,
                                0,
                                &push,
                            );
                        }
                        dev.cmd_dispatch(self.cmd, groups[0], groups[1], groups[2]);
                        if let Some((pool, q)) = query {
                            dev.cmd_write_timestamp(
                                self.cmd,
                                vk::PipelineStageFlags::BOTTOM_OF_PIPE,
                                pool,
                                q + 1,
                            );
                        }
                    }
                    self.passes.push(name);
                    self.pass_scopes.push(scope);
                }
                // SAFETY: recording command buffer; the buffers are borrowed for 'a,
                // were created with transfer usage, and the ranges were checked when the
                // command was scheduled.
                Command::Copy { src, dst, region } => unsafe {
                    dev.cmd_copy_buffer(self.cmd, src, dst, &[region])
                },
                // SAFETY: as for the copy: a recording command buffer and a checked,
                // borrowed transfer destination.
                Command::Update { buffer, data } => unsafe {
                    dev.cmd_update_buffer(self.cmd, buffer, 0, &data)
                },
                // SAFETY: as for the copy.
                Command::Fill { buffer, word } => unsafe {
                    dev.cmd_fill_buffer(self.cmd, buffer, 0, vk::WHOLE_SIZE, word)
                },
                Command::CopyToImage {
                    src,
                    image,
                    layout,
                    region,
                } => {
                    // SAFETY: as for the copy for the buffer; the image is the host's,
                    // valid and in `layout` by the contract of `copy_to_image`.
                    unsafe { dev.cmd_copy_buffer_to_image(self.cmd, src, image, layout, &[region]) }
                }
            }
        }
        Ok(())
    }

    fn allocate_set(&mut self, layout: vk::DescriptorSetLayout) -> Result<vk::DescriptorSet> {
        let dev = &self.ctx.device.raw;
        if self.sets_left == 0 {
            if self.descriptor_pools_used == self.pools.descriptor_pools.len() {
                let sizes = [
                    vk::DescriptorPoolSize::default()
                        .ty(vk::DescriptorType::STORAGE_BUFFER)
                        .descriptor_count(BUFFERS_PER_POOL),
                    vk::DescriptorPoolSize::default()
                        .ty(vk::DescriptorType::UNIFORM_TEXEL_BUFFER)
                        .descriptor_count(BUFFERS_PER_POOL),
                ];
                let info = vk::DescriptorPoolCreateInfo::default()
                    .max_sets(SETS_PER_POOL)
                    .pool_sizes(&sizes);
                // SAFETY: valid device and create info.
                let pool = unsafe { dev.create_descriptor_pool(&info, None) }
                    .vk("vkCreateDescriptorPool", &self.label)?;
                self.pools.descriptor_pools.push(pool);
            }
            // A reused pool was reset when its last recording ended.
            self.descriptor_pools_used += 1;
            self.sets_left = SETS_PER_POOL;
        }
        let layouts = [layout];
        let info = vk::DescriptorSetAllocateInfo::default()
            .descriptor_pool(self.pools.descriptor_pools[self.descriptor_pools_used - 1])
            .set_layouts(&layouts);
        // SAFETY: the pool has room (sets_left > 0, at most MAX_BINDINGS per set).
        let set = unsafe { dev.allocate_descriptor_sets(&info) }
            .vk("vkAllocateDescriptorSets", &self.label)?[0];
        self.sets_left -= 1;
        Ok(set)
    }

    fn write_breadcrumb(&mut self, index: u32) -> Result<()> {
        let chunk = (index / BREADCRUMB_SLOTS) as usize;
        if chunk == self.breadcrumbs.len() {
            let name = format!("{} breadcrumbs {chunk}", self.label);
            let mut b = self
                .ctx
                .create_buffer(&name, BufferDesc::readback(u64::from(BREADCRUMB_SLOTS) * 4))?;
            b.private_to_recording = true;
            // Zeroed by the host, not by a fill that the slots' fills would race with;
            // where the memory is not host-coherent the breadcrumbs cannot be read anyway.
            if let Some(m) = b.coherent_mapping() {
                m.fill(0);
            }
            self.breadcrumbs.push(b);
        }
        let b = &self.breadcrumbs[chunk];
        let offset = u64::from(index % BREADCRUMB_SLOTS) * 4;
        // SAFETY: recording command buffer; the breadcrumb lives as long as the recording.
        unsafe {
            self.ctx
                .device
                .raw
                .cmd_fill_buffer(self.cmd, b.raw, offset, 4, 1)
        };
        Ok(())
    }

    /// The (pool, first query) of pass `index`, or None without timestamps.
    fn timestamp_slot(&mut self, index: u32) -> Result<Option<(vk::QueryPool, u32)>> {
        if self.ctx.info().timestamp_valid_bits == 0 {
            return Ok(None);
        }
        let per_pool = QUERIES_PER_POOL / 2;
        let pool_index = (index / per_pool) as usize;
        if pool_index == self.query_pools_used {
            if pool_index == self.pools.query_pools.len() {
                let info = vk::QueryPoolCreateInfo::default()
                    .query_type(vk::QueryType::TIMESTAMP)
                    .query_count(QUERIES_PER_POOL);
                // SAFETY: valid device and create info.
                let pool = unsafe { self.ctx.device.raw.create_query_pool(&info, None) }
                    .vk("vkCreateQueryPool", &self.label)?;
                self.pools.query_pools.push(pool);
            }
            // SAFETY: recording command buffer; queries must be reset before each use.
            unsafe {
                self.ctx.device.raw.cmd_reset_query_pool(
                    self.cmd,
                    self.pools.query_pools[pool_index],
                    0,
                    QUERIES_PER_POOL,
                )
            };
            self.query_pools_used += 1;
        }
        Ok(Some((
            self.pools.query_pools[pool_index],
            (index % per_pool) * 2,
        )))
    }

    /// Records the scheduled commands and the final barrier that makes the results
    /// visible to the host, and ends the command buffer.
    pub(crate) fn end(&mut self) -> Result<()> {
        self.emit()?;
        // Results are read on the host (mapped buffers): make the writes visible there.
        self.emit_host_barrier();
        // SAFETY: recording command buffer, ended once here.
        unsafe { self.ctx.device.raw.end_command_buffer(self.cmd) }
            .vk("vkEndCommandBuffer", &self.label)
    }

    /// The command buffer (for the submission code).
    pub(crate) fn command_buffer(&self) -> vk::CommandBuffer {
        self.cmd
    }

    /// The label the recording was started with.
    pub fn label(&self) -> &str {
        &self.label
    }

    /// Marks the pools busy (a submission is pending) or reusable (it completed).
    pub(crate) fn set_reusable(&mut self, reusable: bool) {
        self.reusable = reusable;
    }

    /// After the submission completed: the passes' GPU times, added to the profile.
    pub(crate) fn completed(&mut self, wall_ms: f64) -> Result<PassTimings> {
        self.reusable = true;
        let timings = self.read_timings()?;
        if let Some(p) = self
            .ctx
            .device
            .profile
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .as_mut()
        {
            p.add_submission(&self.label, wall_ms);
            for (name, ms) in &timings.passes {
                p.add_pass(name, *ms);
            }
            for (scope, ms) in timings.by_scope() {
                p.add_scope(&scope, ms);
            }
        }
        Ok(timings)
    }

    /// Emits the scheduled commands into the host's `cmd` instead of the recording's
    /// own command buffer (see [`crate::submit`]), ending with the barrier that makes
    /// their writes visible to the host's reads of mapped buffers (as `end` does).
    pub(crate) fn emit_into(&mut self, cmd: vk::CommandBuffer) -> Result<()> {
        let own = std::mem::replace(&mut self.cmd, cmd);
        let result = self.emit();
        if result.is_ok() {
            self.emit_host_barrier();
        }
        self.cmd = own;
        result
    }

    /// Forgets the recording's pools instead of reusing or destroying them: for a
    /// submission whose completion could not be established.
    pub(crate) fn leak_pools(&mut self) {
        self.reusable = false;
        // The breadcrumbs may still be written by the pending work: forgotten too.
        std::mem::forget(std::mem::take(&mut self.breadcrumbs));
        let _ = std::mem::replace(&mut self.pools, RecordingPools::empty());
        self.leaked = true;
    }

    fn emit_host_barrier(&self) {
        self.ctx.device.counters.barrier();
        let to_host = vk::MemoryBarrier::default()
            .src_access_mask(vk::AccessFlags::SHADER_WRITE | vk::AccessFlags::TRANSFER_WRITE)
            .dst_access_mask(vk::AccessFlags::HOST_READ);
        // SAFETY: a command buffer in the recording state (ours, or the host's by
        // HostCommandBuffer::new's contract); a global barrier names no handle.
        unsafe {
            self.ctx.device.raw.cmd_pipeline_barrier(
                self.cmd,
                vk::PipelineStageFlags::COMPUTE_SHADER | vk::PipelineStageFlags::TRANSFER,
                vk::PipelineStageFlags::HOST,
                vk::DependencyFlags::empty(),
                &[to_host],
                &[],
                &[],
            )
        };
    }

    /// The last pass in recording order whose breadcrumb was written (read after a
    /// failure): the one running, or the last of those running side by side.
    pub(crate) fn last_pass(&mut self) -> String {
        let label = self.label.clone();
        let mut started = None;
        for (chunk, b) in self.breadcrumbs.iter_mut().enumerate() {
            if let Some(m) = b.coherent_mapping() {
                for (slot, word) in m.chunks_exact(4).enumerate() {
                    if word != [0, 0, 0, 0] {
                        started = Some(chunk * BREADCRUMB_SLOTS as usize + slot);
                    }
                }
            }
        }
        match started.and_then(|i| self.passes.get(i)) {
            Some(name) => format!("{name} (in '{label}')"),
            None => format!("unknown pass (in '{label}')"),
        }
    }

    fn read_timings(&self) -> Result<PassTimings> {
        let mut timings = PassTimings::default();
        if self.query_pools_used == 0 {
            return Ok(timings);
        }
        let info = self.ctx.info();
        let valid_mask = if info.timestamp_valid_bits >= 64 {
            u64::MAX
        } else {
            (1u64 << info.timestamp_valid_bits) - 1
        };
        let per_pool = QUERIES_PER_POOL / 2;
        let dev = &self.ctx.device.raw;
        let mut ticks = Vec::with_capacity(self.passes.len() * 2);
        for (p, &pool) in self.pools.query_pools[..self.query_pools_used]
            .iter()
            .enumerate()
        {
            let first = p * per_pool as usize;
            let count = (self.passes.len() - first).min(per_pool as usize);
            let mut pool_ticks = vec![0u64; count * 2];
            // SAFETY: these queries were written by the submission we waited for.
            unsafe {
                dev.get_query_pool_results(
                    pool,
                    0,
                    &mut pool_ticks,
                    vk::QueryResultFlags::TYPE_64 | vk::QueryResultFlags::WAIT,
                )
            }
            .vk("vkGetQueryPoolResults", &self.label)?;
            ticks.extend(pool_ticks.into_iter().map(|t| t & valid_mask));
        }
        let origin = ticks.iter().step_by(2).copied().min().unwrap_or(0);
        let ms = |from: u64, to: u64| {
            (to.wrapping_sub(from) & valid_mask) as f64 * info.timestamp_period_ns / 1e6
        };
        for (i, name) in self.passes.iter().enumerate() {
            let (start, end) = (ticks[2 * i], ticks[2 * i + 1]);
            timings.passes.push((name.clone(), ms(start, end)));
            timings.scopes.push(self.pass_scopes[i].clone());
            let at = ms(origin, start);
            timings.intervals.push((at, at + ms(start, end)));
        }
        Ok(timings)
    }
}

impl Drop for Recording<'_> {
    fn drop(&mut self) {
        if self.leaked {
            return;
        }
        let dev = &self.ctx.device.raw;
        let pools = std::mem::replace(&mut self.pools, RecordingPools::empty());
        if self.reusable {
            // SAFETY: the command buffer was never submitted or its submission was
            // waited for, so nothing of these pools is in use.
            unsafe { self.ctx.device.pools.recycle(dev, pools) };
            return;
        }
        // SAFETY (in destroy): not reusable means a failed submission, after which the
        // device is lost or the wait failed; nothing more will run on these objects.
        pools.destroy(dev);
    }
}
