//! Host mirrors (`drape_engine::Mirror`): values copied to the host inside the
//! submission that computed them are read with no wait of their own, and a mirror
//! the next evaluation did not refresh is not read. Counted with device buffers
//! unmapped (`force_staging`), as on a discrete GPU where each read of one is a wait.

use drape_engine::ops::ssim::Ssim;
use drape_engine::{Context, ContextDesc};
use drape_tests::gpu_with;

fn ramp(n: usize, phase: f32) -> Vec<f32> {
    (0..n).map(|i| 0.5 + 0.4 * (i as f32 * 0.37 + phase).sin()).collect()
}

/// SSIM of `pred` against `target`, recorded with or without the copy to the host.
fn evaluate(ctx: &Context, ssim: &Ssim, pred: &[f32], target: &[f32], readback: bool) {
    let p = ctx.upload("pred", pred).expect("upload");
    let t = ctx.upload("target", target).expect("upload");
    let mut rec = ctx.record("mirror test").expect("record");
    ssim.record(&mut rec, &p, &t, None).expect("record");
    if readback {
        ssim.record_readback(&mut rec);
    }
    rec.submit_and_wait().expect("submit");
}

#[test]
fn a_mirrored_value_is_read_without_a_wait_and_a_stale_one_is_not_read() {
    let desc = ContextDesc { force_staging: true, poison_new_buffers: false, ..ContextDesc::for_tests() };
    let ctx = gpu_with(&desc);
    let (w, h) = (16, 12);
    let n = (w * h * 3) as usize;
    let (a, b, c) = (ramp(n, 0.0), ramp(n, 0.9), ramp(n, 2.1));
    // The values as the device holds them, read through staging (one wait each).
    let mut plain = Ssim::new(&ctx, w, h).expect("ssim");
    evaluate(&ctx, &plain, &a, &b, false);
    let ab = plain.read_mean(&ctx).expect("read");
    evaluate(&ctx, &plain, &a, &c, false);
    let ac = plain.read_mean(&ctx).expect("read");
    assert!((ab - ac).abs() > 1e-3, "the two pairs must differ for the stale read to show: {ab} vs {ac}");

    let mut mirrored = Ssim::new(&ctx, w, h).expect("ssim");
    mirrored.keep_host_mirror(&ctx).expect("mirror");
    evaluate(&ctx, &mirrored, &a, &b, true);
    let waits = ctx.fence_waits();
    let from_mirror = mirrored.read_mean(&ctx).expect("read");
    assert_eq!(ctx.fence_waits(), waits, "a mirrored read waits on nothing");
    // Bit for bit: the mirror is a copy of the same map, summed the same way.
    assert_eq!(from_mirror, ab);

    // Recomputed without the copy: the mirror is stale and the device is read instead.
    evaluate(&ctx, &mirrored, &a, &c, false);
    let waits = ctx.fence_waits();
    let after = mirrored.read_mean(&ctx).expect("read");
    assert_eq!(ctx.fence_waits(), waits + 1, "a stale mirror falls back to a read through staging");
    assert_eq!(after, ac, "the stale mirror's old value is not returned");
}
