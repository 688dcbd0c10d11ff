//! Host mirrors (`drape_engine::Mirror`) in each op that keeps them (SSIM, LPIPS,
//! Chamfer, ARAP): values copied to the host inside the submission that computed them
//! are read with no wait of their own and the same bits as a read from the device, and
//! a mirror the next evaluation did not refresh is not read. Counted with device
//! buffers unmapped (`force_staging`), as on a discrete GPU where each read of one is a
//! wait.

use drape_engine::ops::cloth_loss::{Arap, Chamfer};
use drape_engine::ops::lpips::{Lpips, LpipsNet, LpipsWeights};
use drape_engine::ops::ssim::Ssim;
use drape_engine::{Buffer, Context, ContextDesc, Recording};
use drape_tests::{gpu_with, TestGpu};

use crate::lpips::{random_tensors, weights_file};

fn staged_gpu() -> TestGpu {
    gpu_with(&ContextDesc { force_staging: true, poison_new_buffers: false, ..ContextDesc::for_tests() })
}

fn ramp(n: usize, phase: f32) -> Vec<f32> {
    (0..n).map(|i| 0.5 + 0.4 * (i as f32 * 0.37 + phase).sin()).collect()
}

/// Records `body` into one submission and waits for it.
fn submit<'a>(ctx: &'a Context, body: impl FnOnce(&mut Recording<'a>)) {
    let mut rec = ctx.record("mirror test").expect("record");
    body(&mut rec);
    rec.submit_and_wait().expect("submit");
}

/// `read`'s value and the host waits it took.
fn counted<T>(ctx: &Context, read: impl FnOnce() -> T) -> (T, u64) {
    let before = ctx.fence_waits();
    let value = read();
    (value, ctx.fence_waits() - before)
}

/// The checks every op's mirror must pass: `fresh` (read after a recording that
/// copied to the mirror) equals the device's value and took no wait; `stale` (read
/// after a recording that recomputed without copying) equals the device's new value
/// and took a wait at least.
fn check<T: PartialEq + std::fmt::Debug>(what: &str, fresh: (T, u64), device: T, stale: (T, u64), device_after: T) {
    assert_ne!(device, device_after, "{what}: the two evaluations must differ for a stale read to show");
    assert_eq!(fresh.1, 0, "{what}: a mirrored read waits on nothing");
    assert_eq!(fresh.0, device, "{what}: the mirror holds the device's bits");
    assert!(stale.1 >= 1, "{what}: a stale mirror falls back to a read through staging ({} waits)", stale.1);
    assert_eq!(stale.0, device_after, "{what}: the stale mirror's old value is not returned");
}

#[test]
fn ssim_reads_its_mirror_without_a_wait_and_not_when_stale() {
    let ctx = staged_gpu();
    let (w, h) = (16, 12);
    let n = (w * h * 3) as usize;
    let [a, b, c] = [0.0, 0.9, 2.1].map(|phase| ctx.upload("image", &ramp(n, phase)).expect("upload"));
    let eval = |s: &Ssim, x: &Buffer, copy: bool| {
        submit(&ctx, |rec| {
            s.record(rec, &a, x, None).expect("record");
            if copy {
                s.record_readback(rec);
            }
        })
    };
    let mut plain = Ssim::new(&ctx, w, h).expect("ssim");
    eval(&plain, &b, false);
    let ab = plain.read_mean(&ctx).expect("read");
    eval(&plain, &c, false);
    let ac = plain.read_mean(&ctx).expect("read");
    let mut mirrored = Ssim::new(&ctx, w, h).expect("ssim");
    mirrored.keep_host_mirror(&ctx).expect("mirror");
    eval(&mirrored, &b, true);
    let fresh = counted(&ctx, || mirrored.read_mean(&ctx).expect("read"));
    eval(&mirrored, &c, false);
    let stale = counted(&ctx, || mirrored.read_mean(&ctx).expect("read"));
    check("ssim", fresh, ab, stale, ac);
}

#[test]
fn lpips_reads_its_mirrors_without_a_wait_and_not_when_stale() {
    let ctx = staged_gpu();
    let net = LpipsNet::Alex;
    let weights = LpipsWeights::load(&weights_file("mirror.safetensors", &random_tensors(net, 7)), net).expect("load");
    let (w, h) = (32, 32);
    let n = (w * h * 3) as usize;
    let [a, b, c] = [0.0, 0.9, 2.1].map(|phase| ctx.upload("image", &ramp(n, phase)).expect("upload"));
    let eval = |l: &Lpips, x: &Buffer, copy: bool| {
        submit(&ctx, |rec| {
            l.record(rec, &a, x, None).expect("record");
            if copy {
                l.record_readback(rec);
            }
        })
    };
    let mut plain = Lpips::new(&ctx, &weights, w, h).expect("lpips");
    eval(&plain, &b, false);
    let ab = plain.read_value(&ctx).expect("read");
    eval(&plain, &c, false);
    let ac = plain.read_value(&ctx).expect("read");
    let mut mirrored = Lpips::new(&ctx, &weights, w, h).expect("lpips");
    mirrored.keep_host_mirror(&ctx).expect("mirror");
    eval(&mirrored, &b, true);
    let fresh = counted(&ctx, || mirrored.read_value(&ctx).expect("read"));
    eval(&mirrored, &c, false);
    let stale = counted(&ctx, || mirrored.read_value(&ctx).expect("read"));
    check("lpips", fresh, ab, stale, ac);
}

#[test]
fn chamfer_and_arap_read_their_mirrors_without_a_wait_and_not_when_stale() {
    let ctx = staged_gpu();
    let (n, m) = (40u32, 30u32);
    let pred = ctx.upload("pred", &ramp(3 * n as usize, 0.0)).expect("upload");
    let [t1, t2] = [0.9, 2.1].map(|phase| ctx.upload("target", &ramp(3 * m as usize, phase)).expect("upload"));
    let eval = |c: &Chamfer, target: &Buffer, copy: bool| {
        submit(&ctx, |rec| {
            c.record(rec, &pred, n, target, m, 0.1, None).expect("record");
            if copy {
                c.record_readback(rec);
            }
        })
    };
    let mut plain = Chamfer::new(&ctx, n, m).expect("chamfer");
    eval(&plain, &t1, false);
    let first = plain.read_value(&ctx).expect("read");
    eval(&plain, &t2, false);
    let second = plain.read_value(&ctx).expect("read");
    let mut mirrored = Chamfer::new(&ctx, n, m).expect("chamfer");
    mirrored.keep_host_mirror(&ctx).expect("mirror");
    eval(&mirrored, &t1, true);
    let fresh = counted(&ctx, || mirrored.read_value(&ctx).expect("read"));
    eval(&mirrored, &t2, false);
    let stale = counted(&ctx, || mirrored.read_value(&ctx).expect("read"));
    check("chamfer", fresh, first, stale, second);

    // ARAP over a chain of the 40 points, on two different point sets.
    let edges: Vec<[u32; 2]> = (0..n - 1).map(|i| [i, i + 1]).collect();
    let other = ctx.upload("other", &ramp(3 * n as usize, 1.3)).expect("upload");
    let eval = |a: &Arap, positions: &Buffer, copy: bool| {
        submit(&ctx, |rec| {
            a.record(rec, positions, None).expect("record");
            if copy {
                a.record_readback(rec);
            }
        })
    };
    let mut plain = Arap::new(&ctx, n, &edges).expect("arap");
    eval(&plain, &pred, false);
    let first = plain.read_stats(&ctx).expect("read");
    eval(&plain, &other, false);
    let second = plain.read_stats(&ctx).expect("read");
    let mut mirrored = Arap::new(&ctx, n, &edges).expect("arap");
    mirrored.keep_host_mirror(&ctx).expect("mirror");
    eval(&mirrored, &pred, true);
    let fresh = counted(&ctx, || mirrored.read_stats(&ctx).expect("read"));
    eval(&mirrored, &other, false);
    let stale = counted(&ctx, || mirrored.read_stats(&ctx).expect("read"));
    check("arap", fresh, first, stale, second);
}
