//! Host mirrors (`drape_engine::Mirror`) in each op that keeps them (SSIM, LPIPS,
//! Chamfer, ARAP): values copied to the host inside the submission that computed them
//! are read with no wait of their own and the same bits as a read from the device, and
//! a mirror the next evaluation did not refresh is not read. Counted with device
//! buffers unmapped (`force_staging`), as on a discrete GPU where each read of one is a
//! wait.

use drape_engine::ops::cloth_loss::{Arap, Chamfer};
use drape_engine::ops::lpips::{Lpips, LpipsNet, LpipsWeights};
use drape_engine::ops::ssim::Ssim;
use drape_engine::{Context, ContextDesc, Recording};
use drape_tests::{gpu_with, TestGpu};

use crate::lpips::{random_tensors, weights_file};

fn staged_gpu() -> TestGpu {
    gpu_with(&ContextDesc {
        force_staging: true,
        poison_new_buffers: false,
        ..ContextDesc::for_tests()
    })
}

fn ramp(n: usize, phase: f32) -> Vec<f32> {
    (0..n)
        .map(|i| 0.5 + 0.4 * (i as f32 * 0.37 + phase).sin())
        .collect()
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

/// The checks every op's mirror must pass. `make(true)` makes the op with its host
/// mirror, `eval(op, k, copy)` evaluates it on input `k` (0 or 1, which must give
/// different values), copying to the mirror where `copy`, and `read` reads its value.
/// A read after a recording that copied equals the device's value and takes no wait;
/// a read after one that recomputed without copying equals the device's new value and
/// takes a wait at least.
fn check<O, T: PartialEq + std::fmt::Debug>(
    ctx: &Context,
    what: &str,
    make: impl Fn(bool) -> O,
    eval: impl Fn(&O, usize, bool),
    read: impl Fn(&mut O) -> T,
) {
    let mut plain = make(false);
    eval(&plain, 0, false);
    let device = read(&mut plain);
    eval(&plain, 1, false);
    let device_after = read(&mut plain);
    assert_ne!(
        device, device_after,
        "{what}: the two evaluations must differ for a stale read to show"
    );
    let mut mirrored = make(true);
    eval(&mirrored, 0, true);
    let (fresh, waits) = counted(ctx, || read(&mut mirrored));
    assert_eq!(waits, 0, "{what}: a mirrored read waits on nothing");
    assert_eq!(fresh, device, "{what}: the mirror holds the device's bits");
    eval(&mirrored, 1, false);
    let (stale, waits) = counted(ctx, || read(&mut mirrored));
    assert!(
        waits >= 1,
        "{what}: a stale mirror falls back to a read through staging ({waits} waits)"
    );
    assert_eq!(
        stale, device_after,
        "{what}: the stale mirror's old value is not returned"
    );
}

#[test]
fn ssim_reads_its_mirror_without_a_wait_and_not_when_stale() {
    let ctx = staged_gpu();
    let (w, h) = (16, 12);
    let n = (w * h * 3) as usize;
    let [a, b, c] =
        [0.0, 0.9, 2.1].map(|phase| ctx.upload("image", &ramp(n, phase)).expect("upload"));
    let make = |mirror: bool| {
        let mut s = Ssim::new(&ctx, w, h).expect("ssim");
        if mirror {
            s.keep_host_mirror(&ctx).expect("mirror");
        }
        s
    };
    let eval = |s: &Ssim, k: usize, copy: bool| {
        submit(&ctx, |rec| {
            s.record(rec, &a, [&b, &c][k], None).expect("record");
            if copy {
                s.record_readback(rec);
            }
        })
    };
    check(&ctx, "ssim", make, eval, |s| {
        s.read_mean(&ctx).expect("read")
    });
}

#[test]
fn lpips_reads_its_mirrors_without_a_wait_and_not_when_stale() {
    let ctx = staged_gpu();
    let net = LpipsNet::Alex;
    let weights = LpipsWeights::load(
        &weights_file("mirror.safetensors", &random_tensors(net, 7)),
        net,
    )
    .expect("load");
    let (w, h) = (32, 32);
    let n = (w * h * 3) as usize;
    let [a, b, c] =
        [0.0, 0.9, 2.1].map(|phase| ctx.upload("image", &ramp(n, phase)).expect("upload"));
    let make = |mirror: bool| {
        let mut l = Lpips::new(&ctx, &weights, w, h).expect("lpips");
        if mirror {
            l.keep_host_mirror(&ctx).expect("mirror");
        }
        l
    };
    let eval = |l: &Lpips, k: usize, copy: bool| {
        submit(&ctx, |rec| {
            l.record(rec, &a, [&b, &c][k], None).expect("record");
            if copy {
                l.record_readback(rec);
            }
        })
    };
    check(&ctx, "lpips", make, eval, |l| {
        l.read_value(&ctx).expect("read")
    });
}

#[test]
fn chamfer_and_arap_read_their_mirrors_without_a_wait_and_not_when_stale() {
    let ctx = staged_gpu();
    let (n, m) = (40u32, 30u32);
    let pred = ctx
        .upload("pred", &ramp(3 * n as usize, 0.0))
        .expect("upload");
    let targets = [0.9, 2.1].map(|phase| {
        ctx.upload("target", &ramp(3 * m as usize, phase))
            .expect("upload")
    });
    let make = |mirror: bool| {
        let mut c = Chamfer::new(&ctx, n, m).expect("chamfer");
        if mirror {
            c.keep_host_mirror(&ctx).expect("mirror");
        }
        c
    };
    let eval = |c: &Chamfer, k: usize, copy: bool| {
        submit(&ctx, |rec| {
            c.record(rec, &pred, n, &targets[k], m, 0.1, None)
                .expect("record");
            if copy {
                c.record_readback(rec);
            }
        })
    };
    check(&ctx, "chamfer", make, eval, |c| {
        c.read_value(&ctx).expect("read")
    });

    // ARAP over a chain of the 40 points, on two different point sets.
    let edges: Vec<[u32; 2]> = (0..n - 1).map(|i| [i, i + 1]).collect();
    let positions = [0.0, 1.3].map(|phase| {
        ctx.upload("positions", &ramp(3 * n as usize, phase))
            .expect("upload")
    });
    let make = |mirror: bool| {
        let mut a = Arap::new(&ctx, n, &edges).expect("arap");
        if mirror {
            a.keep_host_mirror(&ctx).expect("mirror");
        }
        a
    };
    let eval = |a: &Arap, k: usize, copy: bool| {
        submit(&ctx, |rec| {
            a.record(rec, &positions[k], None).expect("record");
            if copy {
                a.record_readback(rec);
            }
        })
    };
    check(&ctx, "arap", make, eval, |a| {
        a.read_stats(&ctx).expect("read")
    });
}
