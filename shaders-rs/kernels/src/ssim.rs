//! SSIM and its gradient on the GPU (`drape_shared::ssim` is the math and the form).
//!
//! `moments`: `x`, `y` (read), `planes` 5 × (H·W·3) (written: x, y, x², y², xy).
//! `blur`: `src`, `dst` (`planes` images, one separable pass, zero padding; runs of
//! `SSIM_BLUR_RUN` outputs an invocation).
//! `map`: `moments` (blurred, read), `smap` H·W·3 and `partials` 3 × (H·W·3) (written).
//! `grad`: `x`, `y`, `partials` (blurred, read), `grad` (added to: `scale` times the
//! derivative of the mean SSIM).
//! One invocation per element (per run in `blur`) on a two-dimensional grid (1080p
//! moments are 31M).

use drape_shared::ssim::{
    blur_invocations, ssim_pointwise, SsimParams, SSIM_BLUR_RUN, SSIM_WINDOW,
};
const _: () = assert!(
    SSIM_WINDOW == 11 && SSIM_BLUR_RUN == 16,
    "blur unrolls 11 taps over runs of 16"
);
/// Window values over one run of `blur`.
const WINDOW_OVER_RUN: usize = SSIM_BLUR_RUN as usize + SSIM_WINDOW - 1;
const _: () = assert!(WINDOW_OVER_RUN == 26, "blur loads 24 + 2 window values");
use spirv_std::glam::UVec3;
use spirv_std::spirv;

use crate::flat_index;

#[spirv(compute(threads(256)))]
pub fn moments(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(push_constant)] p: &SsimParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] x: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] y: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] planes: &mut [f32],
) {
    let n = p.width * p.height * 3;
    let i = flat_index(id, groups);
    if i >= n {
        return;
    }
    let (a, b) = (x[i as usize], y[i as usize]);
    let n = n as usize;
    let i = i as usize;
    planes[i] = a;
    planes[n + i] = b;
    planes[2 * n + i] = a * a;
    planes[3 * n + i] = b * b;
    planes[4 * n + i] = a * b;
}

/// One separable pass of the window over `p.planes` images: invocation `e` blurs the
/// run of [`SSIM_BLUR_RUN`] pixels `run · 16 ..` along the pass's axis, of one line
/// across it, one channel and one plane ([`blur_invocations`] in all), from the 26
/// values of the window over the run, read once into registers. Each output adds the
/// same taps in the same order as the CPU reference, which skips the taps past the
/// image where these read 0 and add nothing.
#[spirv(compute(threads(256)))]
pub fn blur(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(push_constant)] p: &SsimParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] src: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] dst: &mut [f32],
) {
    let vertical = p.vertical != 0;
    let e = flat_index(id, groups);
    if e >= blur_invocations(p.width, p.height, p.planes, vertical) {
        return;
    }
    let (along, across) = if vertical {
        (p.height, p.width)
    } else {
        (p.width, p.height)
    };
    let runs = along.div_ceil(SSIM_BLUR_RUN);
    let run = e % runs;
    let line = e / runs;
    let c = line % 3;
    let other = (line / 3) % across;
    let plane = line / (3 * across);
    let image = p.width * p.height * 3;
    // Element of the pixel at `a` along the axis: origin + a · stride.
    let (origin, stride) = if vertical {
        (plane * image + other * 3 + c, p.width * 3)
    } else {
        (plane * image + other * p.width * 3 + c, 3)
    };
    let first = run * SSIM_BLUR_RUN;
    let half = SSIM_WINDOW as u32 / 2;
    // Window value k is the pixel at first + k - half along the axis (0 outside).
    let mut w = [0.0f32; WINDOW_OVER_RUN];
    macro_rules! load {
        ($k:expr) => {{
            let k = $k as u32;
            if first + k >= half && first + k - half < along {
                w[$k] = src[(origin + (first + k - half) * stride) as usize];
            }
        }};
    }
    // Constant indices (see `drape_shared::each_index!`): the window stays in registers.
    drape_shared::each_index!(24, k => { load!(k); });
    load!(24);
    load!(25);
    drape_shared::each_index!(16, j => {
        if first + (j as u32) < along {
            let mut sum = 0.0f32;
            drape_shared::each_index!(11, t => {
                sum += p.taps[t] * w[j + t];
            });
            dst[(origin + (first + j as u32) * stride) as usize] = sum;
        }
    });
}

#[spirv(compute(threads(256)))]
pub fn map(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(push_constant)] p: &SsimParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] moments: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] smap: &mut [f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] partials: &mut [f32],
) {
    let n = (p.width * p.height * 3) as usize;
    let i = flat_index(id, groups) as usize;
    if i >= n {
        return;
    }
    let (s, pm, pxx, pxy) = ssim_pointwise(
        moments[i],
        moments[n + i],
        moments[2 * n + i],
        moments[3 * n + i],
        moments[4 * n + i],
    );
    smap[i] = s;
    partials[i] = pm;
    partials[n + i] = pxx;
    partials[2 * n + i] = pxy;
}

#[spirv(compute(threads(256)))]
pub fn grad(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(push_constant)] p: &SsimParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] x: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] y: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] partials: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] grad: &mut [f32],
) {
    let n = (p.width * p.height * 3) as usize;
    let i = flat_index(id, groups) as usize;
    if i >= n {
        return;
    }
    grad[i] += p.scale * (partials[i] + 2.0 * x[i] * partials[n + i] + y[i] * partials[2 * n + i]);
}
