//! SSIM and its gradient on the GPU (`drape_shared::ssim` is the math and the form).
//!
//! `moments`: `x`, `y` (read), `planes` 5 × (H·W·3) (written: x, y, x², y², xy).
//! `blur`: `src`, `dst` (`planes` images, one separable pass, zero padding).
//! `map`: `moments` (blurred, read), `smap` H·W·3 and `partials` 3 × (H·W·3) (written).
//! `grad`: `x`, `y`, `partials` (blurred, read), `grad` (added to: `scale` times the
//! derivative of the mean SSIM).
//! One invocation per element on a two-dimensional grid (1080p moments are 31M).

use drape_shared::ssim::{ssim_pointwise, SsimParams, SSIM_WINDOW};
const _: () = assert!(SSIM_WINDOW == 11, "blur unrolls 11 taps");
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

#[spirv(compute(threads(256)))]
pub fn blur(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(push_constant)] p: &SsimParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] src: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] dst: &mut [f32],
) {
    let image = p.width * p.height * 3;
    let e = flat_index(id, groups);
    if e >= image * p.planes {
        return;
    }
    let within = e % image;
    let base = e - within;
    let pixel = within / 3;
    let c = within % 3;
    let (px, py) = ((pixel % p.width) as i32, (pixel / p.width) as i32);
    let half = (SSIM_WINDOW / 2) as i32;
    let mut sum = 0.0f32;
    // Constant tap indices (see `drape_shared::each_index!`).
    drape_shared::each_index!(11, t => {
        let d = t as i32 - half;
        let (qx, qy) = if p.vertical != 0 { (px, py + d) } else { (px + d, py) };
        if qx >= 0 && qy >= 0 && qx < p.width as i32 && qy < p.height as i32 {
            sum += p.taps[t] * src[(base + (qy as u32 * p.width + qx as u32) * 3 + c) as usize];
        }
    });
    dst[e as usize] = sum;
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
    let (s, pm, pxx, pxy) = ssim_pointwise(moments[i], moments[n + i], moments[2 * n + i], moments[3 * n + i], moments[4 * n + i]);
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
