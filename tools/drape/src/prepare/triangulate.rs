//! Triangulating one person's 2D landmarks across calibrated views (the body stage's
//! first half): per frame and landmark, a linear (DLT) solve over the views that saw
//! it, on undistorted normalised coordinates, robust to one bad view, after a per-view
//! time offset estimated from the data.
//!
//! - **Observations.** A view's landmark counts when its visibility is at least
//!   [`Options::min_visibility`] (mediapipe's usual 0.5); its row in the DLT is weighted
//!   by the visibility. Pixels follow drape's convention (centres at +0.5), which is
//!   mediapipe's `x * width`.
//! - **Solve.** Each observation's pixel is undistorted to normalised camera
//!   coordinates `(x, y)` (`Distortion::undistort_normalized`); each gives two rows
//!   `w (x r3 - r1) X = w (t1 - x t3)`, `w (y r3 - r2) X = w (t2 - y t3)` (`r_i` the
//!   rows of R), solved by least squares (3x3 normal equations; the point is never at
//!   infinity). A point not in front of every camera it used is dropped.
//! - **Robust to one bad view** (a left/right swap, a view out of sync): with three
//!   or more views, unless every view's reprojection error is within
//!   [`Options::reject_floor`] of its image height, each view is left out in turn and
//!   the point solved from the rest; the view whose leaving out makes the rest agree
//!   best (smallest median error) is dropped when its error against that point is over
//!   [`Options::reject_ratio`] times that median *and* over the floor. At most one view
//!   a point is dropped. (Dropping the view with the largest error against the all-view
//!   point fails: a view 100 px off pulls that point until the others' errors are a
//!   third of its own.)
//! - **Time offsets.** Unsynchronised videos (Pose2Sim's demo: cam03 about 3 frames off)
//!   make a moving limb disagree across views. Each view but the first gets an offset
//!   `d` in frames (landmarks read at `f + d`, linear between the two frames around it),
//!   chosen from `-max..max` in half frames to minimise the median reprojection error of
//!   all observations; the views are searched one at a time, twice over.
//!
//! NaN policy: a landmark no view solved is NaN in every coordinate; every test on an
//! error or a weight is written so that NaN fails it.

use drape_trainer::camera::Camera;
use drape_trainer::dataset::distortion::{self, Distortion};
use glam::{DMat3, DVec3};

/// mediapipe's pose landmarks.
pub const LANDMARKS: usize = 33;

/// One calibrated view.
#[derive(Clone, Debug)]
pub struct View {
    pub name: String,
    pub camera: Camera,
    pub distortion: Distortion,
}

/// One view's landmarks: `[frame][landmark] = (x_px, y_px, visibility)`, NaN where not
/// detected.
pub type Track = Vec<[[f64; 3]; LANDMARKS]>;

/// How observations are used and rejected (the module header).
#[derive(Clone, Copy, Debug)]
pub struct Options {
    pub min_visibility: f64,
    pub reject_ratio: f64,
    /// A fraction of the image height.
    pub reject_floor: f64,
    /// The time offsets searched, +-frames (0: none).
    pub max_offset: f64,
}

impl Default for Options {
    fn default() -> Self {
        Self {
            min_visibility: 0.5,
            reject_ratio: 2.5,
            reject_floor: 0.01,
            max_offset: 6.0,
        }
    }
}

/// One landmark solved in one frame.
#[derive(Clone, Copy, Debug)]
pub struct Solved {
    pub point: DVec3,
    /// Views whose observation the point was solved from (bit per view).
    pub used: u32,
    /// Views that saw it but were rejected.
    pub rejected: u32,
}

/// The triangulation of a sequence.
#[derive(Clone, Debug)]
pub struct Triangulation {
    /// `[frame][landmark]`.
    pub points: Vec<[Option<Solved>; LANDMARKS]>,
    /// Per view, in frames.
    pub offsets: Vec<f64>,
}

/// An observation: view index, pixel, weight.
type Obs = (usize, [f64; 2], f64);

/// The landmark at a fractional frame, linear between its two frames; None unless both
/// are observed at `min_visibility` or more.
fn sample(track: &Track, frame: f64, landmark: usize, min_visibility: f64) -> Option<[f64; 3]> {
    let f0 = frame.floor();
    if !(f0 >= 0.0) {
        return None;
    }
    let i0 = f0 as usize;
    let a = track.get(i0)?[landmark];
    let s = frame - f0;
    let b = if s > 0.0 {
        track.get(i0 + 1)?[landmark]
    } else {
        a
    };
    if !(a[2] >= min_visibility && b[2] >= min_visibility) {
        return None;
    }
    Some([
        a[0] + s * (b[0] - a[0]),
        a[1] + s * (b[1] - a[1]),
        a[2].min(b[2]),
    ])
}

/// The least-squares DLT point of `obs` (undistorted normalised coordinates), None when
/// degenerate or behind a camera.
fn dlt(views: &[View], obs: &[Obs]) -> Option<DVec3> {
    if obs.len() < 2 {
        return None;
    }
    let mut ata = DMat3::ZERO;
    let mut atb = DVec3::ZERO;
    for &(v, px, w) in obs {
        let c = &views[v].camera;
        let [x, y] = views[v]
            .distortion
            .undistort_normalized((px[0] - c.cx) / c.fx, (px[1] - c.cy) / c.fy);
        if !(x.is_finite() && y.is_finite()) {
            continue;
        }
        let r = c.rotation.map(DVec3::from_array);
        let t = c.translation;
        for (row, rhs) in [
            (r[2] * x - r[0], t[0] - x * t[2]),
            (r[2] * y - r[1], t[1] - y * t[2]),
        ] {
            let (row, rhs) = (row * w, rhs * w);
            ata += DMat3::from_cols(row * row.x, row * row.y, row * row.z);
            atb += row * rhs;
        }
    }
    let det = ata.determinant();
    if !(det.abs() > 1e-18) {
        return None;
    }
    let p = ata.inverse() * atb;
    let in_front = obs
        .iter()
        .all(|&(v, _, _)| views[v].camera.to_camera(p).z > views[v].camera.near);
    (p.is_finite() && in_front).then_some(p)
}

/// Reprojection error of `p` in pixels against an observation.
pub fn reprojection_error(view: &View, p: DVec3, px: [f64; 2]) -> f64 {
    let q = distortion::project(&view.camera, &view.distortion, p);
    (q[0] - px[0]).hypot(q[1] - px[1])
}

fn median(values: &mut [f64]) -> f64 {
    if values.is_empty() {
        return f64::NAN;
    }
    values.sort_by(f64::total_cmp);
    let n = values.len();
    if n % 2 == 1 {
        values[n / 2]
    } else {
        0.5 * (values[n / 2 - 1] + values[n / 2])
    }
}

/// One point from its observations, with the one-bad-view rule (module header).
pub fn solve_point(views: &[View], obs: &[Obs], options: &Options) -> Option<Solved> {
    let p = dlt(views, obs)?;
    let all: u32 = obs.iter().map(|o| 1 << o.0).sum();
    let error = |i: usize, q: DVec3| reprojection_error(&views[obs[i].0], q, obs[i].1);
    let floor = |i: usize| options.reject_floor * f64::from(views[obs[i].0].camera.height);
    let agree = (0..obs.len()).all(|i| error(i, p) <= floor(i));
    if obs.len() >= 3 && !agree {
        // Leave each view out in turn; the candidate is the one whose leaving out makes
        // the others agree best (the smallest median error of the rest).
        let mut best: Option<(f64, usize, DVec3)> = None;
        for out in 0..obs.len() {
            let kept: Vec<Obs> = (0..obs.len())
                .filter(|&i| i != out)
                .map(|i| obs[i])
                .collect();
            let Some(q) = dlt(views, &kept) else { continue };
            let m = median(
                (0..obs.len())
                    .filter(|&i| i != out)
                    .map(|i| error(i, q))
                    .collect::<Vec<_>>()
                    .as_mut_slice(),
            );
            if best.is_none_or(|b| m < b.0) {
                best = Some((m, out, q));
            }
        }
        if let Some((m, out, q)) = best {
            let e = error(out, q);
            if e > options.reject_ratio * m && e > floor(out) {
                return Some(Solved {
                    point: q,
                    used: all & !(1 << obs[out].0),
                    rejected: 1 << obs[out].0,
                });
            }
        }
    }
    Some(Solved {
        point: p,
        used: all,
        rejected: 0,
    })
}

/// The observations of `landmark` in reference frame `frame`, views read at their
/// offsets.
fn observations(
    tracks: &[Track],
    offsets: &[f64],
    frame: usize,
    landmark: usize,
    min_visibility: f64,
) -> Vec<Obs> {
    tracks
        .iter()
        .zip(offsets)
        .enumerate()
        .filter_map(|(v, (track, d))| {
            sample(track, frame as f64 + d, landmark, min_visibility)
                .map(|s| (v, [s[0], s[1]], s[2]))
        })
        .collect()
}

/// Every frame and landmark at the given offsets.
fn solve_all(
    views: &[View],
    tracks: &[Track],
    offsets: &[f64],
    options: &Options,
) -> Vec<[Option<Solved>; LANDMARKS]> {
    let frames = tracks.first().map_or(0, Vec::len);
    (0..frames)
        .map(|f| {
            std::array::from_fn(|l| {
                let obs = observations(tracks, offsets, f, l, options.min_visibility);
                solve_point(views, &obs, options)
            })
        })
        .collect()
}

/// Per view, the reprojection errors (pixels) of the solved points against that view's
/// observations at its offset: `(inliers, all)` (all includes rejected views).
pub fn view_errors(
    views: &[View],
    tracks: &[Track],
    t: &Triangulation,
    options: &Options,
) -> Vec<(Vec<f64>, Vec<f64>)> {
    let mut out = vec![(Vec::new(), Vec::new()); views.len()];
    for (f, row) in t.points.iter().enumerate() {
        for (l, s) in row.iter().enumerate() {
            let Some(s) = s else { continue };
            for (v, (track, d)) in tracks.iter().zip(&t.offsets).enumerate() {
                let Some(o) = sample(track, f as f64 + d, l, options.min_visibility) else {
                    continue;
                };
                let e = reprojection_error(&views[v], s.point, [o[0], o[1]]);
                if s.used & (1 << v) != 0 {
                    out[v].0.push(e);
                }
                out[v].1.push(e);
            }
        }
    }
    out
}

/// The median reprojection error over all observations, each relative to its image
/// height (what the offset search minimises).
fn score(views: &[View], tracks: &[Track], offsets: &[f64], options: &Options) -> f64 {
    let t = Triangulation {
        points: solve_all(views, tracks, offsets, options),
        offsets: offsets.to_vec(),
    };
    let mut all: Vec<f64> = view_errors(views, tracks, &t, options)
        .into_iter()
        .zip(views)
        .flat_map(|((_, a), v)| {
            let h = f64::from(v.camera.height);
            a.into_iter().map(move |e| e / h)
        })
        .collect();
    median(&mut all)
}

/// Triangulates a sequence (module header). `tracks[v]` is view `v`'s landmarks; all
/// tracks have the first one's frames (shorter ones count as undetected at the end).
pub fn triangulate(views: &[View], tracks: &[Track], options: &Options) -> Triangulation {
    let mut offsets = vec![0.0; views.len()];
    if options.max_offset > 0.0 && views.len() >= 3 {
        let steps = (options.max_offset * 2.0).round() as i64;
        for _sweep in 0..2 {
            for v in 1..views.len() {
                let mut best = (score(views, tracks, &offsets, options), offsets[v]);
                for k in -steps..=steps {
                    let d = k as f64 * 0.5;
                    if d == best.1 {
                        continue;
                    }
                    let mut trial = offsets.clone();
                    trial[v] = d;
                    let s = score(views, tracks, &trial, options);
                    if s < best.0 {
                        best = (s, d);
                    }
                }
                offsets[v] = best.1;
            }
        }
    }
    Triangulation {
        points: solve_all(views, tracks, &offsets, options),
        offsets,
    }
}

/// The median of `values` (NaN when empty).
pub fn median_of(mut values: Vec<f64>) -> f64 {
    median(&mut values)
}

#[cfg(test)]
/// Four cameras 3-4 m around a 2 m-tall volume, z up, with a lens like Pose2Sim's
/// demo's (k1 = -0.05 here, stronger, so that skipping the undistortion shows).
pub fn test_rig() -> Vec<View> {
    let eyes = [
        DVec3::new(1.5, -2.0, 1.9),
        DVec3::new(2.6, 0.7, 1.7),
        DVec3::new(-3.2, 2.2, 2.1),
        DVec3::new(-3.8, -1.4, 1.9),
    ];
    eyes.iter()
        .enumerate()
        .map(|(i, &e)| View {
            name: format!("cam{i}"),
            camera: Camera::look_at(e, DVec3::new(0.0, 0.0, 1.0), DVec3::Z, 1600.0, 1080, 1920),
            distortion: Distortion {
                k1: -0.05,
                k2: 0.01,
                ..Distortion::NONE
            },
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng as _, SeedableRng as _};

    fn rig() -> Vec<View> {
        test_rig()
    }

    /// Known points, their projections with Gaussian noise of `sigma` px, and view 2
    /// corrupted in every frame for landmarks 0..10 (a swap-sized error, 60-120 px).
    fn synthetic(sigma: f64) -> (Vec<View>, Vec<Track>, Vec<Vec<DVec3>>) {
        let views = rig();
        let mut rng = rand::rngs::StdRng::seed_from_u64(55);
        let frames = 12;
        let truth: Vec<Vec<DVec3>> = (0..frames)
            .map(|_| {
                (0..LANDMARKS)
                    .map(|_| {
                        DVec3::new(
                            rng.random_range(-0.4..0.4),
                            rng.random_range(-0.4..0.4),
                            rng.random_range(0.1..1.9),
                        )
                    })
                    .collect()
            })
            .collect();
        let tracks = views
            .iter()
            .enumerate()
            .map(|(v, view)| {
                truth
                    .iter()
                    .map(|pts| {
                        std::array::from_fn(|l| {
                            let [x, y] =
                                distortion::project(&view.camera, &view.distortion, pts[l]);
                            let mut n = [0.0; 2];
                            for k in &mut n {
                                // Box-Muller.
                                let (a, b): (f64, f64) =
                                    (rng.random_range(1e-12..1.0), rng.random());
                                *k = sigma
                                    * (-2.0 * a.ln()).sqrt()
                                    * (std::f64::consts::TAU * b).cos();
                            }
                            if v == 2 && l < 10 {
                                let angle = l as f64;
                                let r = 60.0 + 6.0 * l as f64;
                                n[0] += r * angle.cos();
                                n[1] += r * angle.sin();
                            }
                            [x + n[0], y + n[1], 0.9]
                        })
                    })
                    .collect()
            })
            .collect();
        (views, tracks, truth)
    }

    /// The largest 3D error over all points: the tolerance is 2 cm, about 10 times the
    /// error 1 px of noise gives at 3-4 m with f = 1600 px (1 px = 2.2 mm); with the
    /// view rejection disabled the corrupted view pulls points by up to 13 cm (seen).
    #[test]
    fn recovers_points_despite_one_corrupted_view() {
        let (views, tracks, truth) = synthetic(1.0);
        let options = Options {
            max_offset: 0.0,
            ..Options::default()
        };
        let t = triangulate(&views, &tracks, &options);
        let mut worst: f64 = 0.0;
        let mut rejected_in_2 = 0;
        for (row, pts) in t.points.iter().zip(&truth) {
            for (l, s) in row.iter().enumerate() {
                let s = s.expect("every point is seen by four views");
                worst = worst.max((s.point - pts[l]).length());
                if s.rejected == 1 << 2 {
                    rejected_in_2 += 1;
                }
            }
        }
        assert!(worst < 0.02, "largest 3D error {worst} m");
        // The corrupted observations (12 frames x 10 landmarks) are the ones rejected.
        assert_eq!(rejected_in_2, 120);
    }

    /// A view shifted in time by 3 frames is found at +3 (points moving smoothly).
    #[test]
    fn finds_a_views_time_offset() {
        let views = rig();
        let frames = 30;
        let point = |f: f64, l: usize| {
            let a = 0.25 * f + l as f64;
            DVec3::new(0.4 * a.cos(), 0.4 * a.sin(), 0.2 + 0.05 * l as f64)
        };
        let tracks: Vec<Track> = views
            .iter()
            .enumerate()
            .map(|(v, view)| {
                (0..frames)
                    .map(|f| {
                        // View 2's frame f shows the scene at f - 3.
                        let time = if v == 2 { f as f64 - 3.0 } else { f as f64 };
                        std::array::from_fn(|l| {
                            let [x, y] =
                                distortion::project(&view.camera, &view.distortion, point(time, l));
                            [x, y, 1.0]
                        })
                    })
                    .collect()
            })
            .collect();
        let t = triangulate(&views, &tracks, &Options::default());
        assert_eq!(t.offsets, vec![0.0, 0.0, 3.0, 0.0]);
    }
}
