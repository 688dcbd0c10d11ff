//! The cloth physics losses: the Chamfer + Geman–McClure term and ARAP on the GPU
//! against their CPU references (f64), the references' gradients against central
//! differences, and the extremes (coincident points, empty sets, zero-length edges).

use drape_engine::ops::cloth_loss::{arap_reference, chamfer_reference, csr, nearest_reference, Arap, Chamfer};
use drape_engine::{BufferDesc, Context, EngineError};
use drape_tests::gpu;
use drape_tests::num::{rel_err, to_f32, to_f64, uniform};

fn points(n: usize, seed: u64) -> Vec<[f64; 3]> {
    uniform(3 * n, -0.3, 0.3, seed).chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect()
}

fn flat(p: &[[f64; 3]]) -> Vec<f64> {
    p.iter().flatten().copied().collect()
}

/// (robust loss, gradient with λ = 1, pred → target nearest indices) on the GPU.
fn gpu_chamfer(ctx: &Context, pred: &[[f64; 3]], target: &[[f64; 3]], sigma: f32) -> (f64, Vec<f64>, Vec<u32>) {
    let p = ctx.upload("pred", &to_f32(&flat(pred))).expect("upload");
    let t = ctx.upload("target", &to_f32(&flat(target))).expect("upload");
    let mut g = ctx.create_buffer("grad", BufferDesc::gpu_only(12 * pred.len() as u64)).expect("buffer");
    let mut c = Chamfer::new(ctx, pred.len() as u32, target.len() as u32).expect("chamfer");
    {
        let mut rec = ctx.record("chamfer test").expect("record");
        rec.fill(&g, 0);
        rec.barrier();
        c.record(&mut rec, &p, pred.len() as u32, &t, target.len() as u32, sigma, Some((&g, 1.0))).expect("record");
        rec.submit_and_wait().expect("submit");
    }
    let grad = to_f64(&ctx.read_buffer::<f32>(&mut g, 3 * pred.len()).expect("read"));
    let (near, _) = c.read_nearest(ctx).expect("nearest");
    (c.read_value(ctx).expect("value").robust, grad, near)
}

#[test]
fn chamfer_gpu_matches_cpu_reference() {
    let ctx = gpu();
    let sigma = 0.05f32;
    // Row counts on each side, with the other side small enough for brute force here.
    for (n, m) in [(1usize, 1usize), (7, 1000), (1000, 7), (1000, 1000), (100_003, 7), (7, 100_003)] {
        let pred = points(n, 1 + n as u64);
        let target = points(m, 2 + m as u64);
        let (loss, grad) = chamfer_reference(&pred, &target, f64::from(sigma));
        let (gl, gg, near) = gpu_chamfer(&ctx, &pred, &target, sigma);
        // f32 squared distances of O(0.1) points: ~1e-7 absolute; the mean of ρ ≤ 1 keeps that.
        assert!((gl - loss).abs() <= 1e-5 * loss.abs().max(1e-3), "{n}x{m}: loss {gl} vs {loss}");
        // Per-point gradients are sums of at most a few pair terms, each f32-rounded: 1e-4 of the largest.
        let e = rel_err(&gg, &flat(&grad), 1e-12);
        assert!(e < 1e-4, "{n}x{m}: gradient relative error {e:e}");
        // Nearest indices agree except where two candidates are within f32 rounding.
        let cpu = nearest_reference(&pred, &target);
        for (i, (&g, &(c, d))) in near.iter().zip(&cpu).enumerate() {
            if g as usize != c {
                let dg = drape_shared::cloth_loss::distance2(pred[i], target[g as usize]);
                assert!((dg - d).abs() <= 1e-6 * d.max(1e-6), "{n}x{m}: point {i} nearest {g} vs {c} ({dg} vs {d})");
            }
        }
    }
}

#[test]
fn chamfer_gradient_matches_central_differences() {
    let pred = points(40, 11);
    let target = points(60, 12);
    let sigma = 0.07;
    let (_, grad) = chamfer_reference(&pred, &target, sigma);
    let h = 1e-6;
    let mut worst = 0.0f64;
    for i in 0..pred.len() {
        for c in 0..3 {
            let mut a = pred.clone();
            a[i][c] += h;
            let mut b = pred.clone();
            b[i][c] -= h;
            let fd = (chamfer_reference(&a, &target, sigma).0 - chamfer_reference(&b, &target, sigma).0) / (2.0 * h);
            worst = worst.max((fd - grad[i][c]).abs());
        }
    }
    let scale = grad.iter().flatten().fold(0.0f64, |m, v| m.max(v.abs()));
    // Central differences in f64 with h = 1e-6 (nearest neighbours do not change under
    // it on random points): ~1e-9 of the largest gradient.
    assert!(worst <= 1e-6 * scale, "worst FD error {worst:e} (largest gradient {scale:e})");
}

#[test]
fn chamfer_extremes() {
    let ctx = gpu();
    // Coincident sets: zero loss, zero gradient, nothing non-finite.
    let p = points(300, 5);
    let (loss, grad, _) = gpu_chamfer(&ctx, &p, &p, 0.02);
    assert_eq!(loss, 0.0, "coincident sets have zero loss");
    assert!(grad.iter().all(|&g| g == 0.0), "coincident sets have zero gradient");
    // Far apart (d ≫ σ): ρ saturates near 1 and the gradient stays finite and small.
    let far: Vec<[f64; 3]> = p.iter().map(|v| [v[0] + 1e4, v[1], v[2]]).collect();
    let (loss, grad, _) = gpu_chamfer(&ctx, &p, &far, 0.02);
    assert!((loss - 1.0).abs() < 1e-6, "saturated loss {loss}");
    assert!(grad.iter().all(|g| g.is_finite() && g.abs() < 1e-6), "saturated gradient");
    // An empty set is an error naming it, and nothing is recorded.
    let buf = ctx.upload("p", &to_f32(&flat(&p))).expect("upload");
    let c = Chamfer::new(&ctx, 300, 300).expect("chamfer");
    for (n, m, which) in [(0u32, 300u32, "predicted"), (300, 0, "target")] {
        let mut rec = ctx.record("empty").expect("record");
        let err = c.record(&mut rec, &buf, n, &buf, m, 0.02, None).expect_err("an empty set must be refused");
        assert!(matches!(err, EngineError::Empty { .. }), "{err}");
        assert!(err.to_string().contains(which), "'{err}' does not name the {which} set");
        rec.submit_and_wait().expect("an empty recording still submits");
    }
    // More points than the scratch was made for: TooLarge, not a panic.
    let mut rec = ctx.record("too large").expect("record");
    let err = c.record(&mut rec, &buf, 301, &buf, 300, 0.02, None).expect_err("too many points");
    assert!(matches!(err, EngineError::TooLarge { .. }), "{err}");
    rec.submit_and_wait().expect("an empty recording still submits");
}

/// A triangulated grid of `w × h` vertices with random jitter: its edges.
fn grid_mesh(w: u32, h: u32) -> Vec<[u32; 2]> {
    let mut edges = Vec::new();
    for y in 0..h {
        for x in 0..w {
            let v = y * w + x;
            if x + 1 < w {
                edges.push([v, v + 1]);
            }
            if y + 1 < h {
                edges.push([v, v + w]);
            }
            if x + 1 < w && y + 1 < h {
                edges.push([v, v + w + 1]);
            }
        }
    }
    edges
}

fn gpu_arap(ctx: &Context, positions: &[[f64; 3]], edges: &[[u32; 2]]) -> (f64, Vec<f64>) {
    let p = ctx.upload("positions", &to_f32(&flat(positions))).expect("upload");
    let mut g = ctx.create_buffer("grad", BufferDesc::gpu_only(12 * positions.len().max(1) as u64)).expect("buffer");
    let mut a = Arap::new(ctx, positions.len() as u32, edges).expect("arap");
    {
        let mut rec = ctx.record("arap test").expect("record");
        rec.fill(&g, 0);
        rec.barrier();
        a.record(&mut rec, &p, Some((&g, 1.0))).expect("record");
        rec.submit_and_wait().expect("submit");
    }
    (f64::from(a.read_stats(ctx).expect("stats")[1]), to_f64(&ctx.read_buffer::<f32>(&mut g, 3 * positions.len()).expect("read")))
}

#[test]
fn arap_gpu_matches_cpu_reference() {
    let ctx = gpu();
    // Vertex counts 2, 7 (a strip), 1,000 and 100,003 (grids; the last one row short).
    for (w, h) in [(2u32, 1u32), (7, 1), (40, 25), (317, 316)] {
        let n = (w * h) as usize;
        let edges = grid_mesh(w, h);
        let jitter = uniform(3 * n, -0.004, 0.004, u64::from(w));
        let positions: Vec<[f64; 3]> = (0..n).map(|i| [0.01 * (i as u32 % w) as f64 + jitter[3 * i], 0.01 * (i as u32 / w) as f64 + jitter[3 * i + 1], jitter[3 * i + 2]]).collect();
        let (var, grad) = arap_reference(&positions, &edges);
        let (gv, gg) = gpu_arap(&ctx, &positions, &edges);
        // The variance subtracts a mean of f32 lengths from each: ~1e-4 relative at 300k edges.
        assert!((gv - var).abs() <= 2e-4 * var, "{w}x{h}: variance {gv} vs {var}");
        let e = rel_err(&gg, &flat(&grad), 1e-12);
        assert!(e < 2e-4, "{w}x{h}: gradient relative error {e:e}");
    }
}

#[test]
fn arap_gradient_matches_central_differences_and_degenerate_edges() {
    let edges = grid_mesh(5, 4);
    let positions = points(20, 9);
    let (_, grad) = arap_reference(&positions, &edges);
    let h = 1e-6;
    let mut worst = 0.0f64;
    for i in 0..positions.len() {
        for c in 0..3 {
            let mut a = positions.clone();
            a[i][c] += h;
            let mut b = positions.clone();
            b[i][c] -= h;
            let fd = (arap_reference(&a, &edges).0 - arap_reference(&b, &edges).0) / (2.0 * h);
            worst = worst.max((fd - grad[i][c]).abs());
        }
    }
    let scale = grad.iter().flatten().fold(0.0f64, |m, v| m.max(v.abs()));
    // f64 central differences of a smooth function (no edge is near zero length).
    assert!(worst <= 1e-6 * scale, "worst FD error {worst:e} (largest gradient {scale:e})");

    // A zero-length edge (two coincident vertices) contributes no direction: finite.
    let ctx = gpu();
    let mut p = positions.clone();
    p[1] = p[0];
    let (v, g) = gpu_arap(&ctx, &p, &edges);
    assert!(v.is_finite() && g.iter().all(|x| x.is_finite()), "zero-length edge gave non-finite values");
    // No edges: zero variance, zero gradient.
    let (v, g) = gpu_arap(&ctx, &p, &[]);
    assert_eq!(v, 0.0);
    assert!(g.iter().all(|&x| x == 0.0));
}

#[test]
fn csr_lists_each_edge_at_both_ends() {
    let edges = [[0u32, 1], [1, 2], [0, 2], [2, 3]];
    let (offsets, neighbours) = csr(5, &edges);
    assert_eq!(offsets, vec![0, 2, 4, 7, 8, 8]);
    assert_eq!(neighbours, vec![1, 2, 0, 2, 1, 0, 3, 2]);
}
