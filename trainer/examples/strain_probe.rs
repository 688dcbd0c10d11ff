//! Diagnostic: per-frame strain of the garments on a walk, where it is, and whether the
//! stretched edge is in contact with the body.
//! `strain_probe [SPEED] [SUBSTEPS] [ITERATIONS] > frames.txt`
use drape_trainer::body::kinematics::pose_body;
use drape_trainer::body::procedural::{default_body, BodyOptions};
use drape_trainer::cloth::{simulate, ClothParams};
use drape_trainer::collider::BodyCollider;
use drape_trainer::garment::{pants, tshirt};
use drape_trainer::motion::{procedural, MotionKind};

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let speed: f64 = args.get(1).map(|s| s.parse().unwrap()).unwrap_or(1.0);
    let substeps: u32 = args.get(2).map(|s| s.parse().unwrap()).unwrap_or(8);
    let mut params = ClothParams::with_substeps(substeps);
    if let Some(iterations) = args.get(3) {
        params.iterations = iterations.parse().unwrap();
    }
    let body = default_body(&BodyOptions::default());
    let garments = [tshirt(&body), pants(&body)];
    let motion = procedural(MotionKind::Walk, 90, 30.0, speed);
    let t0 = std::time::Instant::now();
    let r = simulate(&body, &garments, &motion, params, 20);
    eprintln!(
        "sim {:.1}s max strain {:.3} at {:?} pen {:.4}",
        t0.elapsed().as_secs_f64(),
        r.max_strain,
        r.max_strain_at,
        r.max_penetration
    );
    let edges: Vec<Vec<(u32, u32, f64)>> = garments
        .iter()
        .map(|g| {
            let mut e: Vec<(u32, u32)> = g
                .faces
                .iter()
                .flat_map(|f| [(f[0], f[1]), (f[1], f[2]), (f[2], f[0])])
                .map(|(a, b)| (a.min(b), a.max(b)))
                .collect();
            e.sort();
            e.dedup();
            e.into_iter()
                .map(|(a, b)| {
                    (
                        a,
                        b,
                        (g.vertices[a as usize] - g.vertices[b as usize]).length(),
                    )
                })
                .collect()
        })
        .collect();
    for (f, frame) in r.frames.iter().enumerate() {
        let posed = pose_body(&body, &[], &motion.poses[f], motion.translations[f]);
        let col = BodyCollider::new(posed.vertices.clone(), &body.faces);
        let mut line = format!("{f:3}");
        for (gi, pos) in frame.iter().enumerate() {
            let mut over = 0;
            let mut worst = (0.0, 0, 0);
            for &(a, b, rest) in &edges[gi] {
                let s = (pos[a as usize] - pos[b as usize]).length() / rest;
                if s > 1.1 {
                    over += 1;
                }
                if s > worst.0 {
                    worst = (s, a, b);
                }
            }
            let da = col.query(pos[worst.1 as usize]).map(|q| q.0).unwrap_or(9.0);
            let db = col.query(pos[worst.2 as usize]).map(|q| q.0).unwrap_or(9.0);
            let rv = garments[gi].vertices[worst.1 as usize];
            line += &format!(
                " | {} {:.3} over={over} rest=({:.2},{:.2},{:.2}) d=({:.1},{:.1})mm",
                garments[gi].name,
                worst.0,
                rv[0],
                rv[1],
                rv[2],
                da * 1e3,
                db * 1e3
            );
        }
        println!("{line}");
    }
}
