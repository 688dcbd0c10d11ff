//! Triplane sampling and Gaussian deformation on the GPU against the CPU reference
//! (f64), the references' gradients against central differences, and the stated
//! padding at and beyond the box.

use drape_engine::ops::accumulate::Accumulation;
use drape_engine::ops::deform::{self, DeformGrads, DeformInputs, HostInputs};
use drape_engine::ops::triplane::{self, Triplane, TriplaneDesc};
use drape_engine::{BufferDesc, Context};
use drape_shared::deform::{rot6d_to_matrix, DeformOutput};
use drape_shared::skinning::SKIN_JOINTS;
use drape_tests::num::{rel_err, to_f32, to_f64, uniform};
use drape_tests::{gpu, has_feature, Feature};
use rand::{Rng, SeedableRng};

fn desc() -> TriplaneDesc {
    TriplaneDesc {
        resolution: 9,
        channels: 5,
        box_min: [-1.0, -0.5, -2.0],
        box_max: [1.0, 1.5, 0.0],
    }
}

/// Points mostly inside the box, some on its faces and corners, some just outside
/// (within a texel) and far outside, and one NaN.
fn points(n: usize, seed: u64) -> Vec<f64> {
    let d = desc();
    let mut p = Vec::new();
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    for i in 0..n {
        for a in 0..3 {
            let (lo, hi) = (f64::from(d.box_min[a]), f64::from(d.box_max[a]));
            let w = hi - lo;
            let v = match i % 10 {
                0 => lo,
                1 => hi,
                2 => hi + 0.05 * w,
                3 => lo - 3.0 * w,
                _ => rng.random_range(lo - 0.02 * w..hi + 0.02 * w),
            };
            p.push(v);
        }
    }
    if n > 20 {
        p[3 * 17 + 1] = f64::NAN;
    }
    p
}

struct TriplaneRun {
    features: Vec<f64>,
    grad_planes: Vec<f64>,
    grad_points: Vec<f64>,
}

fn run_triplane(
    ctx: &Context,
    planes: &[f64],
    pts: &[f64],
    gfeat: &[f64],
    accumulation: Accumulation,
) -> TriplaneRun {
    let d = desc();
    let n = pts.len() / 3;
    let mut tp = Triplane::with_planes(ctx, "test triplane", d, &to_f32(planes)).expect("triplane");
    tp.prepare(ctx, accumulation).expect("scratch");
    let p = ctx.upload("points", &to_f32(pts)).expect("upload");
    let g = ctx.upload("grad features", &to_f32(gfeat)).expect("upload");
    let mut f = ctx
        .create_buffer("features", BufferDesc::gpu_only((gfeat.len() * 4) as u64))
        .expect("buffer");
    let mut gp = ctx
        .create_buffer("grad points", BufferDesc::gpu_only((pts.len() * 4) as u64))
        .expect("buffer");
    {
        let mut rec = ctx.record("triplane test").expect("record");
        tp.record_forward(&mut rec, &p, &f, n as u32).expect("fwd");
        tp.record_backward(&mut rec, &p, &g, &gp, n as u32, accumulation)
            .expect("bwd");
        rec.submit_and_wait().expect("submit");
    }
    TriplaneRun {
        features: to_f64(&ctx.read_buffer::<f32>(&mut f, gfeat.len()).expect("read")),
        grad_planes: to_f64(
            &ctx.read_buffer::<f32>(&mut tp.grads, d.len())
                .expect("read"),
        ),
        grad_points: to_f64(&ctx.read_buffer::<f32>(&mut gp, pts.len()).expect("read")),
    }
}

#[test]
fn triplane_gpu_matches_cpu_reference() {
    let ctx = gpu();
    let d = desc();
    let planes = uniform(d.len(), -1.0, 1.0, 1);
    // Without float atomics the compare-and-swap and fixed-point paths are still checked.
    let atomics = has_feature(
        &ctx,
        Feature::FloatAtomics,
        "triplane_gpu_matches_cpu_reference (float-atomic backward)",
    );
    let modes: &[Accumulation] = if atomics {
        &[
            Accumulation::FloatAtomics,
            Accumulation::CompareAndSwap,
            Accumulation::Deterministic,
        ]
    } else {
        &[Accumulation::CompareAndSwap, Accumulation::Deterministic]
    };
    for n in [0usize, 1, 7, 1000, 100_003] {
        let pts = points(n, n as u64);
        let gfeat = uniform(n * d.feature_width(), -1.0, 1.0, 7);
        let f_ref = triplane::reference::forward(&d, &planes, &pts);
        let (gpl_ref, gpt_ref) = triplane::reference::backward(&d, &planes, &pts, &gfeat);
        for &mode in modes {
            let run = run_triplane(&ctx, &planes, &pts, &gfeat, mode);
            // Four products per feature in f32.
            let e = rel_err(&run.features, &f_ref, 1e-3);
            assert!(e <= 1e-5, "n {n}: feature relative error {e:e}");
            // The plane gradient sums up to ~100k·4/243 contributions per texel in an
            // order the atomics choose: f32 rounding ~1e-7 · sqrt(1600) relative (fixed
            // point: 2^-37 per contribution, far below).
            let e = rel_err(&run.grad_planes, &gpl_ref, 1e-3);
            assert!(
                e <= 1e-4,
                "n {n} {mode:?}: plane gradient relative error {e:e}"
            );
            let e = rel_err(&run.grad_points, &gpt_ref, 1e-3);
            assert!(e <= 1e-4, "n {n}: point gradient relative error {e:e}");
        }
    }
}

/// The deterministic backward gives the same bits on every run, where float atomics
/// (which add in the order the invocations happen to run) need not: 100,003 points
/// on a 16 × 16 plane put ~1,600 contributions on each texel.
#[test]
fn triplane_deterministic_backward_repeats_bit_for_bit() {
    let ctx = gpu();
    let d = desc();
    let planes = uniform(d.len(), -1.0, 1.0, 11);
    let n = 100_003;
    let pts = points(n, 12);
    let gfeat = uniform(n * d.feature_width(), -1.0, 1.0, 13);
    let bits = |run: &TriplaneRun| {
        run.grad_planes
            .iter()
            .map(|v| v.to_bits())
            .collect::<Vec<u64>>()
    };
    let first = bits(&run_triplane(
        &ctx,
        &planes,
        &pts,
        &gfeat,
        Accumulation::Deterministic,
    ));
    for repeat in 0..3 {
        let again = bits(&run_triplane(
            &ctx,
            &planes,
            &pts,
            &gfeat,
            Accumulation::Deterministic,
        ));
        let differing = first.iter().zip(&again).filter(|(a, b)| a != b).count();
        assert_eq!(
            differing,
            0,
            "repeat {repeat}: {differing} of {} plane-gradient values changed bits",
            first.len()
        );
    }
    // A non-finite contribution cannot be held in an integer: it poisons the whole
    // gradient (NaN everywhere), so that a training step's non-finite guard sees it.
    let mut poisoned = gfeat.clone();
    poisoned[5] = f64::NAN;
    let run = run_triplane(&ctx, &planes, &pts, &poisoned, Accumulation::Deterministic);
    assert!(
        run.grad_planes.iter().all(|v| v.is_nan()),
        "a NaN feature gradient left finite plane gradients"
    );
    // For the record (not asserted: the scheduler may happen to repeat an order).
    let atomic = |_: u32| {
        bits(&run_triplane(
            &ctx,
            &planes,
            &pts,
            &gfeat,
            Accumulation::Auto,
        ))
    };
    let (a, b) = (atomic(0), atomic(1));
    eprintln!(
        "float atomics: {} of {} plane-gradient values differ between two runs",
        a.iter().zip(&b).filter(|(x, y)| x != y).count(),
        a.len()
    );
}

#[test]
fn triplane_padding_at_and_beyond_the_box() {
    let d = desc();
    let planes = uniform(d.len(), -1.0, 1.0, 2);
    let r = d.resolution as usize;
    let ch = d.channels as usize;
    let texel =
        |p: usize, row: usize, col: usize, c: usize| planes[((p * r + row) * r + col) * ch + c];
    // The box's max corner samples the last texel of every plane exactly.
    let corner = d.box_max.map(f64::from);
    let f = triplane::reference::forward(&d, &planes, &corner);
    for p in 0..3 {
        for c in 0..ch {
            assert!(
                (f[p * ch + c] - texel(p, r - 1, r - 1, c)).abs() < 1e-12,
                "max corner, plane {p}"
            );
        }
    }
    // Half a texel beyond the max face along x: zeros padding halves plane XY's
    // last-column value (the outer corner reads 0).
    let half_texel = 0.5 * f64::from(d.box_max[0] - d.box_min[0]) / (r - 1) as f64;
    let mut p = corner;
    p[0] += half_texel;
    let f = triplane::reference::forward(&d, &planes, &p);
    for c in 0..ch {
        assert!(
            (f[c] - 0.5 * texel(0, r - 1, r - 1, c)).abs() < 1e-12,
            "half a texel out, channel {c}"
        );
    }
    // Further out than one texel: zero features and zero gradients.
    let far = [10.0, 10.0, 10.0];
    assert!(triplane::reference::forward(&d, &planes, &far)
        .iter()
        .all(|&v| v == 0.0));
    let (gpl, gpt) =
        triplane::reference::backward(&d, &planes, &far, &vec![1.0; d.feature_width()]);
    assert!(gpl.iter().chain(&gpt).all(|&v| v == 0.0));
}

#[test]
fn triplane_gradients_match_central_differences() {
    let d = desc();
    let planes = uniform(d.len(), -1.0, 1.0, 3);
    // Inside points only: central differences across a texel edge see a kink.
    let pts: Vec<f64> = (0..6)
        .flat_map(|i| {
            (0..3).map(move |a| {
                let (lo, hi) = (f64::from(d.box_min[a]), f64::from(d.box_max[a]));
                lo + (hi - lo) * (0.13 + 0.137 * i as f64 + 0.05 * a as f64)
            })
        })
        .collect();
    let gfeat = uniform(6 * d.feature_width(), -1.0, 1.0, 4);
    let (gpl, gpt) = triplane::reference::backward(&d, &planes, &pts, &gfeat);
    let loss = |pl: &[f64], pt: &[f64]| {
        triplane::reference::forward(&d, pl, pt)
            .iter()
            .zip(&gfeat)
            .map(|(a, b)| a * b)
            .sum::<f64>()
    };
    let h = 1e-6;
    let num_pl: Vec<f64> = (0..planes.len())
        .map(|i| {
            let (mut a, mut b) = (planes.clone(), planes.clone());
            a[i] += h;
            b[i] -= h;
            (loss(&a, &pts) - loss(&b, &pts)) / (2.0 * h)
        })
        .collect();
    let num_pt: Vec<f64> = (0..pts.len())
        .map(|i| {
            let (mut a, mut b) = (pts.clone(), pts.clone());
            a[i] += h;
            b[i] -= h;
            (loss(&planes, &a) - loss(&planes, &b)) / (2.0 * h)
        })
        .collect();
    // Bilinear in the planes (exact up to rounding ~1e-10) and piecewise bilinear in
    // the points away from texel edges.
    assert!(
        rel_err(&gpl, &num_pl, 1e-6) <= 1e-6,
        "plane gradient vs central differences"
    );
    assert!(
        rel_err(&gpt, &num_pt, 1e-6) <= 1e-6,
        "point gradient vs central differences"
    );
}

fn random_transforms(seed: u64) -> Vec<f64> {
    // Rotations from random 6D vectors, translations up to 0.5.
    let mut t = Vec::new();
    let r6 = uniform(6 * SKIN_JOINTS, -1.0, 1.0, seed);
    let tr = uniform(3 * SKIN_JOINTS, -0.5, 0.5, seed + 1);
    for j in 0..SKIN_JOINTS {
        let mut v = [0.0; 6];
        v.copy_from_slice(&r6[6 * j..6 * j + 6]);
        let m = rot6d_to_matrix(v);
        for r in 0..3 {
            t.extend_from_slice(&m[r]);
            t.push(tr[3 * j + r]);
        }
    }
    t
}

fn deform_inputs(n: usize, seed: u64) -> HostInputs<f64> {
    let mut quats = uniform(4 * n, -1.0, 1.0, seed + 2);
    for q in quats.chunks_exact_mut(4) {
        let norm = q.iter().map(|v| v * v).sum::<f64>().sqrt();
        q.iter_mut().for_each(|v| *v /= norm);
    }
    // Softmax-like weights: positive, summing to 1, a few dominant.
    let mut weights = uniform(SKIN_JOINTS * n, 0.0, 1.0, seed + 3);
    for w in weights.chunks_exact_mut(SKIN_JOINTS) {
        w.iter_mut().for_each(|v| *v = v.powi(6));
        let s: f64 = w.iter().sum();
        w.iter_mut().for_each(|v| *v /= s);
    }
    HostInputs {
        transforms: random_transforms(seed),
        means: uniform(3 * n, -1.0, 1.0, seed + 4),
        quats,
        log_scales: uniform(3 * n, -5.0, -2.0, seed + 5),
        offsets: uniform(3 * n, -0.05, 0.05, seed + 6),
        rot6d: uniform(6 * n, -1.0, 1.0, seed + 7),
        log_scale_deltas: uniform(3 * n, -0.3, 0.3, seed + 8),
        weights,
    }
}

/// Gradients on n posed Gaussians (mean, quaternion, log-scale), uniform in [-1, 1].
fn random_upstream(n: usize, seed: u64) -> Vec<DeformOutput<f64>> {
    let r = uniform(10 * n, -1.0, 1.0, seed);
    r.chunks_exact(10)
        .map(|c| DeformOutput {
            mean: [c[0], c[1], c[2]],
            quat: [c[3], c[4], c[5], c[6]],
            log_scale: [c[7], c[8], c[9]],
        })
        .collect()
}

fn flat_outputs(o: &[DeformOutput<f64>]) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
    (
        o.iter().flat_map(|g| g.mean).collect(),
        o.iter().flat_map(|g| g.quat).collect(),
        o.iter().flat_map(|g| g.log_scale).collect(),
    )
}

#[test]
fn deform_gpu_matches_cpu_reference() {
    let ctx = gpu();
    for n in [0usize, 1, 7, 1000, 100_003] {
        let host = deform_inputs(n, n as u64);
        let up = random_upstream(n, 99);
        let fwd = deform::reference::forward(&host);
        let bwd = deform::reference::backward(&host, &up);
        let b = |name: &str, v: &[f64]| ctx.upload(name, &to_f32(v)).expect("upload");
        let (t, m, q, s, o, r6, ds, w) = (
            b("t", &host.transforms),
            b("m", &host.means),
            b("q", &host.quats),
            b("s", &host.log_scales),
            b("o", &host.offsets),
            b("r6", &host.rot6d),
            b("ds", &host.log_scale_deltas),
            b("w", &host.weights),
        );
        let (um, uq, us) = flat_outputs(&up);
        let (gum, guq, gus) = (b("gm", &um), b("gq", &uq), b("gs", &us));
        let out = |name: &str, len: usize| {
            ctx.create_buffer(name, BufferDesc::gpu_only((len.max(1) * 4) as u64))
                .expect("buffer")
        };
        let (mut pm, mut pq, mut ps) = (out("pm", 3 * n), out("pq", 4 * n), out("ps", 3 * n));
        let (mut gm, mut go, mut g6, mut gd, mut gw) = (
            out("gm", 3 * n),
            out("go", 3 * n),
            out("g6", 6 * n),
            out("gd", 3 * n),
            out("gw", SKIN_JOINTS * n),
        );
        let terms = out("terms", deform::transform_terms_len(n as u32));
        let partials_len = deform::transform_partials_len(n as u32);
        let mut partials = out("partials", partials_len);
        {
            let inputs = DeformInputs {
                transforms: &t,
                means: &m,
                quats: &q,
                log_scales: &s,
                offsets: &o,
                rot6d: &r6,
                log_scale_deltas: &ds,
                weights: &w,
            };
            let grads = DeformGrads {
                means: &gm,
                offsets: &go,
                rot6d: &g6,
                log_scale_deltas: &gd,
                weights: &gw,
                transform_terms: &terms,
            };
            let mut rec = ctx.record("deform test").expect("record");
            deform::record_forward(&mut rec, &inputs, &pm, &pq, &ps, n as u32, 0.0).expect("fwd");
            deform::record_backward(&mut rec, &inputs, &gum, &guq, &gus, &grads, n as u32)
                .expect("bwd");
            deform::record_transform_grad(&mut rec, &w, &terms, &partials, n as u32)
                .expect("transform grad");
            rec.submit_and_wait().expect("submit");
        }
        let read = |buf: &mut drape_engine::Buffer, len: usize| {
            to_f64(&ctx.read_buffer::<f32>(buf, len).expect("read"))
        };
        let (rm, rq, rs) = flat_outputs(&fwd);
        // Sums of 24 weighted transforms and 3x3 products in f32.
        for (what, gpu_v, cpu_v) in [
            ("mean", read(&mut pm, 3 * n), rm),
            ("quat", read(&mut pq, 4 * n), rq),
            ("log scale", read(&mut ps, 3 * n), rs),
        ] {
            let e = rel_err(&gpu_v, &cpu_v, 1e-3);
            assert!(e <= 1e-5, "n {n}: posed {what} relative error {e:e}");
        }
        let cat = |f: &dyn Fn(&drape_shared::deform::DeformGrad<f64>) -> Vec<f64>| {
            bwd.iter().flat_map(f).collect::<Vec<f64>>()
        };
        let checks = [
            ("mean", read(&mut gm, 3 * n), cat(&|g| g.mean.to_vec())),
            ("offset", read(&mut go, 3 * n), cat(&|g| g.offset.to_vec())),
            ("rot6d", read(&mut g6, 6 * n), cat(&|g| g.rot6d.to_vec())),
            (
                "log-scale delta",
                read(&mut gd, 3 * n),
                cat(&|g| g.log_scale_delta.to_vec()),
            ),
            (
                "weights",
                read(&mut gw, SKIN_JOINTS * n),
                cat(&|g| g.weights.to_vec()),
            ),
        ];
        for (what, gpu_v, cpu_v) in checks {
            // The 6D backward divides by column norms as small as ~0.01: f32 rounding
            // is amplified there, so 1e-4 of the array's largest gradient.
            let e = rel_err(&gpu_v, &cpu_v, 1e-3);
            assert!(e <= 1e-4, "n {n}: gradient on {what}: relative error {e:e}");
        }
        // The transforms' gradient: a sum over up to 100,003 Gaussians of terms of
        // either sign, each rounded in f32 (chunks of 256 summed in f32, then in f64):
        // 1e-4 of the largest entry.
        let gpu_t = deform::sum_transform_partials(
            &ctx.read_buffer::<f32>(&mut partials, partials_len)
                .expect("read"),
        );
        let cpu_t = deform::reference::transform_grad(&host, &bwd);
        let e = rel_err(&gpu_t, &cpu_t, 1e-3);
        assert!(
            e <= 1e-4,
            "n {n}: gradient on the transforms: relative error {e:e}"
        );
        if n == 0 {
            assert!(gpu_t.iter().all(|&v| v == 0.0), "no Gaussians, no gradient");
        }
    }
}

#[test]
fn transform_gradient_matches_central_differences() {
    let n = 9;
    let host = deform_inputs(n, 77);
    let up = random_upstream(n, 78);
    let loss = |h: &HostInputs<f64>| -> f64 {
        deform::reference::forward(h)
            .iter()
            .zip(&up)
            .map(|(o, u)| {
                (0..3).map(|k| o.mean[k] * u.mean[k]).sum::<f64>()
                    + (0..4).map(|k| o.quat[k] * u.quat[k]).sum::<f64>()
            })
            .sum()
    };
    let analytic =
        deform::reference::transform_grad(&host, &deform::reference::backward(&host, &up));
    let h = 1e-6;
    let numeric: Vec<f64> = (0..host.transforms.len())
        .map(|i| {
            let (mut a, mut b) = (host.clone(), host.clone());
            a.transforms[i] += h;
            b.transforms[i] -= h;
            (loss(&a) - loss(&b)) / (2.0 * h)
        })
        .collect();
    // Linear in each transform entry away from Shepperd branch switches: central
    // differences in f64 agree to ~1e-9.
    let e = rel_err(&analytic, &numeric, 1e-6);
    assert!(
        e <= 1e-6,
        "transforms: relative error {e:e} against central differences"
    );
}

#[test]
fn deform_gradients_match_central_differences() {
    let n = 5;
    let host = deform_inputs(n, 42);
    let up = random_upstream(n, 43);
    let loss = |h: &HostInputs<f64>| -> f64 {
        deform::reference::forward(h)
            .iter()
            .zip(&up)
            .map(|(o, u)| {
                (0..3)
                    .map(|k| o.mean[k] * u.mean[k] + o.log_scale[k] * u.log_scale[k])
                    .sum::<f64>()
                    + (0..4).map(|k| o.quat[k] * u.quat[k]).sum::<f64>()
            })
            .sum()
    };
    let bwd = deform::reference::backward(&host, &up);
    let h = 1e-6;
    type Field = fn(&mut HostInputs<f64>) -> &mut Vec<f64>;
    let fields: [(&str, Field, Vec<f64>); 5] = [
        (
            "mean",
            |h| &mut h.means,
            bwd.iter().flat_map(|g| g.mean).collect(),
        ),
        (
            "offset",
            |h| &mut h.offsets,
            bwd.iter().flat_map(|g| g.offset).collect(),
        ),
        (
            "rot6d",
            |h| &mut h.rot6d,
            bwd.iter().flat_map(|g| g.rot6d).collect(),
        ),
        (
            "log-scale delta",
            |h| &mut h.log_scale_deltas,
            bwd.iter().flat_map(|g| g.log_scale_delta).collect(),
        ),
        (
            "weights",
            |h| &mut h.weights,
            bwd.iter().flat_map(|g| g.weights).collect(),
        ),
    ];
    for (what, field, analytic) in fields {
        let len = field(&mut host.clone()).len();
        let numeric: Vec<f64> = (0..len)
            .map(|i| {
                let (mut a, mut b) = (host.clone(), host.clone());
                field(&mut a)[i] += h;
                field(&mut b)[i] -= h;
                (loss(&a) - loss(&b)) / (2.0 * h)
            })
            .collect();
        // Smooth away from Shepperd branch switches (random inputs are far from them);
        // central differences at 1e-6 in f64 agree to ~1e-9.
        let e = rel_err(&analytic, &numeric, 1e-6);
        assert!(
            e <= 1e-6,
            "{what}: relative error {e:e} against central differences"
        );
    }
}

#[test]
fn rot6d_gives_rotations_and_quaternions_match_them() {
    use drape_shared::deform::matrix_to_quat;
    use drape_shared::splat::project::{normalize_quat, quat_to_mat};
    for (i, r) in uniform(6 * 200, -2.0, 2.0, 5).chunks_exact(6).enumerate() {
        let m = rot6d_to_matrix([r[0], r[1], r[2], r[3], r[4], r[5]]);
        for a in 0..3 {
            for b in 0..3 {
                let dot: f64 = (0..3).map(|k| m[a][k] * m[b][k]).sum();
                assert!(
                    (dot - if a == b { 1.0 } else { 0.0 }).abs() < 1e-12,
                    "case {i}: rows not orthonormal"
                );
            }
        }
        let det = m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
            - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
            + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]);
        assert!((det - 1.0).abs() < 1e-12, "case {i}: det {det}");
        let back = quat_to_mat(normalize_quat(matrix_to_quat(&m)).0);
        for a in 0..3 {
            for b in 0..3 {
                assert!(
                    (back[a][b] - m[a][b]).abs() < 1e-12,
                    "case {i}: quaternion does not give the matrix back"
                );
            }
        }
    }
}

/// The pose-dependent offsets (`deform::record_pose_blend_*`) on the GPU against the
/// CPU reference, at 0, 1, 7 and 1,000 Gaussians (100,003 would need a 248 MB basis
/// binding, above lavapipe's 128 MiB maxStorageBufferRange; the kernel indexes each
/// Gaussian alike). Tolerance 1e-5 of the largest value: a 207-term f32 dot product
/// summed in the same order on both sides, but the GPU may fuse multiply-adds.
#[test]
fn pose_blend_gpu_matches_cpu_reference() {
    use deform::{POSE_BLEND_FLOATS, POSE_FEATURES};
    let ctx = gpu();
    for n in [0usize, 1, 7, 1000] {
        let basis = uniform(n * POSE_BLEND_FLOATS, -0.01, 0.01, 40 + n as u64);
        let features = uniform(POSE_FEATURES, -1.0, 1.0, 41);
        let decoded = uniform(3 * n, -0.05, 0.05, 42);
        let g = uniform(3 * n, -1.0, 1.0, 43);
        let b = |name: &str, v: &[f64]| {
            ctx.upload(
                name,
                &to_f32(&if v.is_empty() { vec![0.0] } else { v.to_vec() }),
            )
            .expect("upload")
        };
        let (bb, bf, bd, bg) = (
            b("basis", &basis),
            b("features", &features),
            b("decoded", &decoded),
            b("grad offsets", &g),
        );
        let mut offsets = ctx
            .create_buffer("offsets", BufferDesc::gpu_only(4 * (3 * n).max(1) as u64))
            .expect("buffer");
        let mut gbasis = ctx
            .create_buffer(
                "grad basis",
                BufferDesc::gpu_only(4 * (n * POSE_BLEND_FLOATS).max(1) as u64),
            )
            .expect("buffer");
        {
            let mut rec = ctx.record("pose blend").expect("record");
            deform::record_pose_blend_forward(&mut rec, &bb, &bf, &bd, &offsets, n as u32)
                .expect("fwd");
            deform::record_pose_blend_backward(&mut rec, &bf, &bg, &gbasis, n as u32).expect("bwd");
            rec.submit_and_wait().expect("submit");
        }
        let got_o = to_f64(&ctx.read_buffer::<f32>(&mut offsets, 3 * n).expect("read"));
        let got_g = to_f64(
            &ctx.read_buffer::<f32>(&mut gbasis, n * POSE_BLEND_FLOATS)
                .expect("read"),
        );
        let (f32s, f32f, f32d, f32g) = (
            to_f32(&basis),
            to_f32(&features),
            to_f32(&decoded),
            to_f32(&g),
        );
        let want_o = to_f64(&deform::reference::pose_blend_forward(&f32s, &f32f, &f32d));
        let want_g = to_f64(&deform::reference::pose_blend_backward(&f32f, &f32g));
        assert_eq!((got_o.len(), got_g.len()), (want_o.len(), want_g.len()));
        if n > 0 {
            assert!(
                rel_err(&got_o, &want_o, 1e-6) <= 1e-5,
                "n = {n}: offsets {}",
                rel_err(&got_o, &want_o, 1e-6)
            );
            assert!(
                rel_err(&got_g, &want_g, 1e-6) <= 1e-6,
                "n = {n}: basis gradient (one product each) {}",
                rel_err(&got_g, &want_g, 1e-6)
            );
            // The blend is not vacuous: it moves the offsets.
            assert!(
                rel_err(&got_o, &decoded, 1e-6) > 1e-3,
                "n = {n}: the blend added nothing"
            );
        }
    }
}

/// The basis gradient against f64 central differences of `Σ g · offsets`.
#[test]
fn pose_blend_gradient_matches_central_differences() {
    use deform::{POSE_BLEND_FLOATS, POSE_FEATURES};
    let n = 3;
    let mut basis = uniform(n * POSE_BLEND_FLOATS, -0.01, 0.01, 50);
    let features = uniform(POSE_FEATURES, -1.0, 1.0, 51);
    let decoded = uniform(3 * n, -0.05, 0.05, 52);
    let g = uniform(3 * n, -1.0, 1.0, 53);
    let analytic = deform::reference::pose_blend_backward(&features, &g);
    let loss = |b: &[f64]| {
        deform::reference::pose_blend_forward(b, &features, &decoded)
            .iter()
            .zip(&g)
            .map(|(o, w)| o * w)
            .sum::<f64>()
    };
    let h = 1e-6;
    let mut worst = 0.0f64;
    for j in (0..basis.len()).step_by(7) {
        let keep = basis[j];
        basis[j] = keep + h;
        let up = loss(&basis);
        basis[j] = keep - h;
        let down = loss(&basis);
        basis[j] = keep;
        worst = worst.max(((up - down) / (2.0 * h) - analytic[j]).abs());
    }
    // A linear function: central differences are exact to rounding (~1e-10 here).
    assert!(worst <= 1e-8, "largest difference {worst:e}");
}
