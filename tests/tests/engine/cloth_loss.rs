//! The cloth physics losses: the Chamfer + Geman–McClure term and ARAP on the GPU
//! against their CPU references (f64), the references' gradients against central
//! differences, and the extremes (coincident points, empty sets, zero-length edges).

use drape_engine::ops::cloth_loss::{csr, reference, Arap, Chamfer, NearestSearch};
use drape_engine::{BufferDesc, Context, EngineError};
use drape_tests::gpu;
use drape_tests::num::{rel_err, to_f32, to_f64, uniform};

fn points(n: usize, seed: u64) -> Vec<[f64; 3]> {
    uniform(3 * n, -0.3, 0.3, seed)
        .chunks_exact(3)
        .map(|c| [c[0], c[1], c[2]])
        .collect()
}

fn flat(p: &[[f64; 3]]) -> Vec<f64> {
    p.iter().flatten().copied().collect()
}

/// (robust loss, gradient with λ = 1, pred → target nearest indices) on the GPU.
fn gpu_chamfer(
    ctx: &Context,
    pred: &[[f64; 3]],
    target: &[[f64; 3]],
    sigma: f32,
) -> (f64, Vec<f64>, Vec<u32>) {
    let (loss, grad, near, _) =
        gpu_chamfer_with(ctx, pred, target, sigma, NearestSearch::BruteForce);
    (loss, grad, near)
}

/// `gpu_chamfer` with a chosen search, and the target → pred nearest indices too.
fn gpu_chamfer_with(
    ctx: &Context,
    pred: &[[f64; 3]],
    target: &[[f64; 3]],
    sigma: f32,
    search: NearestSearch,
) -> (f64, Vec<f64>, Vec<u32>, Vec<u32>) {
    let p = ctx.upload("pred", &to_f32(&flat(pred))).expect("upload");
    let t = ctx
        .upload("target", &to_f32(&flat(target)))
        .expect("upload");
    let mut g = ctx
        .create_buffer("grad", BufferDesc::gpu_only(12 * pred.len() as u64))
        .expect("buffer");
    let mut c =
        Chamfer::with_search(ctx, pred.len() as u32, target.len() as u32, search).expect("chamfer");
    {
        let mut rec = ctx.record("chamfer test").expect("record");
        rec.fill(&g, 0);
        c.record(
            &mut rec,
            &p,
            pred.len() as u32,
            &t,
            target.len() as u32,
            sigma,
            Some((&g, 1.0)),
        )
        .expect("record");
        rec.submit_and_wait().expect("submit");
    }
    let grad = to_f64(
        &ctx.read_buffer::<f32>(&mut g, 3 * pred.len())
            .expect("read"),
    );
    let (near, back) = c.read_nearest(ctx).expect("nearest");
    (c.read_value(ctx).expect("value").robust, grad, near, back)
}

#[test]
fn chamfer_gpu_matches_cpu_reference() {
    let ctx = gpu();
    let sigma = 0.05f32;
    // Row counts on each side, with the other side small enough for brute force here.
    for (n, m) in [
        (1usize, 1usize),
        (7, 1000),
        (1000, 7),
        (1000, 1000),
        (100_003, 7),
        (7, 100_003),
    ] {
        let pred = points(n, 1 + n as u64);
        let target = points(m, 2 + m as u64);
        let (loss, grad) = reference::chamfer(&pred, &target, f64::from(sigma));
        let (gl, gg, near) = gpu_chamfer(&ctx, &pred, &target, sigma);
        // f32 squared distances of O(0.1) points: ~1e-7 absolute; the mean of ρ ≤ 1 keeps that.
        assert!(
            (gl - loss).abs() <= 1e-5 * loss.abs().max(1e-3),
            "{n}x{m}: loss {gl} vs {loss}"
        );
        // Per-point gradients are sums of at most a few pair terms, each f32-rounded: 1e-4 of the largest.
        let e = rel_err(&gg, &flat(&grad), 1e-12);
        assert!(e < 1e-4, "{n}x{m}: gradient relative error {e:e}");
        // Nearest indices agree except where two candidates are within f32 rounding.
        let cpu = reference::nearest(&pred, &target);
        for (i, (&g, &(c, d))) in near.iter().zip(&cpu).enumerate() {
            if g as usize != c {
                let dg = drape_shared::cloth_loss::distance2(pred[i], target[g as usize]);
                assert!(
                    (dg - d).abs() <= 1e-6 * d.max(1e-6),
                    "{n}x{m}: point {i} nearest {g} vs {c} ({dg} vs {d})"
                );
            }
        }
    }
}

#[test]
fn chamfer_gradient_matches_central_differences() {
    let pred = points(40, 11);
    let target = points(60, 12);
    let sigma = 0.07;
    let (_, grad) = reference::chamfer(&pred, &target, sigma);
    let h = 1e-6;
    let mut worst = 0.0f64;
    for i in 0..pred.len() {
        for c in 0..3 {
            let mut a = pred.clone();
            a[i][c] += h;
            let mut b = pred.clone();
            b[i][c] -= h;
            let fd = (reference::chamfer(&a, &target, sigma).0
                - reference::chamfer(&b, &target, sigma).0)
                / (2.0 * h);
            worst = worst.max((fd - grad[i][c]).abs());
        }
    }
    let scale = grad.iter().flatten().fold(0.0f64, |m, v| m.max(v.abs()));
    // Central differences in f64 with h = 1e-6 (nearest neighbours do not change under
    // it on random points): ~1e-9 of the largest gradient.
    assert!(
        worst <= 1e-6 * scale,
        "worst FD error {worst:e} (largest gradient {scale:e})"
    );
}

#[test]
fn chamfer_extremes() {
    let ctx = gpu();
    // Coincident sets: zero loss, zero gradient, nothing non-finite.
    let p = points(300, 5);
    let (loss, grad, _) = gpu_chamfer(&ctx, &p, &p, 0.02);
    assert_eq!(loss, 0.0, "coincident sets have zero loss");
    assert!(
        grad.iter().all(|&g| g == 0.0),
        "coincident sets have zero gradient"
    );
    // Far apart (d ≫ σ): ρ saturates near 1 and the gradient stays finite and small.
    let far: Vec<[f64; 3]> = p.iter().map(|v| [v[0] + 1e4, v[1], v[2]]).collect();
    let (loss, grad, _) = gpu_chamfer(&ctx, &p, &far, 0.02);
    assert!((loss - 1.0).abs() < 1e-6, "saturated loss {loss}");
    assert!(
        grad.iter().all(|g| g.is_finite() && g.abs() < 1e-6),
        "saturated gradient"
    );
    // An empty set is an error naming it, and nothing is recorded.
    let buf = ctx.upload("p", &to_f32(&flat(&p))).expect("upload");
    let c = Chamfer::new(&ctx, 300, 300).expect("chamfer");
    for (n, m, which) in [(0u32, 300u32, "predicted"), (300, 0, "target")] {
        let mut rec = ctx.record("empty").expect("record");
        let err = c
            .record(&mut rec, &buf, n, &buf, m, 0.02, None)
            .expect_err("an empty set must be refused");
        assert!(matches!(err, EngineError::Empty { .. }), "{err}");
        assert!(
            err.to_string().contains(which),
            "'{err}' does not name the {which} set"
        );
        rec.submit_and_wait()
            .expect("an empty recording still submits");
    }
    // More points than the scratch was made for: TooLarge, not a panic.
    let mut rec = ctx.record("too large").expect("record");
    let err = c
        .record(&mut rec, &buf, 301, &buf, 300, 0.02, None)
        .expect_err("too many points");
    assert!(matches!(err, EngineError::TooLarge { .. }), "{err}");
    rec.submit_and_wait()
        .expect("an empty recording still submits");
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
    let p = ctx
        .upload("positions", &to_f32(&flat(positions)))
        .expect("upload");
    let mut g = ctx
        .create_buffer(
            "grad",
            BufferDesc::gpu_only(12 * positions.len().max(1) as u64),
        )
        .expect("buffer");
    let mut a = Arap::new(ctx, positions.len() as u32, edges).expect("arap");
    {
        let mut rec = ctx.record("arap test").expect("record");
        rec.fill(&g, 0);
        a.record(&mut rec, &p, Some((&g, 1.0))).expect("record");
        rec.submit_and_wait().expect("submit");
    }
    (
        f64::from(a.read_stats(ctx).expect("stats")[1]),
        to_f64(
            &ctx.read_buffer::<f32>(&mut g, 3 * positions.len())
                .expect("read"),
        ),
    )
}

#[test]
fn arap_gpu_matches_cpu_reference() {
    let ctx = gpu();
    // Vertex counts 2, 7 (a strip), 1,000 and 100,003 (grids; the last one row short).
    for (w, h) in [(2u32, 1u32), (7, 1), (40, 25), (317, 316)] {
        let n = (w * h) as usize;
        let edges = grid_mesh(w, h);
        let jitter = uniform(3 * n, -0.004, 0.004, u64::from(w));
        let positions: Vec<[f64; 3]> = (0..n)
            .map(|i| {
                [
                    0.01 * (i as u32 % w) as f64 + jitter[3 * i],
                    0.01 * (i as u32 / w) as f64 + jitter[3 * i + 1],
                    jitter[3 * i + 2],
                ]
            })
            .collect();
        let (var, grad) = reference::arap(&positions, &edges);
        let (gv, gg) = gpu_arap(&ctx, &positions, &edges);
        // The variance subtracts a mean of f32 lengths from each: ~1e-4 relative at 300k edges.
        assert!(
            (gv - var).abs() <= 2e-4 * var,
            "{w}x{h}: variance {gv} vs {var}"
        );
        let e = rel_err(&gg, &flat(&grad), 1e-12);
        assert!(e < 2e-4, "{w}x{h}: gradient relative error {e:e}");
    }
}

#[test]
fn arap_gradient_matches_central_differences_and_degenerate_edges() {
    let edges = grid_mesh(5, 4);
    let positions = points(20, 9);
    let (_, grad) = reference::arap(&positions, &edges);
    let h = 1e-6;
    let mut worst = 0.0f64;
    for i in 0..positions.len() {
        for c in 0..3 {
            let mut a = positions.clone();
            a[i][c] += h;
            let mut b = positions.clone();
            b[i][c] -= h;
            let fd = (reference::arap(&a, &edges).0 - reference::arap(&b, &edges).0) / (2.0 * h);
            worst = worst.max((fd - grad[i][c]).abs());
        }
    }
    let scale = grad.iter().flatten().fold(0.0f64, |m, v| m.max(v.abs()));
    // f64 central differences of a smooth function (no edge is near zero length).
    assert!(
        worst <= 1e-6 * scale,
        "worst FD error {worst:e} (largest gradient {scale:e})"
    );

    // A zero-length edge (two coincident vertices) contributes no direction: finite.
    let ctx = gpu();
    let mut p = positions.clone();
    p[1] = p[0];
    let (v, g) = gpu_arap(&ctx, &p, &edges);
    assert!(
        v.is_finite() && g.iter().all(|x| x.is_finite()),
        "zero-length edge gave non-finite values"
    );
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

/// Point sets that stress the grid: a cube, a sphere shell (a surface: most cells
/// empty), a flat sheet, a thin line, duplicated points (ties), all points coincident,
/// and predictions far outside the target box (whose shell search runs out of budget
/// and is finished by brute force).
/// A named case: (name, predicted points, target points).
type GridCase = (&'static str, Vec<[f64; 3]>, Vec<[f64; 3]>);

fn grid_cases() -> Vec<GridCase> {
    let shell = |n: usize, seed: u64, r: f64| -> Vec<[f64; 3]> {
        points(n, seed)
            .into_iter()
            .map(|p| {
                let l = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt().max(1e-9);
                [r * p[0] / l, r * p[1] / l, r * p[2] / l]
            })
            .collect()
    };
    let sheet = |n: usize, seed: u64| -> Vec<[f64; 3]> {
        points(n, seed)
            .into_iter()
            .map(|p| [p[0], p[1], 0.0])
            .collect()
    };
    let line = |n: usize, seed: u64| -> Vec<[f64; 3]> {
        points(n, seed)
            .into_iter()
            .map(|p| [p[0], 1e-4 * p[1], 0.0])
            .collect()
    };
    let mut dup = points(3000, 31);
    dup.extend_from_within(..1500);
    let mut far = points(2000, 41);
    far.extend(
        points(40, 42)
            .into_iter()
            .map(|p| [p[0] + 30.0, p[1] - 20.0, p[2]]),
    );
    // Sizes: the grid sizes its cells to the point count, so thousands of points search
    // it as millions do; the brute force and the f64 reference are quadratic (with the
    // cube at 20,000 x 15,000 and the shell at 12,000 x 9,000 the test took a minute).
    vec![
        ("cube", points(8_000, 21), points(6_000, 22)),
        ("shell", shell(6_000, 23, 0.25), shell(4_500, 24, 0.26)),
        ("sheet", sheet(8_000, 25), sheet(8_000, 26)),
        ("line", line(5_000, 27), line(6_000, 28)),
        ("duplicates", points(2_000, 32), dup),
        (
            "coincident",
            vec![[0.1, 0.2, 0.3]; 700],
            vec![[0.1, 0.2, 0.3]; 500],
        ),
        // 20,000 targets: a far query's shell search must run out of its step budget
        // (at 8,000 the grid is small enough for the search to finish).
        ("far queries", far, points(20_000, 43)),
        ("one point", points(1, 44), points(7, 45)),
    ]
}

#[test]
fn grid_search_finds_what_brute_force_finds() {
    let ctx = gpu();
    let sigma = 0.02f32;
    for (name, pred, target) in grid_cases() {
        let (bl, bg, bn, bb) =
            gpu_chamfer_with(&ctx, &pred, &target, sigma, NearestSearch::BruteForce);
        let (gl, gg, gn, gb) = gpu_chamfer_with(&ctx, &pred, &target, sigma, NearestSearch::Grid);
        // The same f32 distances and the same tie rule (lower index): the same indices.
        for (dir, g, b) in [("pred -> target", &gn, &bn), ("target -> pred", &gb, &bb)] {
            let wrong: Vec<usize> = (0..g.len()).filter(|&i| g[i] != b[i]).collect();
            assert!(wrong.is_empty(), "{name}: {dir}: {} of {} nearest indices differ from brute force (first: query {}, {} vs {})", wrong.len(), g.len(), wrong[0], g[wrong[0]], b[wrong[0]]);
        }
        // Same per-point terms; the mean is summed on the host from the same d² values.
        assert_eq!(gl, bl, "{name}: loss {gl} vs brute force {bl}");
        // The target terms are summed in 2^-36 fixed point (grid) and in f32 (brute
        // force): 1e-5 of the largest component.
        let e = rel_err(&gg, &bg, 1e-12);
        assert!(
            e < 1e-5,
            "{name}: gradient relative error {e:e} against brute force"
        );
        // And against the f64 reference, as the brute-force test states it, on the
        // points as uploaded (f32) so that both see the same sets.
        let f32_points = |v: &[[f64; 3]]| -> Vec<[f64; 3]> {
            v.iter().map(|p| p.map(|c| f64::from(c as f32))).collect()
        };
        let (loss, grad) =
            reference::chamfer(&f32_points(&pred), &f32_points(&target), f64::from(sigma));
        assert!(
            (gl - loss).abs() <= 1e-5 * loss.abs().max(1e-3),
            "{name}: loss {gl} vs {loss}"
        );
        let e = rel_err(&gg, &flat(&grad), 1e-12);
        assert!(
            e < 1e-4,
            "{name}: gradient relative error {e:e} against the f64 reference"
        );
        println!(
            "{name}: {} x {} points, loss {gl:.6}, grid = brute force",
            pred.len(),
            target.len()
        );
    }
}

/// The f32 nearest of `points` to `q` by brute force (lower index on ties), as the
/// kernels compute distances.
fn nearest_f32(q: [f32; 3], points: &[[f32; 3]]) -> (u32, f32) {
    let mut best = (u32::MAX, f32::INFINITY);
    for (j, p) in points.iter().enumerate() {
        let d = drape_shared::cloth_loss::distance2(q, *p);
        if d < best.1 {
            best = (j as u32, d);
        }
    }
    best
}

#[test]
fn chamfer_of_a_million_points_each_way() {
    let ctx = gpu();
    const N: usize = 1_000_000;
    // Two samplings of a garment-like surface (a wavy cylinder, 0.3 m across, 0.6 m
    // tall), the predictions jittered off it by a few millimetres.
    let surface = |n: usize, seed: u64, jitter: f64| -> Vec<[f32; 3]> {
        let u = uniform(4 * n, 0.0, 1.0, seed);
        (0..n)
            .map(|i| {
                let (a, h, j) = (
                    u[4 * i] * std::f64::consts::TAU,
                    u[4 * i + 1] * 0.6,
                    (u[4 * i + 2] - 0.5) * jitter,
                );
                let r = 0.15 + 0.01 * (5.0 * a).sin() * (10.0 * h).cos() + j;
                [(r * a.cos()) as f32, h as f32, (r * a.sin()) as f32]
            })
            .collect()
    };
    let pred = surface(N, 51, 0.006);
    let target = surface(N, 52, 0.0);
    let flat32 = |p: &[[f32; 3]]| p.iter().flatten().copied().collect::<Vec<f32>>();
    let pb = ctx.upload("pred", &flat32(&pred)).expect("upload");
    let tb = ctx.upload("target", &flat32(&target)).expect("upload");
    let mut g = ctx
        .create_buffer("grad", BufferDesc::gpu_only(12 * N as u64))
        .expect("buffer");
    let mut c = Chamfer::new(&ctx, N as u32, N as u32).expect("chamfer");
    let sigma = 0.02f32;
    let start = std::time::Instant::now();
    {
        let mut rec = ctx.record("chamfer 1M").expect("record");
        rec.fill(&g, 0);
        c.record(
            &mut rec,
            &pb,
            N as u32,
            &tb,
            N as u32,
            sigma,
            Some((&g, 1.0)),
        )
        .expect("record");
        rec.submit_and_wait().expect("submit");
    }
    println!(
        "1M x 1M Chamfer with its gradient (Auto: the grid) took {:.1} s on this device",
        start.elapsed().as_secs_f64()
    );
    let value = c.read_value(&ctx).expect("value");
    let (near, back) = c.read_nearest(&ctx).expect("nearest");
    let grad = ctx.read_buffer::<f32>(&mut g, 3 * N).expect("read");
    // Brute force over all 10^12 pairs is out of reach in a test: 300 queries each way,
    // spread over the sets, against an exhaustive f32 search.
    for (dir, queries, points, found) in [
        ("pred -> target", &pred, &target, &near),
        ("target -> pred", &target, &pred, &back),
    ] {
        for q in (0..N).step_by(N / 300) {
            let (j, d) = nearest_f32(queries[q], points);
            assert_eq!(
                found[q],
                j,
                "{dir}: query {q} found {} at {} vs {j} at {d}",
                found[q],
                drape_shared::cloth_loss::distance2(queries[q], points[found[q] as usize])
            );
        }
    }
    // The loss and the gradient recomputed on the host (f64) from the indices found.
    let to64 = |p: [f32; 3]| [f64::from(p[0]), f64::from(p[1]), f64::from(p[2])];
    let s2 = f64::from(sigma * sigma);
    let mut loss = 0.0;
    let mut want = vec![[0.0f64; 3]; N];
    for i in 0..N {
        let (p, t) = (to64(pred[i]), to64(target[near[i] as usize]));
        loss +=
            0.5 * drape_shared::cloth_loss::geman_mcclure(
                drape_shared::cloth_loss::distance2(p, t),
                s2,
            )
            .0 / N as f64;
        want[i] = drape_shared::cloth_loss::chamfer_pair_grad(p, t, s2, 0.5 / N as f64);
    }
    for j in 0..N {
        let i = back[j] as usize;
        let (p, t) = (to64(pred[i]), to64(target[j]));
        loss +=
            0.5 * drape_shared::cloth_loss::geman_mcclure(
                drape_shared::cloth_loss::distance2(p, t),
                s2,
            )
            .0 / N as f64;
        let d = drape_shared::cloth_loss::chamfer_pair_grad(p, t, s2, 0.5 / N as f64);
        for k in 0..3 {
            want[i][k] += d[k];
        }
    }
    // f32 distances summed over 2M terms in f64 on both sides: 1e-5 relative.
    assert!(
        (value.robust - loss).abs() <= 1e-5 * loss,
        "loss {} vs host {loss}",
        value.robust
    );
    let e = rel_err(&to_f64(&grad), &flat(&want), 1e-12);
    // Per-point sums of a few f32 pair terms (fixed point for the target terms): 1e-4.
    assert!(e < 1e-4, "gradient relative error {e:e}");
    assert!(grad.iter().all(|v| v.is_finite()), "non-finite gradient");
    println!(
        "1M x 1M: robust loss {:.6}, Chamfer distance {:.3} mm",
        value.robust,
        value.distance * 1e3
    );
}
