//! Garments, motions and Gaussian initialization on the default body.

use std::path::PathBuf;

use drape_trainer::avatar::groups::Layer;
use drape_trainer::body::gaussians::{gaussians_from_mesh, SkinnedMesh};
use drape_trainer::body::procedural::{default_body, BodyOptions};
use drape_trainer::garment::{load_obj, pants, tshirt, write_obj};
use drape_trainer::mesh::edge_face_counts;
use drape_trainer::motion::{procedural, Motion, MotionKind};

fn temp(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("drape-garment-tests-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

#[test]
fn gaussians_from_the_default_body() {
    let body = default_body(&BodyOptions::default());
    let mesh = SkinnedMesh {
        vertices: body.v_template.clone(),
        faces: body.faces.clone(),
        weights: body.weights.clone(),
        shapedirs: body.shapedirs.clone(),
    };
    let (cloud, sub) = gaussians_from_mesh(&mesh, 2, 0, Layer::Body);
    // Two midpoint subdivisions multiply the vertex count by about 16.
    assert!(
        (80_000..250_000).contains(&cloud.len()),
        "{} Gaussians",
        cloud.len()
    );
    assert_eq!(cloud.len(), sub.vertices.len());
    for w in &sub.weights {
        let s: f64 = w.iter().sum();
        assert!(
            (s - 1.0).abs() < 1e-9,
            "averaged weights stay a partition of unity"
        );
    }
    assert!(
        drape_trainer::mesh::is_watertight(&sub.faces),
        "subdivision keeps the surface closed"
    );
    // Flat along the normal: the third scale is a tenth of the others.
    let s = &cloud.log_scales[..3];
    assert!((s[0] - s[2] - (10f32).ln()).abs() < 1e-4);
}

#[test]
fn garments_are_open_where_clothes_are() {
    let body = default_body(&BodyOptions::default());
    for (g, openings) in [(tshirt(&body), 4), (pants(&body), 3)] {
        assert!(
            (1000..10_000).contains(&g.vertices.len()),
            "{}: {} vertices",
            g.name,
            g.vertices.len()
        );
        // Boundary loops: neck, two sleeves and the waist; waist and two legs.
        let counts = edge_face_counts(&g.faces);
        assert!(counts.values().all(|&c| c <= 2), "{}: manifold", g.name);
        let boundary: Vec<(u32, u32)> = counts
            .iter()
            .filter(|(_, &c)| c == 1)
            .map(|(&e, _)| e)
            .collect();
        let loops = count_loops(&boundary);
        assert!(
            loops >= openings,
            "{}: {loops} openings, expected at least {openings}",
            g.name
        );
        assert_eq!(g.uvs.len(), g.vertices.len());
        assert!(g.uvs.iter().flatten().all(|u| (0.0..=1.0).contains(u)));
        for w in g.weights.iter().chain(&g.weights_blend6) {
            assert!((w.iter().sum::<f64>() - 1.0).abs() < 1e-9);
        }
        assert!(g.attached.iter().any(|&a| a) && !g.attached.iter().all(|&a| a));
        // Rest lengths are what the simulator keeps: none may be (nearly) zero. 1 mm
        // is a tenth of the shortest edge the body mesh has.
        let shortest = counts
            .keys()
            .map(|&(a, b)| (g.vertices[a as usize] - g.vertices[b as usize]).length())
            .fold(f64::MAX, f64::min);
        assert!(shortest > 1e-3, "{}: an edge of {shortest} m", g.name);
    }
}

fn count_loops(edges: &[(u32, u32)]) -> usize {
    let mut parent: std::collections::HashMap<u32, u32> = Default::default();
    fn find(p: &mut std::collections::HashMap<u32, u32>, x: u32) -> u32 {
        let px = *p.entry(x).or_insert(x);
        if px == x {
            x
        } else {
            let r = find(p, px);
            p.insert(x, r);
            r
        }
    }
    for &(a, b) in edges {
        let (ra, rb) = (find(&mut parent, a), find(&mut parent, b));
        if ra != rb {
            parent.insert(ra, rb);
        }
    }
    let keys: Vec<u32> = parent.keys().copied().collect();
    let roots: std::collections::HashSet<u32> =
        keys.into_iter().map(|k| find(&mut parent, k)).collect();
    roots.len()
}

#[test]
fn obj_garment_round_trip_binds_to_the_body() {
    let body = default_body(&BodyOptions::default());
    let shirt = tshirt(&body);
    let path = temp("shirt.obj");
    write_obj(&path, &shirt.vertices, &shirt.faces, Some(&shirt.uvs)).unwrap();
    let loaded = load_obj(&path, &body).expect("load");
    assert_eq!(loaded.faces.len(), shirt.faces.len());
    assert_eq!(loaded.vertices.len(), shirt.vertices.len());
    let err = load_obj(&temp("missing.obj"), &body)
        .expect_err("missing file")
        .to_string();
    assert!(err.contains("missing.obj"), "{err}");
}

#[test]
fn motions_round_trip_through_npz() {
    for kind in MotionKind::ALL {
        let m = procedural(kind, 45, 30.0, 1.0);
        assert_eq!(m.len(), 45);
        assert!(m.poses.iter().flatten().all(|v| v.is_finite()));
        let path = temp(&format!("{}.npz", kind.name()));
        m.save_npz(&path).unwrap();
        assert_eq!(Motion::load_npz(&path).unwrap(), m);
    }
    assert_eq!(MotionKind::parse("walk"), Some(MotionKind::Walk));
    assert_eq!(MotionKind::parse("moonwalk"), None);
}
