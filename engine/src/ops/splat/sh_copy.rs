//! Copies SH coefficients between Gaussian buffers of different degrees (kernel
//! `train::copy_sh`; the index math is `drape_shared::splat::layout::sh_copy_indices`,
//! which the CPU reference below calls too). Layers with their own SH degrees are
//! rendered in one pass at the highest: a lower degree is padded with zeros (the same
//! colour), and the gradient coming back is truncated to the layer's degree. Equal
//! degrees are a plain buffer copy.

use drape_shared::splat::layout::{sh_coeffs, sh_copy_indices, ShCopyParams};

use crate::buffer::Buffer;
use crate::error::Result;
use crate::kernels;
use crate::recorder::{flat_grid, Recording};

/// Where a copy reads and writes: a buffer, its SH degree, and the first Gaussian.
#[derive(Clone, Copy)]
pub struct ShSlice<'a> {
    /// The SH buffer.
    pub buffer: &'a Buffer,
    /// Its SH degree.
    pub degree: u32,
    /// The first Gaussian of the slice.
    pub first: u32,
}

fn params(src: (u32, u32), dst: (u32, u32), count: u32) -> ShCopyParams {
    ShCopyParams {
        count,
        src_coeffs: sh_coeffs(src.0) as u32,
        dst_coeffs: sh_coeffs(dst.0) as u32,
        src_first: src.1,
        dst_first: dst.1,
        _pad: [0; 3],
    }
}

/// Records the copy of `count` Gaussians' SH from `src` into `dst`.
pub fn record_copy_sh<'a>(
    rec: &mut Recording<'a>,
    src: ShSlice<'a>,
    dst: ShSlice<'a>,
    count: u32,
) -> Result<()> {
    if count == 0 {
        return Ok(());
    }
    if src.degree == dst.degree {
        let per = 12 * sh_coeffs(src.degree) as u64;
        rec.copy_region(
            src.buffer,
            per * u64::from(src.first),
            dst.buffer,
            per * u64::from(dst.first),
            per * u64::from(count),
        );
        return Ok(());
    }
    let p = params((src.degree, src.first), (dst.degree, dst.first), count);
    rec.dispatch(
        "train.copy_sh",
        kernels::train::CopySh {
            src: src.buffer.read(),
            dst: dst.buffer.write(),
        },
        &p,
        flat_grid(p.floats()),
    )
}

/// CPU reference of the SH copy.
pub mod reference {
    use super::*;

    /// CPU reference: `dst` after the same copy.
    pub fn copy_sh(
        src: &[f32],
        src_degree_first: (u32, u32),
        dst: &mut [f32],
        dst_degree_first: (u32, u32),
        count: u32,
    ) {
        let p = params(src_degree_first, dst_degree_first, count);
        for i in 0..p.floats() {
            let (d, s) = sh_copy_indices(i, &p);
            dst[d] = s.map_or(0.0, |s| src[s]);
        }
    }
}
