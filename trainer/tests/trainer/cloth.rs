//! The XPBD cloth simulator: a pinned square drapes and settles; the two garments on a
//! walk stay outside the body, no edge stretches by more than 10%, finite and
//! deterministic (also at 3x speed and with one substep).

use drape_trainer::body::procedural::{default_body, BodyOptions};
use drape_trainer::cloth::{simulate, ClothParams, ClothSim};
use drape_trainer::collider::BodyCollider;
use drape_trainer::garment::{pants, tshirt, Garment};
use drape_trainer::motion::{procedural, MotionKind};
use glam::DVec3;

/// A 21x21 grid of 1 m, pinned at two corners, with no body to hit.
fn square() -> Garment {
    let n = 21;
    let mut vertices = Vec::new();
    for i in 0..n {
        for j in 0..n {
            vertices.push(DVec3::new(
                i as f64 / (n - 1) as f64,
                1.5,
                j as f64 / (n - 1) as f64,
            ));
        }
    }
    let mut faces = Vec::new();
    for i in 0..n - 1 {
        for j in 0..n - 1 {
            let a = (i * n + j) as u32;
            faces.push([a, a + n as u32, a + 1]);
            faces.push([a + 1, a + n as u32, a + n as u32 + 1]);
        }
    }
    let mut attached = vec![false; n * n];
    attached[0] = true;
    attached[n - 1] = true;
    let count = vertices.len();
    Garment {
        name: "square".into(),
        uvs: vec![[0.0; 2]; count],
        weights: vec![[0.0; 24]; count],
        weights_blend6: vec![[0.0; 24]; count],
        vertices,
        faces,
        attached,
        attach_joint: 0,
        build_pose: [DVec3::ZERO; 24],
    }
}

const FRAMES: usize = 450;

#[test]
fn pinned_square_settles_under_its_pins() {
    let cloth = square();
    let pins = [cloth.vertices[0], cloth.vertices[20]];
    // Damping 2/s (the default is 0.5/s, air-like): a pinned sheet otherwise swings as a
    // pendulum for tens of seconds.
    let mut sim = ClothSim::new(
        &cloth,
        ClothParams {
            damping: 2.0,
            ..ClothParams::default()
        },
    );
    // A collider far away: nothing to hit.
    let far = BodyCollider::new(
        vec![
            DVec3::new(100.0, 100.0, 100.0),
            DVec3::new(101.0, 100.0, 100.0),
            DVec3::new(100.0, 101.0, 100.0),
        ],
        &[[0, 1, 2]],
    );
    let targets = |_s: f64| cloth.vertices.clone();
    let dt = 1.0 / 30.0;
    let mut kinetic = Vec::new();
    for _ in 0..FRAMES {
        let before = sim.positions.clone();
        sim.step_frame(dt, &far, &targets);
        let e: f64 = sim
            .positions
            .iter()
            .zip(&before)
            .map(|(a, b)| (0..3).map(|k| ((a[k] - b[k]) / dt).powi(2)).sum::<f64>() * 0.5)
            .sum();
        kinetic.push(e);
    }
    // Settled: the kinetic energy of the last second is tiny next to the first.
    let early = kinetic[..30].iter().cloned().fold(0.0, f64::max);
    let late = kinetic[FRAMES - 30..].iter().cloned().fold(0.0, f64::max);
    eprintln!(
        "kinetic energy by second: {:?}",
        kinetic
            .iter()
            .step_by(30)
            .map(|e| format!("{e:.2e}"))
            .collect::<Vec<_>>()
    );
    // Settled: in the last second, 441 unit masses move at ~2 mm/s at most.
    assert!(
        late < 1e-3 && late < early * 1e-5,
        "kinetic energy: early {early:e}, late {late:e}"
    );
    // Hangs under the pins: every vertex below them, the free corners far below.
    // (1 cm of slack: bending stiffness lifts the cloth next to a pin a little.)
    assert!(sim.positions.iter().all(|p| p[1] <= pins[0][1] + 0.01));
    let lowest = sim.positions.iter().map(|p| p[1]).fold(f64::MAX, f64::min);
    assert!(
        lowest < 1.5 - 0.8,
        "the cloth hangs about its length below the pins (lowest {lowest})"
    );
    assert!(sim.max_strain() < 1.1, "strain {}", sim.max_strain());
}

fn walk_check(
    frames: usize,
    speed: f64,
    params: ClothParams,
) -> drape_trainer::cloth::SimulationResult {
    let body = default_body(&BodyOptions::default());
    let garments = [tshirt(&body), pants(&body)];
    let motion = procedural(MotionKind::Walk, frames, 30.0, speed);
    let r = simulate(&body, &garments, &motion, params, 20);
    assert_eq!(r.frames.len(), frames);
    assert!(!r.any_nan, "no NaN");
    // Penetration is measured after every frame against the posed body.
    assert!(
        r.max_penetration <= params.margin,
        "penetration {} m deeper than the margin {}",
        r.max_penetration,
        params.margin
    );
    eprintln!(
        "speed {speed}, {} substeps: max penetration {:.4} m, max strain {:.3} at {:?}",
        params.substeps, r.max_penetration, r.max_strain, r.max_strain_at
    );
    // The acceptance bound: no edge longer than 110% of its rest length after any frame.
    assert!(
        r.max_strain <= 1.10,
        "an edge stretched to {:.3} of its rest length (frame, garment, edge) {:?}",
        r.max_strain,
        r.max_strain_at
    );
    r
}

/// Three seconds of walking (2.7 gait cycles of the 0.9 Hz walk) at the default settings.
#[test]
fn walk_keeps_both_garments_outside_the_body() {
    walk_check(90, 1.0, ClothParams::default());
}

/// The simulation is a function of its inputs: two runs of the same motion give the
/// same bits (no hash order, threads or stale state in it). A short walk: the 90-frame
/// one above checks the bounds, this the repeatability.
#[test]
fn a_walk_simulated_twice_gives_identical_meshes() {
    let body = default_body(&BodyOptions::default());
    let garments = [tshirt(&body), pants(&body)];
    let motion = procedural(MotionKind::Walk, 12, 30.0, 1.0);
    let a = simulate(&body, &garments, &motion, ClothParams::default(), 20);
    let b = simulate(&body, &garments, &motion, ClothParams::default(), 20);
    assert_eq!(a.frames.len(), 12);
    assert!(a.frames == b.frames, "two runs give identical meshes");
}

/// The same three seconds of walking played three times as fast: in 30 frames, each
/// moving the limbs three times as far.
#[test]
fn walk_three_times_faster() {
    walk_check(30, 3.0, ClothParams::default());
}

/// One substep of 16 iterations a frame, through 1.5 s of walking (1.35 gait cycles; a
/// frame costs about twice the default's CPU: the 90-frame walk took two minutes here).
#[test]
fn walk_with_one_substep() {
    walk_check(45, 1.0, ClothParams::one_substep());
}

/// A garment made in another pose than the first one (an OBJ garment is made in the
/// T-pose, the project's in the A-pose) starts skinned into the start pose and drapes
/// like the same garment made in the A-pose.
#[test]
fn garments_made_in_different_poses_simulate_together() {
    use drape_trainer::body::kinematics::{pose_body, relative_transforms, skin, t_pose};
    let body = default_body(&BodyOptions::default());
    let shirt = tshirt(&body);
    let a = pose_body(&body, &[], &shirt.build_pose, DVec3::ZERO).transforms;
    let t = pose_body(&body, &[], &t_pose(), DVec3::ZERO).transforms;
    // The shirt taken into the T-pose by skinning, and declared made there.
    let shirt_t = Garment {
        vertices: skin(
            &shirt.weights_blend6,
            &relative_transforms(&t, &a),
            &shirt.vertices,
        ),
        build_pose: t_pose(),
        ..shirt.clone()
    };
    let motion = procedural(MotionKind::Walk, 10, 30.0, 1.0);
    let params = ClothParams::default();
    let together = simulate(&body, &[pants(&body), shirt_t], &motion, params, 20);
    let alone = simulate(&body, &[pants(&body), shirt], &motion, params, 20);
    assert!(!together.any_nan);
    assert!(
        together.max_penetration <= params.margin,
        "penetration {}",
        together.max_penetration
    );
    let last = |r: &drape_trainer::cloth::SimulationResult| r.frames.last().unwrap()[1].clone();
    let (x, y) = (last(&together), last(&alone));
    let mean = x
        .iter()
        .zip(&y)
        .map(|(p, q)| (0..3).map(|k| (p[k] - q[k]).powi(2)).sum::<f64>().sqrt())
        .sum::<f64>()
        / x.len() as f64;
    eprintln!(
        "mean distance between the two shirts after 10 frames: {mean:.4} m; strain {:.3}",
        together.max_strain
    );
    // 2 cm: the round trip through the T-pose changes the rest shape a little (7 mm
    // measured); the same shirt declared as made in the A-pose ends 19 cm away.
    assert!(mean < 0.02, "mean distance {mean} m");
    assert!(
        together.max_strain <= 1.10,
        "strain {}",
        together.max_strain
    );
}
