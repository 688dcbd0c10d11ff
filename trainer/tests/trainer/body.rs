//! The procedural body and the SMPL-format loader.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use drape_trainer::body::kinematics::{
    da_pose, forward_kinematics, pose_body, pose_gradient, regress_joints, shaped_vertices, t_pose,
    Pose,
};
use drape_trainer::body::procedural::{default_body, BodyOptions};
use drape_trainer::body::{SmplModel, NUM_JOINTS};
use drape_trainer::mesh::{is_watertight, self_intersections, signed_volume};
use drape_trainer::npy::{self, Array};
use glam::DVec3;

fn temp(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("drape-body-tests-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

fn body() -> SmplModel {
    default_body(&BodyOptions::default())
}

#[test]
fn default_body_is_a_closed_human_sized_mesh() {
    let b = body();
    let n = b.num_vertices();
    assert!((3000..20_000).contains(&n), "{n} vertices");
    assert!(
        is_watertight(&b.faces),
        "every edge is shared by exactly two faces"
    );
    assert!(
        signed_volume(&b.v_template, &b.faces) > 0.03,
        "outward-facing, with a body's volume (m^3)"
    );
    let ys: Vec<f64> = b.v_template.iter().map(|v| v[1]).collect();
    let height =
        ys.iter().cloned().fold(f64::MIN, f64::max) - ys.iter().cloned().fold(f64::MAX, f64::min);
    assert!((1.6..1.85).contains(&height), "height {height} m");
    let span = b.v_template.iter().map(|v| v[0]).fold(f64::MIN, f64::max) * 2.0;
    assert!((1.5..1.8).contains(&span), "arm span {span} m in T-pose");
}

#[test]
fn default_body_does_not_intersect_itself_in_t_pose() {
    let b = body();
    let hits = self_intersections(&b.v_template, &b.faces, 5);
    assert!(hits.is_empty(), "intersecting face pairs: {hits:?}");
}

#[test]
fn default_body_weights_and_regressor() {
    let b = body();
    for (i, w) in b.weights.iter().enumerate() {
        let s: f64 = w.iter().sum();
        assert!((s - 1.0).abs() <= 1e-6, "vertex {i}: weights sum to {s}");
        assert!(w.iter().all(|&x| x >= 0.0));
    }
    let joints = regress_joints(&b, &b.v_template);
    for (j, (got, want)) in joints
        .iter()
        .zip(drape_trainer::body::procedural::JOINTS)
        .enumerate()
    {
        let d =
            ((got[0] - want[0]).powi(2) + (got[1] - want[1]).powi(2) + (got[2] - want[2]).powi(2))
                .sqrt();
        // 4 cm: the ring centroid sits on the limb axis, the joints are placed by hand.
        assert!(d < 0.04, "joint {j} regresses {d} m away from its place");
    }
}

#[test]
fn shape_directions_change_height_and_girth() {
    let b = body();
    let height = |v: &[DVec3]| v.iter().map(|p| p[1]).fold(f64::MIN, f64::max);
    let tall = shaped_vertices(&b, &[2.0]);
    assert!(height(&tall) > height(&b.v_template) * 1.05);
    let wide = shaped_vertices(&b, &[0.0, 2.0]);
    let waist = |v: &[DVec3]| {
        v.iter()
            .filter(|p| (p[1] - 1.1).abs() < 0.02 && p[0].abs() < 0.3)
            .map(|p| p[0].abs())
            .fold(0.0, f64::max)
    };
    assert!(waist(&wide) > waist(&b.v_template) * 1.1);
}

#[test]
fn rest_pose_reproduces_the_template_exactly() {
    let b = body();
    let posed = pose_body(&b, &[], &t_pose(), DVec3::ZERO);
    assert!(posed.vertices == b.v_template, "bit-identical");
}

#[test]
fn da_pose_spreads_the_legs() {
    let b = body();
    let posed = pose_body(&b, &[], &da_pose(), DVec3::ZERO);
    // Left ankle (joint 7) moves outward (+x) and up.
    assert!(
        posed.joints[7][0] > 0.3 && posed.joints[7][1] > 0.25,
        "{:?}",
        posed.joints[7]
    );
    assert!(posed.joints[8][0] < -0.3);
}

#[test]
fn pose_gradient_matches_finite_differences() {
    let b = body();
    let joints = regress_joints(&b, &b.v_template);
    let mut pose: Pose = [DVec3::ZERO; NUM_JOINTS];
    for (j, p) in pose.iter_mut().enumerate() {
        *p = DVec3::new(
            0.3 * ((j * 7 % 5) as f64 - 2.0) / 2.0,
            0.2 * ((j * 3 % 4) as f64 - 1.5),
            0.25 * ((j % 3) as f64 - 1.0),
        );
    }
    // A linear loss on the transforms with fixed random-ish weights.
    let weight = |j: usize, r: usize, c: usize| ((j * 31 + r * 7 + c * 3) % 11) as f64 / 11.0 - 0.5;
    let loss = |p: &Pose| {
        let (a, _) = forward_kinematics(&b.parents, &joints, p);
        (0..NUM_JOINTS)
            .flat_map(|j| (0..3).flat_map(move |r| (0..4).map(move |c| (j, r, c))))
            .map(|(j, r, c)| weight(j, r, c) * a[j][r][c])
            .sum::<f64>()
    };
    let mut grad_a = [[[0.0; 4]; 3]; NUM_JOINTS];
    for j in 0..NUM_JOINTS {
        for r in 0..3 {
            for c in 0..4 {
                grad_a[j][r][c] = weight(j, r, c);
            }
        }
    }
    let analytic = pose_gradient(&b.parents, &joints, &pose, &grad_a);
    // Central differences, h = 1e-6 in f64: error ~h^2 + 1e-16/h, far below 1e-6.
    let h = 1e-6;
    for j in 0..NUM_JOINTS {
        for i in 0..3 {
            let mut plus = pose;
            plus[j][i] += h;
            let mut minus = pose;
            minus[j][i] -= h;
            let numeric = (loss(&plus) - loss(&minus)) / (2.0 * h);
            assert!(
                (numeric - analytic[j][i]).abs() <= 1e-6 * (1.0 + numeric.abs()),
                "joint {j} axis {i}: analytic {} numeric {numeric}",
                analytic[j][i]
            );
        }
    }
}

#[test]
fn npz_round_trip_through_the_loader() {
    let b = body();
    let path = temp("body.npz");
    b.write_npz(&path).expect("write");
    let back = SmplModel::load_npz(&path).expect("load");
    assert_eq!(back, b);
}

fn with_arrays(name: &str, edit: impl FnOnce(&mut BTreeMap<String, Array>)) -> PathBuf {
    let mut arrays = body().to_arrays();
    edit(&mut arrays);
    let path = temp(name);
    npy::write_npz(&path, &arrays).unwrap();
    path
}

fn expect_error(path: &Path, needles: &[&str]) {
    let err = SmplModel::load_npz(path)
        .expect_err("must not load")
        .to_string();
    for n in needles {
        assert!(err.contains(n), "'{n}' not in: {err}");
    }
}

#[test]
fn loader_names_a_missing_key() {
    let path = with_arrays("missing.npz", |a| {
        a.remove("J_regressor");
    });
    expect_error(&path, &["missing.npz", "J_regressor", "missing key"]);
}

#[test]
fn loader_names_a_wrong_shape() {
    let path = with_arrays("shape.npz", |a| {
        let w = a.get_mut("weights").unwrap();
        let v = w.shape[0];
        *w = Array::f64(vec![v, 23], vec![1.0 / 23.0; v * 23]);
    });
    expect_error(&path, &["shape.npz", "weights", "shape"]);
}

#[test]
fn loader_names_a_nan() {
    let path = with_arrays("nan.npz", |a| {
        a.get_mut("v_template").unwrap().data[5] = f64::NAN;
    });
    expect_error(&path, &["nan.npz", "v_template", "not finite"]);
}

#[test]
fn loader_names_a_truncated_file() {
    let path = temp("truncated.npz");
    body().write_npz(&path).unwrap();
    let bytes = std::fs::read(&path).unwrap();
    drape_io::write(&path, &bytes[..bytes.len() / 3]).unwrap();
    expect_error(&path, &["truncated.npz"]);
}
