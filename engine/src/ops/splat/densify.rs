//! Densification statistics on the GPU (kernel `splat::screen_stats`; the math is
//! `drape_shared::splat::densify`, which the CPU reference below calls too): after a
//! render's backward pass, each Gaussian of a slice of the render adds the norm of its
//! projected centre's gradient (in 3DGS's NDC units), one visible frame and its screen
//! radius into a statistics buffer that its layer owns. The trainer reads the buffer
//! when it densifies and prunes (`drape_trainer::avatar::densify`), then starts it
//! again from zero.

pub use drape_shared::splat::densify::{
    accumulate, screen_radius, ScreenStatsParams, SCREEN_STATS_FLOATS,
};
use drape_shared::splat::layout::{ProjectedSplat, SPLAT_GRAD_FLOATS};

use crate::buffer::Buffer;
use crate::error::Result;
use crate::kernels;
use crate::ops::splat::render::SplatRenderer;
use crate::recorder::{flat_grid, Recording};

/// Records the addition of the last frame of `renderer` (its forward and backward
/// passes) for its Gaussians `[first, first + count)` into `stats` starting at
/// Gaussian `out_first` ([`SCREEN_STATS_FLOATS`] per Gaussian). Statistics of one
/// buffer from two renders are ordered by the barrier the recorder derives.
pub fn record_screen_stats<'a>(
    rec: &mut Recording<'a>,
    renderer: &'a SplatRenderer,
    first: u32,
    count: u32,
    stats: &'a Buffer,
    out_first: u32,
) -> Result<()> {
    if count == 0 {
        return Ok(());
    }
    let (width, height) = renderer.size();
    let (splats, grads) = renderer.splat_buffers();
    let p = ScreenStatsParams {
        first,
        count,
        out_first,
        width,
        height,
        _pad: [0; 3],
    };
    rec.dispatch(
        "splat.screen_stats",
        kernels::splat::ScreenStats {
            splats: splats.read(),
            splat_grads: grads.read(),
            stats: stats.write(),
        },
        &p,
        flat_grid(count),
    )
}

/// CPU reference of the screen-space statistics.
pub mod reference {
    use super::*;

    /// The CPU reference of [`record_screen_stats`] on read-back splats and per-splat
    /// gradients.
    pub fn screen_stats(
        splats: &[ProjectedSplat],
        splat_grads: &[f32],
        p: ScreenStatsParams,
        stats: &mut [f32],
    ) {
        for local in 0..p.count as usize {
            let i = p.first as usize + local;
            let o = SCREEN_STATS_FLOATS * (p.out_first as usize + local);
            let g = i * SPLAT_GRAD_FLOATS;
            let s = accumulate(
                [stats[o], stats[o + 1], stats[o + 2]],
                &splats[i],
                splat_grads[g],
                splat_grads[g + 1],
                p.width,
                p.height,
            );
            stats[o..o + 3].copy_from_slice(&s);
        }
    }
}
