//! The loose T-shirt (`GarmentFit::Loose`, `drape synth --fit loose`): it is the tight
//! one with more ease and a lower hem, and the cloth simulation stays within the bounds
//! `cloth.rs` holds the tight garments to (no NaN, no vertex deeper in the body
//! than the collision margin, no edge longer than 110% of its rest length).

use drape_trainer::body::procedural::{default_body, BodyOptions};
use drape_trainer::cloth::{simulate, ClothParams};
use drape_trainer::collider::BodyCollider;
use drape_trainer::garment::{pants, tshirt, GarmentFit};
use drape_trainer::motion::{procedural, MotionKind};
use glam::DVec3;

#[test]
fn loose_shirt_is_looser_and_longer_than_the_tight_one() {
    let body = default_body(&BodyOptions::default());
    let (tight, loose) = (tshirt(&body), GarmentFit::Loose.upper(&body));
    assert_eq!(
        GarmentFit::default(),
        GarmentFit::Tight,
        "drape synth's default stays the tight shirt"
    );
    assert_eq!(GarmentFit::Tight.upper(&body), tight);
    let posed =
        drape_trainer::body::kinematics::pose_body(&body, &[], &loose.build_pose, DVec3::ZERO)
            .vertices;
    let collider = BodyCollider::new(posed, &body.faces);
    // Mean distance to the skin over the torso below the chest (y < 1.2 m in the A-pose).
    let ease = |g: &drape_trainer::garment::Garment| {
        let d: Vec<f64> = g
            .vertices
            .iter()
            .filter(|v| v[1] < 1.2 && v[1] > 1.0)
            .filter_map(|&v| collider.query(v).map(|q| q.0))
            .collect();
        d.iter().sum::<f64>() / d.len() as f64
    };
    let (et, el) = (ease(&tight), ease(&loose));
    eprintln!(
        "mean clearance below the chest: tight {:.1} mm, loose {:.1} mm",
        et * 1e3,
        el * 1e3
    );
    // The offsets are 15 and 45 mm; relaxation only ever pushes further out.
    assert!(et > 0.012 && et < 0.03, "tight {et}");
    assert!(el > 0.040, "loose {el}");
    let hem = |g: &drape_trainer::garment::Garment| {
        g.vertices.iter().map(|v| v[1]).fold(f64::MAX, f64::min)
    };
    assert!(
        hem(&loose) < hem(&tight) - 0.08,
        "hem: tight {} m, loose {} m",
        hem(&tight),
        hem(&loose)
    );
}

#[test]
fn loose_shirt_simulates_through_a_short_walk() {
    let body = default_body(&BodyOptions::default());
    let garments = [GarmentFit::Loose.upper(&body), pants(&body)];
    let motion = procedural(MotionKind::Walk, 30, 30.0, 1.0);
    let params = ClothParams::default();
    let r = simulate(&body, &garments, &motion, params, 20);
    eprintln!(
        "loose walk: max penetration {:.4} m, max strain {:.3} at {:?}",
        r.max_penetration, r.max_strain, r.max_strain_at
    );
    assert_eq!(r.frames.len(), 30);
    assert!(!r.any_nan, "no NaN");
    assert!(r.frames.iter().flatten().flatten().all(|v| v.is_finite()));
    assert!(
        r.max_penetration <= params.margin,
        "penetration {} m deeper than the margin {}",
        r.max_penetration,
        params.margin
    );
    assert!(
        r.max_strain <= 1.10,
        "an edge stretched to {:.3} of its rest length (frame, garment, edge) {:?}",
        r.max_strain,
        r.max_strain_at
    );
}
