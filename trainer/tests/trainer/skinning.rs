//! Linear blend skinning: the GPU kernels against the CPU reference (same shared
//! functions), finite differences in f64 for every gradient, and the pose gradient
//! through the whole body.

use drape_engine::ops::skinning::{reference, Skinning, TRANSFORMS_LEN};
use drape_engine::BufferDesc;
use drape_tests::gpu;
use drape_trainer::body::kinematics::{
    forward_kinematics, pose_body, pose_gradient, regress_joints, Pose,
};
use drape_trainer::body::procedural::{default_body, BodyOptions};
use drape_trainer::body::NUM_JOINTS;
use glam::DVec3;
use rand::{Rng, SeedableRng};

fn random_pose(seed: u64) -> Pose {
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    let mut p = [DVec3::ZERO; NUM_JOINTS];
    for a in p.iter_mut() {
        *a = DVec3::from_array([0, 1, 2].map(|_| rng.random_range(-0.6..0.6)));
    }
    p
}

fn flat_transforms(pose: &Pose, model: &drape_trainer::body::SmplModel) -> Vec<f64> {
    let joints = regress_joints(model, &model.v_template);
    let (a, _) = forward_kinematics(&model.parents, &joints, pose);
    a.iter().flatten().flatten().copied().collect()
}

fn to_f32(v: &[f64]) -> Vec<f32> {
    v.iter().map(|&x| x as f32).collect()
}

#[test]
fn gpu_skinning_matches_cpu_on_10_random_poses() {
    let gpu = gpu();
    let model = default_body(&BodyOptions::default());
    let n = model.num_vertices();
    let points: Vec<f32> = to_f32(
        &model
            .v_template
            .iter()
            .flat_map(|v| v.to_array())
            .collect::<Vec<_>>(),
    );
    let weights: Vec<f32> = to_f32(&model.weights.iter().flatten().copied().collect::<Vec<_>>());
    let b_points = gpu.upload("points", &points).unwrap();
    let b_weights = gpu.upload("weights", &weights).unwrap();
    let mut out = gpu
        .create_buffer("skinned", BufferDesc::gpu_only(12 * n as u64))
        .unwrap();
    let plan = Skinning::new(&gpu, n).unwrap();
    for seed in 0..10 {
        let t = to_f32(&flat_transforms(&random_pose(seed), &model));
        let b_t = gpu.upload("transforms", &t).unwrap();
        let mut rec = gpu.record("skin").unwrap();
        plan.record_fwd(&mut rec, &b_t, &b_weights, &b_points, &out, n as u32)
            .unwrap();
        rec.submit_and_wait().unwrap();
        let got = gpu.read_buffer::<f32>(&mut out, 3 * n).unwrap();
        let want = reference::forward(&t, &weights, &points);
        let err = got
            .iter()
            .zip(&want)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f32::max);
        // 1e-5 m: the same f32 operations on both sides, up to fused multiply-adds.
        assert!(err <= 1e-5, "pose {seed}: max error {err:e}");
    }
}

#[test]
fn gpu_skinning_backward_matches_cpu() {
    let gpu = gpu();
    let model = default_body(&BodyOptions::default());
    let n = model.num_vertices();
    let points: Vec<f32> = to_f32(
        &model
            .v_template
            .iter()
            .flat_map(|v| v.to_array())
            .collect::<Vec<_>>(),
    );
    let weights: Vec<f32> = to_f32(&model.weights.iter().flatten().copied().collect::<Vec<_>>());
    let t = to_f32(&flat_transforms(&random_pose(3), &model));
    let mut rng = rand::rngs::StdRng::seed_from_u64(9);
    let g: Vec<f32> = (0..3 * n).map(|_| rng.random_range(-1.0..1.0)).collect();
    let (bp, bw, bt, bg) = (
        gpu.upload("p", &points).unwrap(),
        gpu.upload("w", &weights).unwrap(),
        gpu.upload("t", &t).unwrap(),
        gpu.upload("g", &g).unwrap(),
    );
    let mut gp = gpu
        .create_buffer("gp", BufferDesc::gpu_only(12 * n as u64))
        .unwrap();
    let mut gw = gpu
        .create_buffer("gw", BufferDesc::gpu_only(96 * n as u64))
        .unwrap();
    let mut gt = gpu
        .create_buffer("gt", BufferDesc::gpu_only(4 * TRANSFORMS_LEN as u64))
        .unwrap();
    let plan = Skinning::new(&gpu, n).unwrap();
    let mut rec = gpu.record("skin bwd").unwrap();
    plan.record_bwd(&mut rec, &bt, &bw, &bp, &bg, &gp, &gw, &gt, n as u32)
        .unwrap();
    rec.submit_and_wait().unwrap();
    let (cp, cw, ct) = reference::backward(&t, &weights, &points, &g);
    let rel = |a: &[f32], b: &[f32]| {
        let num: f64 = a.iter().zip(b).map(|(x, y)| f64::from(x - y).powi(2)).sum();
        let den: f64 = b.iter().map(|y| f64::from(*y).powi(2)).sum();
        (num / den).sqrt()
    };
    // 1e-4 relative: the transform gradient sums ~10^4 terms in a different order.
    assert!(
        rel(&gpu.read_buffer::<f32>(&mut gp, 3 * n).unwrap(), &cp) <= 1e-4,
        "points"
    );
    assert!(
        rel(&gpu.read_buffer::<f32>(&mut gw, 24 * n).unwrap(), &cw) <= 1e-4,
        "weights"
    );
    assert!(
        rel(
            &gpu.read_buffer::<f32>(&mut gt, TRANSFORMS_LEN).unwrap(),
            &ct
        ) <= 1e-4,
        "transforms"
    );
}

/// f64 central differences (h = 1e-6: error ~h^2 + 1e-16/h, below the 1e-7 bound)
/// of a linear loss on the skinned points, for every input group.
#[test]
fn skinning_gradients_match_finite_differences() {
    let mut rng = rand::rngs::StdRng::seed_from_u64(4);
    let n = 20;
    let points: Vec<f64> = (0..3 * n).map(|_| rng.random_range(-1.0..1.0)).collect();
    let mut weights: Vec<f64> = (0..24 * n).map(|_| rng.random_range(0.0..1.0)).collect();
    for row in weights.chunks_mut(24) {
        let s: f64 = row.iter().sum();
        row.iter_mut().for_each(|w| *w /= s);
    }
    let model = default_body(&BodyOptions::default());
    let transforms = flat_transforms(&random_pose(5), &model);
    let g: Vec<f64> = (0..3 * n).map(|_| rng.random_range(-1.0..1.0)).collect();
    let loss = |t: &[f64], w: &[f64], p: &[f64]| {
        reference::forward(t, w, p)
            .iter()
            .zip(&g)
            .map(|(a, b)| a * b)
            .sum::<f64>()
    };
    let (gp, gw, gt) = reference::backward(&transforms, &weights, &points, &g);
    let h = 1e-6;
    let check = |name: &str, analytic: &[f64], perturb: &dyn Fn(usize, f64) -> f64| {
        for (i, a) in analytic.iter().enumerate() {
            let numeric = (perturb(i, h) - perturb(i, -h)) / (2.0 * h);
            assert!(
                (numeric - a).abs() <= 1e-7 * (1.0 + numeric.abs()),
                "{name}[{i}]: analytic {a}, numeric {numeric}"
            );
        }
    };
    check("points", &gp, &|i, d| {
        let mut p = points.clone();
        p[i] += d;
        loss(&transforms, &weights, &p)
    });
    check("weights", &gw, &|i, d| {
        let mut w = weights.clone();
        w[i] += d;
        loss(&transforms, &w, &points)
    });
    check("transforms", &gt, &|i, d| {
        let mut t = transforms.clone();
        t[i] += d;
        loss(&t, &weights, &points)
    });
}

/// The pose gradient through skinning and kinematics, against finite differences of
/// the posed body itself.
#[test]
fn pose_gradient_through_skinning_matches_finite_differences() {
    let model = default_body(&BodyOptions::default());
    let joints = regress_joints(&model, &model.v_template);
    let pose = random_pose(6);
    let mut rng = rand::rngs::StdRng::seed_from_u64(8);
    let g: Vec<f64> = (0..3 * model.num_vertices())
        .map(|_| rng.random_range(-1.0..1.0))
        .collect();
    let loss = |p: &Pose| {
        pose_body(&model, &[], p, DVec3::ZERO)
            .vertices
            .iter()
            .flat_map(|v| v.to_array())
            .zip(&g)
            .map(|(a, b)| a * b)
            .sum::<f64>()
    };
    let points: Vec<f64> = model.v_template.iter().flat_map(|v| v.to_array()).collect();
    let weights: Vec<f64> = model.weights.iter().flatten().copied().collect();
    let (_, _, gt) = reference::backward(&flat_transforms(&pose, &model), &weights, &points, &g);
    let mut grad_a = [[[0.0; 4]; 3]; NUM_JOINTS];
    for (k, v) in gt.iter().enumerate() {
        grad_a[k / 12][(k % 12) / 4][k % 4] = *v;
    }
    let analytic = pose_gradient(&model.parents, &joints, &pose, &grad_a);
    let h = 1e-6;
    for j in [0, 1, 4, 9, 16, 18, 20] {
        for i in 0..3 {
            let mut plus = pose;
            plus[j][i] += h;
            let mut minus = pose;
            minus[j][i] -= h;
            let numeric = (loss(&plus) - loss(&minus)) / (2.0 * h);
            // Relative 1e-6: the loss sums ~10^4 terms, so rounding in the
            // difference quotient is ~1e-16 * 10^4 / 1e-6.
            assert!(
                (numeric - analytic[j][i]).abs() <= 1e-6 * (1.0 + numeric.abs()),
                "joint {j} axis {i}: analytic {} numeric {numeric}",
                analytic[j][i]
            );
        }
    }
}
