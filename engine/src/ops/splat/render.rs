//! The GPU splatting renderer, forward and backward.
//!
//! Forward is one submission: the frame parameters (`vkCmdUpdateBuffer`),
//! `project_fwd`, a stable 32-bit radix sort of the splats by depth, `gather_counts`
//! (tiles per splat in depth order, plus a trailing 0, and their total summed without
//! wrap on the GPU), an exclusive scan, `emit_intersections` (tile ids in depth order,
//! nothing past the intersection buffers' capacity), a stable radix sort by tile id
//! over only the bits the tile count needs (so each tile's list stays in depth order)
//! of the GPU's total bounded by the capacity (`RadixSort::record_bounded`),
//! `tile_ranges` (likewise bounded) and `rasterize_fwd`. No host read sits inside the
//! frame. After it the host reads the total: past the capacity, the buffers grow and
//! the frame is rendered again (or a total past what one sort or one buffer binding
//! can hold is refused with `TooLarge`).
//! Per-Gaussian and per-intersection kernels run on `flat_grid`, so no count the
//! buffers allow passes the workgroup-count limit.
//! Backward: zero the per-splat gradients, `rasterize_bwd_atomic` (or `_cas`, or the
//! deterministic `_fixed` into a fixed-point scratch and `fixed_point::resolve`), then
//! `project_bwd` into the parameter gradients.
//! On CPU devices with subgroups of 8 the rasterizers are their subgroup twins
//! ([`RasterVariant`]). The render-only knobs `RenderSettings::half_sh` and
//! `half_splats` add a packing pass (`pack_sh_half`, `pack_splats_half`) and read
//! binary16.

use drape_shared::adam::ExceedsParams;
use drape_shared::half::{sh_half_words, ShHalfParams};
use drape_shared::splat::layout::{
    sh_coeffs, FrameParams, HalfSplat, ProjectChunk, ProjectedSplat, SplatCounts, MAX_SH_COEFFS,
    RASTER_BLOCK, SPLAT_GRAD_FLOATS, TILE_SIZES,
};

use crate::buffer::{Buffer, BufferDesc};
use crate::context::Context;
use crate::error::{EngineError, Result};
use crate::kernels;
use crate::ops::accumulate::{FixedPointScratch, Method};
use crate::ops::radix_sort::RadixSort;
use crate::ops::scan::ExclusiveScan;
use crate::ops::splat::scene::{frame_params, GaussianCloud, PinholeCamera, RenderSettings};
use crate::recorder::{flat_grid as groups, PassTimings, Recording};

/// Most tiles an image may have: `gather_counts` sums 256 splats' tile counts in u32
/// per workgroup, which cannot wrap below 2^24 tiles each. (One colour buffer within a
/// 4 GiB binding already keeps images far smaller: about 1.4M tiles.)
const MAX_TILES: u64 = 1 << 24;

/// The chunks `project_fwd` and `project_bwd` run in: as many Gaussians as one binding
/// of their SH may cover (one chunk unless the SH passes `maxStorageBufferRange`), in
/// multiples of 256 so that each chunk's SH offset (a multiple of 3,072 bytes) meets any
/// `minStorageBufferOffsetAlignment` (at most 256).
fn project_chunks(ctx: &Context, count: u32, sh_degree: u32) -> Vec<ProjectChunk> {
    let sh_bytes = 12 * sh_coeffs(sh_degree) as u64;
    let per_chunk = ((ctx.info().max_storage_buffer_range / sh_bytes) / 256 * 256)
        .clamp(256, u64::from(u32::MAX)) as u32;
    (0..count.div_ceil(per_chunk))
        .map(|c| ProjectChunk {
            first: c * per_chunk,
            len: per_chunk.min(count - c * per_chunk),
            _pad: [0; 2],
        })
        .collect()
}

/// The byte range of chunk `c`'s SH in a buffer of SH for every Gaussian.
fn sh_range(chunk: &ProjectChunk, sh_degree: u32) -> (u64, u64) {
    let sh_bytes = 12 * sh_coeffs(sh_degree) as u64;
    (
        u64::from(chunk.first) * sh_bytes,
        u64::from(chunk.len) * sh_bytes,
    )
}

fn f32_buffer(ctx: &Context, name: &str, len: usize) -> Result<Buffer> {
    ctx.create_buffer(name, BufferDesc::gpu_only(len as u64 * 4))
}

/// Which rasterizer kernels a renderer records (forward, fused and backward alike).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum RasterVariant {
    /// [`Subgroup`](Self::Subgroup) on CPU devices with subgroups of 8 lanes and ballot
    /// operations (lavapipe), [`Workgroup`](Self::Workgroup) elsewhere.
    #[default]
    Auto,
    /// One workgroup of 16 × 16 invocations per tile, batches of 256 splats staged in
    /// workgroup memory: the GPU kernels.
    Workgroup,
    /// One subgroup of 8 lanes per 8 × 4 block of a tile, splats passed between lanes by
    /// broadcasts, no workgroup memory or barriers; the backward sums each splat's
    /// gradient over the block before one atomic add per value. For llvmpipe, where a load
    /// whose address is not provably uniform is a loop over the lanes and a barrier a
    /// coroutine switch. Needs a CPU device with subgroups of exactly 8 lanes.
    Subgroup,
}

/// Whether the device can run the subgroup rasterizers: a CPU device (where they are
/// faster; on a GPU 8-invocation workgroups would waste most of each core) whose
/// subgroups are 8 lanes with ballot operations in compute.
pub fn subgroup_raster_supported(info: &crate::DeviceInfo) -> bool {
    info.kind == crate::DeviceKind::Cpu && info.subgroup_size == 8 && info.subgroup_ballot
}

/// Gaussian parameters (or their gradients) on the GPU, in the layout of
/// [`GaussianCloud`].
pub struct GaussianBuffers {
    /// Gaussians.
    pub count: u32,
    /// SH degree of `sh`.
    pub sh_degree: u32,
    /// 3 per Gaussian.
    pub means: Buffer,
    /// 3 per Gaussian.
    pub log_scales: Buffer,
    /// 4 per Gaussian (w, x, y, z).
    pub quats: Buffer,
    /// 1 per Gaussian.
    pub opacity_logits: Buffer,
    /// 3 (SH degree + 1)² per Gaussian, `[gaussian][k][channel]`.
    pub sh: Buffer,
}

impl GaussianBuffers {
    /// Uninitialised buffers for `count` Gaussians (e.g. gradients).
    pub fn new(ctx: &Context, label: &str, count: usize, sh_degree: u32) -> Result<Self> {
        let k = sh_coeffs(sh_degree);
        Ok(Self {
            count: u32::try_from(count).map_err(|_| {
                EngineError::too_large(
                    "Gaussians",
                    count as u64,
                    u64::from(u32::MAX),
                    "u32 indices",
                )
            })?,
            sh_degree,
            means: f32_buffer(ctx, &format!("{label} means"), 3 * count)?,
            log_scales: f32_buffer(ctx, &format!("{label} log_scales"), 3 * count)?,
            quats: f32_buffer(ctx, &format!("{label} quats"), 4 * count)?,
            opacity_logits: f32_buffer(ctx, &format!("{label} opacity_logits"), count)?,
            sh: f32_buffer(ctx, &format!("{label} sh"), 3 * k * count)?,
        })
    }

    /// Copies a cloud to the GPU.
    pub fn upload(ctx: &Context, label: &str, cloud: &GaussianCloud) -> Result<Self> {
        let mut b = Self::new(ctx, label, cloud.len(), cloud.sh_degree)?;
        ctx.write_buffer(&mut b.means, &cloud.means)?;
        ctx.write_buffer(&mut b.log_scales, &cloud.log_scales)?;
        ctx.write_buffer(&mut b.quats, &cloud.quats)?;
        ctx.write_buffer(&mut b.opacity_logits, &cloud.opacity_logits)?;
        ctx.write_buffer(&mut b.sh, &cloud.sh)?;
        Ok(b)
    }

    /// Copies back to the host (groups are not stored on the GPU; `groups` fills them).
    pub fn download<G: Copy + Into<u32>>(
        &mut self,
        ctx: &Context,
        groups: &[G],
    ) -> Result<GaussianCloud> {
        let n = self.count as usize;
        let k = sh_coeffs(self.sh_degree);
        Ok(GaussianCloud {
            sh_degree: self.sh_degree,
            means: ctx.read_buffer(&mut self.means, 3 * n)?,
            log_scales: ctx.read_buffer(&mut self.log_scales, 3 * n)?,
            quats: ctx.read_buffer(&mut self.quats, 4 * n)?,
            opacity_logits: ctx.read_buffer(&mut self.opacity_logits, n)?,
            sh: ctx.read_buffer(&mut self.sh, 3 * k * n)?,
            groups: groups.iter().map(|&g| g.into()).collect(),
        })
    }

    /// The five buffers in binding order.
    pub fn all(&self) -> [&Buffer; 5] {
        [
            &self.means,
            &self.log_scales,
            &self.quats,
            &self.opacity_logits,
            &self.sh,
        ]
    }

    /// Element count of each buffer, in the order of [`all`](Self::all).
    pub fn lens(&self) -> [usize; 5] {
        let n = self.count as usize;
        [3 * n, 3 * n, 4 * n, n, 3 * sh_coeffs(self.sh_degree) * n]
    }
}

/// How the backward rasterizer accumulates per-splat gradients (shared with the
/// triplane's backward).
pub use crate::ops::accumulate::Accumulation;

/// Names the state one forward pass leaves on its renderer for the backward (the
/// projected splats, the sorted intersections and tile ranges, each pixel's last
/// contributor and final transmittance; the fused frame's per-state ones): the forward
/// returns it ([`ForwardStats::saved`]), the backward takes it and refuses one from
/// another renderer, from a forward the renderer has since overwritten, or for a cloud
/// of another size ([`EngineError::StaleForward`]). The buffers stay on the renderer,
/// reused from frame to frame; this value says whose they are.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct SavedForward {
    renderer: u64,
    frame: u64,
    /// Gaussians of the forward pass.
    pub count: u32,
}

/// Renderer identities for [`SavedForward`] (0 is no renderer's).
static NEXT_RENDERER: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(1);

/// What one forward pass did.
#[derive(Clone, Debug, Default)]
pub struct ForwardStats {
    /// What the backward of this forward takes.
    pub saved: SavedForward,
    /// Tile intersections emitted.
    pub intersections: u32,
    /// Gaussians dropped for a non-finite parameter.
    pub dropped: u32,
    /// The intersections overflowed the capacity the frame was recorded with: the
    /// buffers grew and the frame was rendered again (two submissions, not one).
    pub rerendered: bool,
    /// GPU time per pass.
    pub timings: PassTimings,
}

/// Images read back from a forward pass.
#[derive(Clone, Debug)]
pub struct RenderedImage {
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// 3 per pixel, row-major.
    pub rgb: Vec<f32>,
    /// 1 per pixel: `1 − T`.
    pub alpha: Vec<f32>,
    /// `Σ wᵢ zᵢ` per pixel (divide by alpha for the expected depth of what is hit).
    pub depth: Vec<f32>,
    /// Gaussian-pixel blend steps.
    pub blend_steps: u64,
}

/// Per-pixel buffers of one image size.
struct PixelBuffers {
    rgb: Buffer,
    alpha: Buffer,
    depth: Buffer,
    contributors: Buffer,
    transmittance: Buffer,
    blended: Buffer,
}

/// A GPU renderer for up to `max_count` Gaussians at one image size; the scratch
/// buffers are kept between frames (intersection buffers grow as needed).
pub struct SplatRenderer {
    ctx: Context,
    width: u32,
    height: u32,
    max_count: u32,
    frame: Buffer,
    frame_params: FrameParams,
    splats: Buffer,
    depth_keys: Buffer,
    order: Buffer,
    counts: Buffer,
    dropped: Buffer,
    /// The intersection total as (low word, carries), from `gather_counts`.
    total: Buffer,
    depth_sort: RadixSort,
    count_scan: ExclusiveScan,
    isect_keys: Buffer,
    isect_values: Buffer,
    isect_sort: RadixSort,
    ranges: Buffer,
    pixels: PixelBuffers,
    splat_grads: Buffer,
    /// For [`Accumulation::Deterministic`]: made on the first such backward.
    fixed: Option<FixedPointScratch>,
    intersections: u32,
    /// The rasterizer kernels recorded (never `Auto`).
    raster: RasterVariant,
    /// Half-precision SH for `RenderSettings::half_sh` (made on the first such frame,
    /// for `max_count` Gaussians at degree 3), and whether the frame prepared uses it.
    sh_half: Option<Buffer>,
    half_sh: bool,
    /// [`HalfSplat`]s for `RenderSettings::half_splats` (made on the first such frame),
    /// and whether the frame prepared uses them.
    splats_half: Option<Buffer>,
    half_splats: bool,
    /// This renderer's identity and its forward passes so far (see [`SavedForward`]).
    id: u64,
    frames: u64,
    /// A forward pass was prepared (and perhaps recorded) but not yet finished.
    pending: bool,
}

impl SplatRenderer {
    /// Largest number of tile intersections one frame may have.
    pub const MAX_INTERSECTIONS: u32 = RadixSort::LIMIT;

    /// A renderer for `width × height` images of up to `max_count` Gaussians (buffers grow with the intersections).
    pub fn new(ctx: &Context, width: u32, height: u32, max_count: usize) -> Result<Self> {
        if width == 0 || height == 0 {
            return Err(EngineError::Empty {
                what: "the image",
                why: "width and height must be at least 1 pixel",
            });
        }
        // The depth sort holds every Gaussian (and the count scan one more).
        let sort_limit = u64::from(RadixSort::LIMIT.min(ExclusiveScan::LIMIT - 1));
        if max_count as u64 > sort_limit {
            return Err(EngineError::too_large(
                "Gaussians",
                max_count as u64,
                sort_limit,
                "one depth sort (65,535 workgroups of its block)",
            ));
        }
        let n = max_count as u32;
        // In u64: a 100,000 x 100,000 image has more pixels than u32 counts.
        let pixels64 = u64::from(width) * u64::from(height);
        let colour_bytes = 12 * pixels64;
        let binding = ctx.info().max_storage_buffer_range;
        if colour_bytes > binding {
            return Err(EngineError::too_large(
                format!("bytes of the colour buffer of a {width}x{height} image"),
                colour_bytes,
                binding,
                "the device's maxStorageBufferRange",
            ));
        }
        // The tile ranges are sized for the smallest tile, so every tile size fits.
        let smallest = TILE_SIZES[0];
        let [tiles_x, tiles_y] = tile_grid(width, height, smallest);
        let tiles64 = u64::from(tiles_x) * u64::from(tiles_y);
        let grid = ctx.info().max_compute_workgroup_count;
        let blocks = raster_grid(
            RasterVariant::Workgroup,
            TILE_SIZES[TILE_SIZES.len() - 1],
            width,
            height,
        );
        if tiles64 > MAX_TILES || blocks[0] > grid[0] || blocks[1] > grid[1] {
            return Err(EngineError::too_large(
                format!("{smallest}x{smallest} tiles of a {width}x{height} image"),
                tiles64,
                MAX_TILES,
                "the rasterizer (one workgroup per 16x16 block, within maxComputeWorkGroupCount)",
            ));
        }
        let pixels = pixels64 as usize;
        let tiles = tiles64 as usize;
        // Two tiles per Gaussian to start with; a frame with more grows it (and is
        // rendered again), so a renderer pays that once.
        let isect_limit =
            u64::from(Self::MAX_INTERSECTIONS).min(ctx.info().max_storage_buffer_range / 4);
        let initial_isect = (u64::from(n) * 2).clamp(4096, isect_limit) as u32;
        let splat_bytes = std::mem::size_of::<ProjectedSplat>() as u64;
        Ok(Self {
            ctx: ctx.clone(),
            width,
            height,
            max_count: n,
            frame: ctx.create_buffer(
                "splat frame",
                BufferDesc::gpu_only(std::mem::size_of::<FrameParams>() as u64),
            )?,
            frame_params: FrameParams::default(),
            splats: ctx.create_buffer(
                "splat projected",
                BufferDesc::gpu_only(splat_bytes * u64::from(n)),
            )?,
            depth_keys: f32_buffer(ctx, "splat depth keys", n as usize)?,
            order: f32_buffer(ctx, "splat depth order", n as usize)?,
            counts: f32_buffer(ctx, "splat tile counts", n as usize + 1)?,
            // Host-visible, so reading them after a frame costs no submission of its
            // own, even where device buffers go through staging copies.
            dropped: ctx.create_buffer("splat dropped counter", BufferDesc::readback(4))?,
            total: ctx.create_buffer("splat intersection total", BufferDesc::readback(8))?,
            depth_sort: RadixSort::new(ctx, n)?,
            count_scan: ExclusiveScan::new(ctx, "splat.scan", n + 1)?,
            isect_keys: f32_buffer(ctx, "splat intersection keys", initial_isect as usize)?,
            isect_values: f32_buffer(ctx, "splat intersection values", initial_isect as usize)?,
            isect_sort: RadixSort::new(ctx, initial_isect)?,
            ranges: f32_buffer(ctx, "splat tile ranges", 2 * tiles)?,
            pixels: PixelBuffers {
                rgb: f32_buffer(ctx, "splat rgb", 3 * pixels)?,
                alpha: f32_buffer(ctx, "splat alpha", pixels)?,
                depth: f32_buffer(ctx, "splat depth", pixels)?,
                contributors: f32_buffer(ctx, "splat contributors", pixels)?,
                transmittance: f32_buffer(ctx, "splat transmittance", pixels)?,
                blended: f32_buffer(ctx, "splat blend steps", pixels)?,
            },
            splat_grads: f32_buffer(ctx, "splat gradients", SPLAT_GRAD_FLOATS * n as usize)?,
            fixed: None,
            intersections: 0,
            raster: Self::resolve_variant(ctx, RasterVariant::Auto, width, height)?,
            sh_half: None,
            half_sh: false,
            splats_half: None,
            half_splats: false,
            id: NEXT_RENDERER.fetch_add(1, std::sync::atomic::Ordering::Relaxed),
            frames: 0,
            pending: false,
        })
    }

    /// `variant` as this device runs it for a `width` × `height` image.
    fn resolve_variant(
        ctx: &Context,
        variant: RasterVariant,
        width: u32,
        height: u32,
    ) -> Result<RasterVariant> {
        let info = ctx.info();
        let grid = info.max_compute_workgroup_count;
        // The subgroup kernels run one workgroup per 8 × 4 block, at every tile size.
        let blocks = TILE_SIZES.map(|t| raster_grid(RasterVariant::Subgroup, t, width, height));
        let fits = blocks.iter().all(|b| b[0] <= grid[0] && b[1] <= grid[1]);
        let tiles = [u64::from(blocks[2][0]), u64::from(blocks[2][1])];
        match variant {
            RasterVariant::Auto if subgroup_raster_supported(info) && fits => {
                Ok(RasterVariant::Subgroup)
            }
            RasterVariant::Auto | RasterVariant::Workgroup => Ok(RasterVariant::Workgroup),
            RasterVariant::Subgroup if !subgroup_raster_supported(info) => {
                Err(EngineError::MissingFeature {
                    kernel: "splat_lavapipe::rasterize_fwd",
                    feature: "a CPU device with subgroups of 8 lanes with ballot operations",
                })
            }
            RasterVariant::Subgroup if !fits => Err(EngineError::too_large(
                "8x4 blocks along an image side for the subgroup rasterizer (one workgroup each)",
                tiles[1].max(tiles[0]),
                u64::from(grid[1]),
                "the device's maxComputeWorkGroupCount",
            )),
            RasterVariant::Subgroup => Ok(RasterVariant::Subgroup),
        }
    }

    /// Chooses the rasterizer kernels (see [`RasterVariant`]); both give the same
    /// images, and gradients equal up to the order of float additions.
    pub fn set_raster_variant(&mut self, variant: RasterVariant) -> Result<()> {
        self.raster = Self::resolve_variant(&self.ctx, variant, self.width, self.height)?;
        Ok(())
    }

    /// The rasterizer kernels this renderer records (`Workgroup` or `Subgroup`).
    pub fn raster_variant(&self) -> RasterVariant {
        self.raster
    }

    /// The kernel of the chosen variant and its dispatch, given the workgroup kernel
    /// and its subgroup twin.
    pub(crate) fn raster_dispatch<K>(&self, workgroup: K, subgroup: K) -> (K, [u32; 3]) {
        let kernel = if self.raster == RasterVariant::Subgroup {
            subgroup
        } else {
            workgroup
        };
        (kernel, self.raster_grid())
    }

    /// The rasterizer's workgroup grid for the frame's tile size.
    fn raster_grid(&self) -> [u32; 3] {
        let fp = &self.frame_params;
        raster_grid(self.raster, fp.tile_size, fp.width, fp.height)
    }

    /// The image size (width, height).
    pub fn size(&self) -> (u32, u32) {
        (self.width, self.height)
    }

    /// The per-pixel outputs, for losses computed on the GPU: (rgb, alpha, depth).
    pub fn outputs(&self) -> (&Buffer, &Buffer, &Buffer) {
        (&self.pixels.rgb, &self.pixels.alpha, &self.pixels.depth)
    }

    /// The image's width in pixels.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// The image's height in pixels.
    pub fn height(&self) -> u32 {
        self.height
    }

    /// Most intersections this device can take: one sort, and one buffer binding of keys.
    pub fn max_intersections(&self) -> u64 {
        u64::from(Self::MAX_INTERSECTIONS).min(self.ctx.info().max_storage_buffer_range / 4)
    }

    fn grow_intersections(&mut self, needed: u64) -> Result<()> {
        if needed <= u64::from(self.isect_sort.max_len()) {
            return Ok(());
        }
        let limit = self.max_intersections();
        if needed > limit {
            let whose = if limit < u64::from(Self::MAX_INTERSECTIONS) {
                "the device's maxStorageBufferRange (4 bytes each)"
            } else {
                "one radix sort (65,535 workgroups of its block)"
            };
            return Err(EngineError::too_large(
                format!(
                    "tile intersections of a {}x{} frame",
                    self.width, self.height
                ),
                needed,
                limit,
                whose,
            ));
        }
        let needed = needed as u32;
        let capacity = needed
            .checked_next_power_of_two()
            .unwrap_or(needed)
            .min(limit as u32);
        self.resize_intersections(capacity)
    }

    fn resize_intersections(&mut self, capacity: u32) -> Result<()> {
        self.isect_keys = f32_buffer(&self.ctx, "splat intersection keys", capacity as usize)?;
        self.isect_values = f32_buffer(&self.ctx, "splat intersection values", capacity as usize)?;
        self.isect_sort = RadixSort::new(&self.ctx, capacity)?;
        Ok(())
    }

    /// Room for tile intersections the next frame is recorded with (it grows by itself
    /// when a frame has more).
    pub fn intersection_capacity(&self) -> u32 {
        self.isect_sort.max_len()
    }

    /// Sets the intersection capacity (at least 1): smaller to save memory, larger to
    /// spare the first frames a re-render, tiny in a test of the overflow path.
    pub fn set_intersection_capacity(&mut self, capacity: u32) -> Result<()> {
        let limit = self.max_intersections();
        if u64::from(capacity) > limit {
            return Err(EngineError::too_large(
                "intersection capacity",
                capacity.into(),
                limit,
                "one radix sort or one buffer binding",
            ));
        }
        self.resize_intersections(capacity.max(1))
    }

    /// Renders `gaussians` through `camera` into the renderer's per-pixel buffers.
    ///
    /// One submission: the frame parameters are written by the command buffer, and
    /// the intersection total stays on the GPU, where the tile sort and the tile
    /// ranges read it (bounded by the capacity). After the frame the host reads the
    /// total; if it passed the capacity, the buffers grow and the frame is recorded
    /// and rendered again (`ForwardStats::rerendered`), so no image is drawn from
    /// a truncated list. [`prepare_forward`](Self::prepare_forward),
    /// [`record_forward`](Self::record_forward) and
    /// [`finish_forward`](Self::finish_forward) do the same for several renders in one
    /// recording.
    pub fn forward(
        &mut self,
        gaussians: &GaussianBuffers,
        camera: &PinholeCamera,
        settings: &RenderSettings,
    ) -> Result<ForwardStats> {
        self.prepare_forward(gaussians, camera, settings)?;
        let mut timings = self.record_frame(gaussians)?;
        let mut stats = self.finish_forward()?;
        if stats.rerendered {
            timings.extend(self.record_frame(gaussians)?);
            stats = ForwardStats {
                rerendered: true,
                ..self.finish_forward()?
            };
        }
        stats.timings = timings;
        Ok(stats)
    }

    /// Checks `gaussians` against the renderer and sets the frame's parameters for
    /// [`record_forward`](Self::record_forward).
    pub fn prepare_forward(
        &mut self,
        gaussians: &GaussianBuffers,
        camera: &PinholeCamera,
        settings: &RenderSettings,
    ) -> Result<()> {
        assert_eq!(
            (camera.width, camera.height),
            (self.width, self.height),
            "camera size differs from the renderer's"
        );
        if gaussians.count > self.max_count {
            return Err(EngineError::too_large(
                "Gaussians",
                gaussians.count.into(),
                self.max_count.into(),
                "the renderer's capacity (SplatRenderer::new)",
            ));
        }
        settings.validate()?;
        if settings.tile_size < RASTER_BLOCK && self.raster != RasterVariant::Subgroup {
            return Err(EngineError::MissingFeature {
                kernel: "splat::rasterize_fwd",
                feature: "tiles of 8 pixels: the workgroup rasterizers walk 16x16 blocks, so tiles of 8 need the subgroup rasterizers of CPU devices (take 16 or 32)",
            });
        }
        if settings.half_sh && self.sh_half.is_none() {
            let bytes = 4 * sh_half_words(MAX_SH_COEFFS) as u64 * u64::from(self.max_count.max(1));
            self.sh_half = Some(
                self.ctx
                    .create_buffer("splat half-precision sh", BufferDesc::gpu_only(bytes))?,
            );
        }
        self.half_sh = settings.half_sh;
        if settings.half_splats && self.splats_half.is_none() {
            let bytes = std::mem::size_of::<HalfSplat>() as u64 * u64::from(self.max_count.max(1));
            self.splats_half = Some(
                self.ctx
                    .create_buffer("splat projected half", BufferDesc::gpu_only(bytes))?,
            );
        }
        self.half_splats = settings.half_splats;
        self.frame_params = frame_params(
            camera,
            settings,
            gaussians.sh_degree,
            gaussians.count as usize,
        );
        // The saved state is about to be overwritten: no earlier forward's stands.
        self.frames += 1;
        self.pending = true;
        Ok(())
    }

    /// After the submission of a recording with [`record_forward`](Self::record_forward):
    /// reads the intersection total and the dropped count. Past the capacity the
    /// buffers grow and the result says `rerendered: true`: the image is not valid and
    /// the caller records and submits the frame again (then calls this once more).
    /// A total past one sort or one binding is `TooLarge`.
    pub fn finish_forward(&mut self) -> Result<ForwardStats> {
        let ctx = self.ctx.clone();
        let words = ctx.read_buffer::<u32>(&mut self.total, 2)?;
        let total64 = u64::from(words[0]) | (u64::from(words[1]) << 32);
        let overflowed = total64 > u64::from(self.intersection_capacity());
        if overflowed {
            self.grow_intersections(total64)?;
        }
        let dropped = ctx.read_buffer::<u32>(&mut self.dropped, 1)?[0];
        self.intersections = total64 as u32;
        self.frames += 1;
        self.pending = false;
        // An overflowed frame is rendered again: its state stands for nothing.
        let saved = if overflowed {
            SavedForward::default()
        } else {
            SavedForward {
                renderer: self.id,
                frame: self.frames,
                count: self.frame_params.count,
            }
        };
        Ok(ForwardStats {
            saved,
            intersections: total64 as u32,
            dropped,
            rerendered: overflowed,
            timings: PassTimings::default(),
        })
    }

    /// The saved state of the forward pass prepared last, before
    /// [`finish_forward`](Self::finish_forward): for a backward recorded into the same
    /// recording as its forward, with no host wait between them. The recording's
    /// results stand only if `finish_forward` then reports no overflow
    /// ([`record_overflow_flag`](Self::record_overflow_flag) raises a guard on the GPU
    /// for what comes after it in the recording).
    pub fn recorded_forward(&self) -> SavedForward {
        SavedForward {
            renderer: self.id,
            frame: if self.pending {
                self.frames + 1
            } else {
                self.frames
            },
            count: self.frame_params.count,
        }
    }

    /// Records `counter[0] += 1` if the recorded forward pass's intersections outgrew
    /// the capacity (after [`record_forward`](Self::record_forward) in the same
    /// recording): a guard that work recorded later in the recording reads on the GPU.
    pub fn record_overflow_flag<'a>(
        &'a self,
        rec: &mut Recording<'a>,
        counter: &'a Buffer,
    ) -> Result<()> {
        let p = ExceedsParams::new(u64::from(self.intersection_capacity()));
        rec.dispatch(
            "guard.intersections",
            kernels::train::FlagExceeds {
                value: self.total.read(),
                counter: counter.write(),
            },
            &p,
            [1, 1, 1],
        )
    }

    /// Makes what a backward pass with `accumulation` needs (before
    /// [`record_backward`](Self::record_backward)).
    pub fn prepare_backward(&mut self, accumulation: Accumulation) -> Result<()> {
        let method = accumulation.method(&self.ctx);
        self.make_scratch(method)
    }

    /// Records [`backward`](Self::backward) into `rec` (after
    /// [`prepare_backward`](Self::prepare_backward)), with no host wait.
    #[allow(clippy::too_many_arguments)]
    pub fn record_backward<'a>(
        &'a self,
        rec: &mut Recording<'a>,
        saved: &SavedForward,
        gaussians: &'a GaussianBuffers,
        grad_rgb: &'a Buffer,
        grad_alpha: &'a Buffer,
        grad_depth: &'a Buffer,
        out: &'a GaussianBuffers,
        accumulation: Accumulation,
    ) -> Result<()> {
        // (`record_project_backward` checks `out` against `gaussians`.)
        self.check_saved("splat backward", saved, gaussians.count)?;
        let method = accumulation.method(&self.ctx);
        self.record_raster_backward(
            rec,
            gaussians.count,
            grad_rgb,
            grad_alpha,
            grad_depth,
            method,
        )?;
        self.record_project_backward(rec, gaussians, out)
    }

    /// Checks that `saved` names this renderer's last forward pass, of `count` Gaussians.
    pub(crate) fn check_saved(
        &self,
        op: &'static str,
        saved: &SavedForward,
        count: u32,
    ) -> Result<()> {
        let problem = if saved.renderer == 0 {
            "the saved state of no complete forward pass (an overflowed frame's, or a default value)".to_string()
        } else if saved.renderer != self.id {
            "another renderer's forward pass".to_string()
        } else if saved.frame != self.frames && !(self.pending && saved.frame == self.frames + 1) {
            "the saved state of an earlier forward pass, overwritten since by another".to_string()
        } else if saved.count != count {
            format!(
                "a forward pass of {} Gaussians, but {count} to back-propagate into",
                saved.count
            )
        } else {
            return Ok(());
        };
        Err(EngineError::StaleForward { op, problem })
    }

    /// Records and submits one whole forward frame with the current capacity.
    fn record_frame(&self, gaussians: &GaussianBuffers) -> Result<PassTimings> {
        let mut rec = self.ctx.record("splat forward")?;
        self.record_forward(&mut rec, gaussians)?;
        rec.submit_and_wait()
    }

    /// Records the forward pass of the frame [`prepare_forward`](Self::prepare_forward)
    /// set, with no host read inside it; after the submission,
    /// [`finish_forward`](Self::finish_forward). The renders of several renderers
    /// recorded into one recording share only what they read, so the recorder
    /// interleaves them.
    pub fn record_forward<'a>(
        &'a self,
        rec: &mut Recording<'a>,
        gaussians: &'a GaussianBuffers,
    ) -> Result<()> {
        self.record_binning(rec, gaussians)?;
        let (kernel, grid) = if self.half_splats {
            self.raster_dispatch(
                kernels::splat::RasterizeFwdKernel::SplatRasterizeFwdHalf,
                kernels::splat::RasterizeFwdKernel::SplatLavapipeRasterizeFwdHalf,
            )
        } else {
            self.raster_dispatch(
                kernels::splat::RasterizeFwdKernel::SplatRasterizeFwd,
                kernels::splat::RasterizeFwdKernel::SplatLavapipeRasterizeFwd,
            )
        };
        let p = &self.pixels;
        let (_, splats, _, _) = self.binned();
        rec.dispatch_as(
            "splat.rasterize_fwd",
            kernel,
            kernels::splat::RasterizeFwd {
                frame: self.frame.read(),
                splats: splats.read(),
                isect_values: self.isect_values.read(),
                ranges: self.ranges.read(),
                rgb: p.rgb.write(),
                alpha: p.alpha.write(),
                depth: p.depth.write(),
                contributors: p.contributors.write(),
                transmittance: p.transmittance.write(),
                blended: p.blended.write(),
            },
            &(),
            grid,
        )
    }

    /// The buffers a rasterizer reads after [`record_binning`](Self::record_binning):
    /// frame parameters, projected splats (the [`HalfSplat`]s in a half-splat frame),
    /// sorted intersection values, tile ranges.
    pub(crate) fn binned(&self) -> (&Buffer, &Buffer, &Buffer, &Buffer) {
        let splats = if self.half_splats {
            self.splats_half
                .as_ref()
                .expect("prepare_forward makes the half splats")
        } else {
            &self.splats
        };
        (&self.frame, splats, &self.isect_values, &self.ranges)
    }

    /// A backward of a frame rendered with a render-only knob is an error (before
    /// anything is recorded).
    pub(crate) fn refuse_render_only(&self) -> Result<()> {
        if self.half_sh || self.half_splats {
            return Err(EngineError::InvalidSetting { what: "render settings", problem: "a frame rendered from half-precision SH or splats (half_sh, half_splats) has no backward: they are render-only knobs".into() });
        }
        Ok(())
    }

    /// Whether the frame prepared rasterizes [`HalfSplat`]s (the `*_half` forward
    /// kernels read what [`binned`](Self::binned) returns).
    pub(crate) fn half_splats(&self) -> bool {
        self.half_splats
    }

    /// Everything of [`record_forward`](Self::record_forward) before rasterization:
    /// projection, depth sort, tile counts, intersections, tile sort and ranges (the
    /// fused rasterizer walks the same lists).
    pub(crate) fn record_binning<'a>(
        &'a self,
        rec: &mut Recording<'a>,
        gaussians: &'a GaussianBuffers,
    ) -> Result<()> {
        let n = gaussians.count;
        let fp = &self.frame_params;
        let ctx = self.ctx.clone();
        let capacity = self.intersection_capacity();
        let tiles = fp.tiles_x * fp.tiles_y;
        let tile_bits = 32 - (tiles.max(1) - 1).leading_zeros();
        let counts_pc = SplatCounts {
            count: n,
            intersections: capacity,
            use_cas: 0,
            _pad: 0,
        };
        rec.update(&self.frame, std::slice::from_ref(fp));
        rec.fill(&self.dropped, 0);
        rec.fill(&self.total, 0);
        rec.fill(&self.ranges, 0);
        for chunk in project_chunks(&ctx, n, gaussians.sh_degree) {
            let (offset, bytes) = sh_range(&chunk, gaussians.sh_degree);
            if self.half_sh {
                self.record_project_sh_half(rec, gaussians, &chunk, (offset, bytes))?;
                continue;
            }
            rec.dispatch(
                "splat.project_fwd",
                kernels::splat::ProjectFwd {
                    frame: self.frame.read(),
                    means: gaussians.means.read(),
                    log_scales: gaussians.log_scales.read(),
                    quats: gaussians.quats.read(),
                    opacity_logits: gaussians.opacity_logits.read(),
                    sh: gaussians.sh.read_range(offset, bytes),
                    splats: self.splats.write(),
                    depth_keys: self.depth_keys.write(),
                    order: self.order.write(),
                    dropped: self.dropped.write(),
                },
                &chunk,
                groups(chunk.len),
            )?;
        }
        self.depth_sort
            .record(rec, &self.depth_keys, &self.order, n, 32)?;
        rec.dispatch(
            "splat.gather_counts",
            kernels::splat::GatherCounts {
                order: self.order.read(),
                splats: self.splats.read(),
                counts: self.counts.write(),
                total: self.total.write(),
            },
            &counts_pc,
            groups(n + 1),
        )?;
        // The scan wraps past 2^32 - 1; the total from gather_counts does not, and the
        // kernels below read nothing through offsets a wrapped scan made.
        self.count_scan.record(rec, &self.counts, n + 1)?;
        rec.dispatch(
            "splat.emit_intersections",
            kernels::splat::EmitIntersections {
                frame: self.frame.read(),
                order: self.order.read(),
                splats: self.splats.read(),
                offsets: self.counts.read(),
                total: self.total.read(),
                isect_keys: self.isect_keys.write(),
                isect_values: self.isect_values.write(),
            },
            &counts_pc,
            groups(n),
        )?;
        self.isect_sort.record_bounded(
            rec,
            &self.isect_keys,
            &self.isect_values,
            capacity,
            &self.total,
            tile_bits,
        )?;
        rec.dispatch(
            "splat.tile_ranges",
            kernels::splat::TileRanges {
                isect_keys: self.isect_keys.read(),
                total: self.total.read(),
                ranges: self.ranges.write(),
            },
            &counts_pc,
            groups(capacity),
        )?;
        if let (true, Some(half)) = (self.half_splats, &self.splats_half) {
            rec.dispatch(
                "splat.pack_splats_half",
                kernels::splat::PackSplatsHalf {
                    splats: self.splats.read(),
                    half_splats: half.write(),
                },
                &counts_pc,
                groups(n),
            )?;
        }
        Ok(())
    }

    /// The projection of one chunk from half-precision SH: packs the chunk's SH
    /// (`splat.pack_sh_half`), then projects with `splat::project_fwd_sh_half`.
    fn record_project_sh_half<'a>(
        &'a self,
        rec: &mut Recording<'a>,
        gaussians: &'a GaussianBuffers,
        chunk: &ProjectChunk,
        (offset, bytes): (u64, u64),
    ) -> Result<()> {
        let sh_half = self
            .sh_half
            .as_ref()
            .expect("prepare_forward makes the half-precision SH buffer");
        let coeffs = sh_coeffs(gaussians.sh_degree);
        let words = sh_half_words(coeffs) as u64 * u64::from(chunk.len);
        let half_offset = 4 * sh_half_words(coeffs) as u64 * u64::from(chunk.first);
        let params = ShHalfParams {
            count: chunk.len,
            coeffs: coeffs as u32,
            _pad: [0; 2],
        };
        rec.dispatch(
            "splat.pack_sh_half",
            kernels::splat::PackShHalf {
                sh: gaussians.sh.read_range(offset, bytes),
                sh_half: sh_half.write_range(half_offset, 4 * words),
            },
            &params,
            groups(words as u32),
        )?;
        rec.dispatch(
            "splat.project_fwd",
            kernels::splat::ProjectFwdShHalf {
                frame: self.frame.read(),
                means: gaussians.means.read(),
                log_scales: gaussians.log_scales.read(),
                quats: gaussians.quats.read(),
                opacity_logits: gaussians.opacity_logits.read(),
                sh_half: sh_half.read_range(half_offset, 4 * words),
                splats: self.splats.write(),
                depth_keys: self.depth_keys.write(),
                order: self.order.write(),
                dropped: self.dropped.write(),
            },
            chunk,
            groups(chunk.len),
        )?;
        Ok(())
    }

    /// Reads the last forward pass's images back.
    pub fn read_image(&mut self) -> Result<RenderedImage> {
        let pixels = (self.width * self.height) as usize;
        let ctx = self.ctx.clone();
        let blended = ctx.read_buffer::<u32>(&mut self.pixels.blended, pixels)?;
        Ok(RenderedImage {
            width: self.width,
            height: self.height,
            rgb: ctx.read_buffer(&mut self.pixels.rgb, 3 * pixels)?,
            alpha: ctx.read_buffer(&mut self.pixels.alpha, pixels)?,
            depth: ctx.read_buffer(&mut self.pixels.depth, pixels)?,
            blend_steps: blended.iter().map(|&b| u64::from(b)).sum(),
        })
    }

    /// Gradients of a loss with respect to the parameters of the Gaussians of the last
    /// forward pass, given the loss's gradient on rgb (3 per pixel), alpha and depth.
    #[allow(clippy::too_many_arguments)]
    pub fn backward(
        &mut self,
        saved: &SavedForward,
        gaussians: &GaussianBuffers,
        grad_rgb: &Buffer,
        grad_alpha: &Buffer,
        grad_depth: &Buffer,
        out: &GaussianBuffers,
        accumulation: Accumulation,
    ) -> Result<PassTimings> {
        // A stale forward is refused before any scratch is made.
        self.check_saved("splat backward", saved, gaussians.count)?;
        self.prepare_backward(accumulation)?;
        let ctx = self.ctx.clone();
        let mut rec = ctx.record("splat backward")?;
        self.record_backward(
            &mut rec,
            saved,
            gaussians,
            grad_rgb,
            grad_alpha,
            grad_depth,
            out,
            accumulation,
        )?;
        rec.submit_and_wait()
    }

    /// Records the backward rasterization of the last forward pass into the per-splat
    /// gradients (`SPLAT_GRAD_FLOATS` per splat, zeroed first) from the loss's gradient
    /// on each pixel's rgb, alpha and depth.
    /// Call [`Self::make_scratch`] for `method` first.
    fn record_raster_backward<'a>(
        &'a self,
        rec: &mut Recording<'a>,
        count: u32,
        grad_rgb: &'a Buffer,
        grad_alpha: &'a Buffer,
        grad_depth: &'a Buffer,
        method: Method,
    ) -> Result<()> {
        self.refuse_render_only()?;
        let subgroup = self.raster == RasterVariant::Subgroup;
        let kernel = match method {
            Method::FloatAtomics if subgroup => {
                kernels::splat::RasterizeBwdAtomicKernel::SplatLavapipeRasterizeBwdAtomic
            }
            Method::CompareAndSwap if subgroup => {
                kernels::splat::RasterizeBwdAtomicKernel::SplatLavapipeRasterizeBwdCas
            }
            Method::FixedPoint if subgroup => {
                kernels::splat::RasterizeBwdAtomicKernel::SplatLavapipeRasterizeBwdFixed
            }
            Method::FloatAtomics => {
                kernels::splat::RasterizeBwdAtomicKernel::SplatRasterizeBwdAtomic
            }
            Method::CompareAndSwap => {
                kernels::splat::RasterizeBwdAtomicKernel::SplatRasterizeBwdCas
            }
            Method::FixedPoint => kernels::splat::RasterizeBwdAtomicKernel::SplatRasterizeBwdFixed,
        };
        let target = self.grad_target(method);
        rec.fill(target, 0);
        let p = &self.pixels;
        rec.dispatch_as(
            "splat.rasterize_bwd",
            kernel,
            kernels::splat::RasterizeBwdAtomic {
                frame: self.frame.read(),
                splats: self.splats.read(),
                isect_values: self.isect_values.read(),
                ranges: self.ranges.read(),
                contributors: p.contributors.read(),
                transmittance: p.transmittance.read(),
                grad_rgb: grad_rgb.read(),
                grad_alpha: grad_alpha.read(),
                grad_depth: grad_depth.read(),
                splat_grads: target.write(),
            },
            &(),
            self.raster_grid(),
        )?;
        self.record_grad_resolve(rec, count, method)
    }

    /// Records the projection's backward from the per-splat gradients to every
    /// Gaussian's parameters (`out`, written, not accumulated).
    pub(crate) fn record_project_backward<'a>(
        &'a self,
        rec: &mut Recording<'a>,
        gaussians: &'a GaussianBuffers,
        out: &'a GaussianBuffers,
    ) -> Result<()> {
        assert_eq!(
            out.count, gaussians.count,
            "gradient buffers are for another cloud"
        );
        assert_eq!(
            out.sh_degree, gaussians.sh_degree,
            "gradient buffers have another SH degree"
        );
        for chunk in project_chunks(&self.ctx, gaussians.count, gaussians.sh_degree) {
            let (offset, bytes) = sh_range(&chunk, gaussians.sh_degree);
            rec.dispatch(
                "splat.project_bwd",
                kernels::splat::ProjectBwd {
                    frame: self.frame.read(),
                    means: gaussians.means.read(),
                    log_scales: gaussians.log_scales.read(),
                    quats: gaussians.quats.read(),
                    opacity_logits: gaussians.opacity_logits.read(),
                    sh: gaussians.sh.read_range(offset, bytes),
                    splats: self.splats.read(),
                    splat_grads: self.splat_grads.read(),
                    grad_means: out.means.write(),
                    grad_log_scales: out.log_scales.write(),
                    grad_quats: out.quats.write(),
                    grad_opacity_logits: out.opacity_logits.write(),
                    grad_sh: out.sh.write_range(offset, bytes),
                },
                &chunk,
                groups(chunk.len),
            )?;
        }
        Ok(())
    }

    /// Where a backward rasterizer adding with `method` writes the per-splat gradients
    /// (the fixed-point scratch, resolved into them by [`Self::record_grad_resolve`]).
    /// Call [`Self::make_scratch`] first.
    pub(crate) fn grad_target(&self, method: Method) -> &Buffer {
        match method {
            Method::FixedPoint => self.fixed.as_ref().expect("the fixed-point scratch is made before a deterministic backward is recorded (FusedRenderer::prepare_backward)").buffer(),
            _ => &self.splat_grads,
        }
    }

    /// Records the fixed-point sums' conversion into the per-splat gradients of `count`
    /// splats (nothing for the float methods).
    pub(crate) fn record_grad_resolve<'a>(
        &'a self,
        rec: &mut Recording<'a>,
        count: u32,
        method: Method,
    ) -> Result<()> {
        if let (Method::FixedPoint, Some(fixed)) = (method, &self.fixed) {
            fixed.record_resolve(rec, &self.splat_grads, SPLAT_GRAD_FLOATS as u32 * count)?;
        }
        Ok(())
    }

    /// Makes the fixed-point scratch on the first backward that adds in fixed point.
    pub(crate) fn make_scratch(&mut self, method: Method) -> Result<()> {
        if method == Method::FixedPoint && self.fixed.is_none() {
            self.fixed = Some(FixedPointScratch::new(
                &self.ctx,
                "splat gradients",
                SPLAT_GRAD_FLOATS as u32 * self.max_count,
            )?);
        }
        Ok(())
    }

    /// Each splat's contribution to the last forward pass's image: the sum over the
    /// pixels of its blend weight `α · T` (its share of each pixel, the weight its colour
    /// gets there), for pruning by contribution. It is the colour gradient the backward
    /// rasterizer gives a splat when every pixel's upstream gradient on red is 1 (and 0
    /// on green, blue, alpha and depth), so it is computed by that kernel, in 64-bit
    /// fixed point (the same bits on every run). The contributions of a frame sum to the
    /// sum of its alpha image. One value per Gaussian of the forward pass `saved` names
    /// (culled ones 0).
    pub fn contributions(&mut self, saved: &SavedForward) -> Result<Vec<f32>> {
        self.check_saved("splat contributions", saved, saved.count)?;
        let count = saved.count;
        let ctx = self.ctx.clone();
        let pixels = (self.width * self.height) as usize;
        let red: Vec<f32> = (0..pixels).flat_map(|_| [1.0f32, 0.0, 0.0]).collect();
        let upstream = ctx.upload("splat contribution upstream", &red)?;
        let zeros = ctx.upload("splat contribution zeros", &vec![0.0f32; pixels])?;
        self.make_scratch(Method::FixedPoint)?;
        {
            let mut rec = ctx.record("splat contributions")?;
            self.record_raster_backward(
                &mut rec,
                count,
                &upstream,
                &zeros,
                &zeros,
                Method::FixedPoint,
            )?;
            rec.submit_and_wait()?;
        }
        let grads = self.read_splat_grads(count as usize)?;
        // Index 6 of a splat's gradient is its colour's red (`SplatGrad::to_array`).
        Ok(grads
            .chunks_exact(SPLAT_GRAD_FLOATS)
            .map(|g| g[6])
            .collect())
    }

    /// Sorted intersection keys and values, and the tile ranges, of the last forward
    /// pass (for tests and debugging).
    #[doc(hidden)]
    pub fn read_binning(&mut self) -> Result<(Vec<u32>, Vec<u32>, Vec<u32>)> {
        let ctx = self.ctx.clone();
        let m = self.intersections as usize;
        let tiles = (self.frame_params.tiles_x * self.frame_params.tiles_y) as usize;
        Ok((
            ctx.read_buffer(&mut self.isect_keys, m)?,
            ctx.read_buffer(&mut self.isect_values, m)?,
            ctx.read_buffer(&mut self.ranges, 2 * tiles)?,
        ))
    }

    /// The projected splats of the last forward pass and the per-splat gradients of
    /// the last backward pass (`ops::splat::densify` reads them on the GPU).
    pub(crate) fn splat_buffers(&self) -> (&Buffer, &Buffer) {
        (&self.splats, &self.splat_grads)
    }

    /// The projected splats of the last forward pass, for tests and references.
    #[doc(hidden)]
    pub fn read_splats(&mut self, count: usize) -> Result<Vec<ProjectedSplat>> {
        let ctx = self.ctx.clone();
        ctx.read_buffer(&mut self.splats, count)
    }

    /// The per-splat gradients of the last backward pass (10 per Gaussian), for tests.
    pub fn read_splat_grads(&mut self, count: usize) -> Result<Vec<f32>> {
        let ctx = self.ctx.clone();
        ctx.read_buffer(&mut self.splat_grads, SPLAT_GRAD_FLOATS * count)
    }
}

/// Renders a cloud once and returns the image: the one-call entry point for
/// applications that embed the engine (a frame loop keeps a [`SplatRenderer`] and
/// [`GaussianBuffers`] instead, and can read `outputs()` without leaving the GPU).
pub fn render_image(
    ctx: &Context,
    cloud: &GaussianCloud,
    camera: &PinholeCamera,
    settings: &RenderSettings,
) -> Result<(RenderedImage, ForwardStats)> {
    let gaussians = GaussianBuffers::upload(ctx, "render_image gaussians", cloud)?;
    let mut renderer = SplatRenderer::new(ctx, camera.width, camera.height, cloud.len())?;
    let stats = renderer.forward(&gaussians, camera, settings)?;
    Ok((renderer.read_image()?, stats))
}

/// The grid of `tile` × `tile` tiles of a `width` × `height` image.
fn tile_grid(width: u32, height: u32, tile: u32) -> [u32; 2] {
    [width.div_ceil(tile), height.div_ceil(tile)]
}

/// The workgroup grid of the rasterizer `variant` for tiles of side `tile`: every tile
/// of the image covered by whole blocks (16 × 16 for the workgroup kernels, 8 × 4 for
/// the subgroup ones), so the kernels find their tile by dividing the block's position.
fn raster_grid(variant: RasterVariant, tile: u32, width: u32, height: u32) -> [u32; 3] {
    let [tx, ty] = tile_grid(width, height, tile);
    match variant {
        RasterVariant::Subgroup => [tx * (tile / 8), ty * (tile / 4), 1],
        _ => {
            let per = (tile / RASTER_BLOCK).max(1);
            [tx * per, ty * per, 1]
        }
    }
}
