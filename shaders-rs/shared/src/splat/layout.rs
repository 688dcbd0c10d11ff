//! `#[repr(C)]` layouts of the splatting kernels, and the named defaults.

/// Default tile side in pixels. A tile is the unit of binning (every splat is listed in
/// each tile its extent reaches, and each tile's list is sorted by depth) and of the
/// rasterizer's walk (every pixel of a tile walks that tile's list). Smaller tiles mean
/// more intersections to sort and shorter lists to walk; the image is the same.
pub const DEFAULT_TILE_SIZE: u32 = 16;
/// The tile sides the kernels take ([`FrameParams::tile_size`]).
pub const TILE_SIZES: [u32; 3] = [8, 16, 32];
/// Side of the pixel block of one workgroup rasterizer (16 × 16 invocations): a tile
/// of 32 is 2 × 2 such blocks walking the same list; tiles of 8 need the subgroup
/// rasterizers (8 × 4 blocks).
pub const RASTER_BLOCK: u32 = 16;
/// Low-pass dilation added to the diagonal of every 2D covariance (pixels^2).
pub const DEFAULT_DILATION: f32 = 0.3;
/// Smallest alpha a splat must reach at a pixel to be blended there (also the opacity
/// below which a splat is culled).
pub const DEFAULT_ALPHA_MIN: f32 = 1.0 / 255.0;
/// Largest alpha of one splat at one pixel.
pub const DEFAULT_ALPHA_MAX: f32 = 0.99;
/// Blending stops once transmittance would fall to or below this.
pub const DEFAULT_TRANSMITTANCE_MIN: f32 = 1e-4;
/// Largest extent of a splat in standard deviations.
pub const DEFAULT_MAX_SIGMAS: f32 = 3.33;
/// The Jacobian is evaluated at the view point clamped to this many half-fields of view.
pub const DEFAULT_FOV_CLAMP: f32 = 1.3;
/// Floats of gradient per projected splat: x, y, conic a, b, c, opacity, r, g, b, depth.
pub const SPLAT_GRAD_FLOATS: usize = 10;
/// Largest supported spherical-harmonics degree.
pub const MAX_SH_DEGREE: u32 = 3;
/// Coefficients per colour channel at [`MAX_SH_DEGREE`].
pub const MAX_SH_COEFFS: usize = 16;

/// Coefficients per channel for a degree.
pub const fn sh_coeffs(degree: u32) -> usize {
    ((degree + 1) * (degree + 1)) as usize
}

/// Everything the kernels need about the camera and the render settings. Lives in a
/// small read-only storage buffer (it does not fit the guaranteed push-constant size).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[cfg_attr(not(target_arch = "spirv"), derive(bytemuck::Pod, bytemuck::Zeroable))]
pub struct FrameParams {
    /// World-to-camera rotation, row-major.
    pub rot: [f32; 9],
    /// World-to-camera translation.
    pub trans: [f32; 3],
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
    pub near: f32,
    pub far: f32,
    pub width: u32,
    pub height: u32,
    pub tiles_x: u32,
    pub tiles_y: u32,
    /// Tile side in pixels, one of [`TILE_SIZES`].
    pub tile_size: u32,
    pub background: [f32; 3],
    /// Spherical-harmonics degree of the coefficients (0 to 3).
    pub sh_degree: u32,
    /// Number of Gaussians.
    pub count: u32,
    /// 1: antialiased mode (opacity compensated for the dilation, as in Mip-Splatting).
    pub antialiased: u32,
    pub dilation: f32,
    pub alpha_min: f32,
    pub alpha_max: f32,
    pub transmittance_min: f32,
    pub max_sigmas: f32,
    pub fov_clamp: f32,
}

/// One projected Gaussian, as the rasterizer reads it.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[cfg_attr(not(target_arch = "spirv"), derive(bytemuck::Pod, bytemuck::Zeroable))]
pub struct ProjectedSplat {
    /// Centre in pixels.
    pub x: f32,
    pub y: f32,
    /// Camera-space z.
    pub depth: f32,
    /// Inverse 2D covariance (a, b, c) of [[a, b], [b, c]].
    pub conic_a: f32,
    pub conic_b: f32,
    pub conic_c: f32,
    /// Opacity after the sigmoid (and the compensation in antialiased mode).
    pub opacity: f32,
    pub r: f32,
    pub g: f32,
    pub b: f32,
    /// Tile rectangle [x0, x1) x [y0, y1).
    pub tile_x0: u32,
    pub tile_y0: u32,
    pub tile_x1: u32,
    pub tile_y1: u32,
    /// Tiles covered (0: culled).
    pub tiles: u32,
    /// [`SPLAT_DROPPED`] when a parameter was not finite.
    pub flags: u32,
}

/// A projected splat as the half-precision rasterizers read it
/// (`RenderSettings::half_splats`, a render-only knob): the centre stays f32 (past 2048
/// pixels a half cannot tell neighbouring pixels apart), conic, opacity, colour and
/// depth are binary16 (`drape_shared::half`, round to nearest even), two to a word:
/// 6 words where the rasterizers read 10.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[cfg_attr(not(target_arch = "spirv"), derive(bytemuck::Pod, bytemuck::Zeroable))]
pub struct HalfSplat {
    pub x: f32,
    pub y: f32,
    /// conic a (low half), conic b (high half).
    pub conic_ab: u32,
    /// conic c, opacity.
    pub conic_c_opacity: u32,
    /// red, green.
    pub rg: u32,
    /// blue, depth.
    pub b_depth: u32,
}

/// `ProjectedSplat::flags` bit: a parameter was NaN or infinite; the splat is culled.
pub const SPLAT_DROPPED: u32 = 1;

/// Push constants of the per-element splatting kernels.
/// Push constants of `project_fwd` and `project_bwd`: Gaussians `[first, first + len)`.
/// Their `sh` (and `grad_sh`) bindings start at Gaussian `first`, so a cloud whose SH
/// is larger than one storage-buffer binding may hold (lavapipe: 128 MiB, 699k
/// Gaussians at degree 3) is projected in chunks; every other binding is whole.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(not(target_arch = "spirv"), derive(bytemuck::Pod, bytemuck::Zeroable))]
pub struct ProjectChunk {
    pub first: u32,
    pub len: u32,
    pub _pad: [u32; 2],
}

#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(not(target_arch = "spirv"), derive(bytemuck::Pod, bytemuck::Zeroable))]
pub struct SplatCounts {
    /// Gaussians.
    pub count: u32,
    /// Tile intersections (after the scan).
    pub intersections: u32,
    /// 1: accumulate gradients with compare-and-swap loops instead of float atomics.
    pub use_cas: u32,
    pub _pad: u32,
}

/// Push constants of `train::copy_sh`: copies `count` Gaussians' SH from a buffer of
/// `src_coeffs` coefficients per channel (starting at Gaussian `src_first`) into one
/// of `dst_coeffs` (starting at `dst_first`). Layers of different SH degrees are
/// rendered together this way: a lower degree is padded with zero coefficients (the
/// same colour), and the gradient going back is truncated to the lower degree.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[cfg_attr(not(target_arch = "spirv"), derive(bytemuck::Pod, bytemuck::Zeroable))]
pub struct ShCopyParams {
    pub count: u32,
    pub src_coeffs: u32,
    pub dst_coeffs: u32,
    pub src_first: u32,
    pub dst_first: u32,
    pub _pad: [u32; 3],
}

impl ShCopyParams {
    /// Destination floats the copy writes (one invocation each).
    pub const fn floats(&self) -> u32 {
        3 * self.count * self.dst_coeffs
    }
}

/// For destination float `i` of the copy (`i < floats()`): its index in the
/// destination buffer, and the source index it takes (None: a padded coefficient, 0).
/// The layout is `[gaussian][coefficient][channel]` on both sides.
#[inline]
pub fn sh_copy_indices(i: u32, p: &ShCopyParams) -> (usize, Option<usize>) {
    let per_dst = 3 * p.dst_coeffs;
    let g = i / per_dst;
    let r = i % per_dst;
    let dst = ((p.dst_first + g) * per_dst + r) as usize;
    if r / 3 < p.src_coeffs {
        (
            dst,
            Some(((p.src_first + g) * 3 * p.src_coeffs + r) as usize),
        )
    } else {
        (dst, None)
    }
}
