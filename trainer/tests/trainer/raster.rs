//! The CPU mesh rasterizer of the synthetic data.

use drape_trainer::camera::Camera;
use drape_trainer::dataset::raster::{render, Drawable};
use glam::DVec3;

fn camera(w: u32, h: u32) -> Camera {
    Camera {
        fx: 100.0,
        fy: 100.0,
        cx: f64::from(w) / 2.0,
        cy: f64::from(h) / 2.0,
        width: w,
        height: h,
        rotation: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        translation: DVec3::ZERO,
        near: Camera::NEAR,
    }
}

/// A square of side `size` at depth z, facing the camera, UV 0..1.
fn square(size: f64, z: f64) -> (Vec<DVec3>, Vec<[u32; 3]>, Vec<[f64; 2]>) {
    let h = size / 2.0;
    (
        vec![
            DVec3::new(-h, -h, z),
            DVec3::new(h, -h, z),
            DVec3::new(h, h, z),
            DVec3::new(-h, h, z),
        ],
        vec![[0, 2, 1], [0, 3, 2]],
        vec![[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]],
    )
}

#[test]
fn square_covers_its_projected_area_with_depth_and_id() {
    let cam = camera(64, 64);
    let (v, f, uv) = square(1.0, 5.0);
    let white = |_uv: [f64; 2]| [1.0, 1.0, 1.0];
    let d = Drawable {
        vertices: &v,
        faces: &f,
        uvs: &uv,
        object: 3,
        texture: &white,
        two_sided: true,
    };
    let frame = render(&cam, &[d], 4, [0.0; 3], DVec3::NEG_Z, 0.0);
    // 1 m at 5 m with f = 100 px: 20 x 20 pixels, centred.
    let covered: f32 = frame.coverage[3].iter().sum();
    assert!((covered - 400.0).abs() < 1.0, "covered {covered} px");
    let centre = (32 * 64 + 32) as usize;
    assert!((frame.depth[centre] - 5.0).abs() < 1e-6);
    assert!((frame.rgb[3 * centre] - 1.0).abs() < 1e-6, "lit head-on");
    assert_eq!(frame.depth[0], 0.0, "background has no depth");
}

/// Antialiasing: a square whose edges fall a quarter into pixels. 1.025 m at 5 m with
/// f = 100 px is 20.5 px, centred on x = y = 32: edges at 21.75 and 42.25. With 4 x 4
/// samples per pixel (at 1/8, 3/8, 5/8, 7/8) exactly one column (row) of samples of
/// each edge pixel is inside, so each edge pixel is 1/4 covered, each corner 1/16, and
/// the total is 20.5² = 420.25 px exactly (no pixel-aligned edge can pass this).
#[test]
fn edges_inside_pixels_are_partially_covered() {
    let cam = camera(64, 64);
    let (v, f, uv) = square(1.025, 5.0);
    let white = |_uv: [f64; 2]| [1.0, 1.0, 1.0];
    let d = Drawable {
        vertices: &v,
        faces: &f,
        uvs: &uv,
        object: 3,
        texture: &white,
        two_sided: true,
    };
    let frame = render(&cam, &[d], 4, [0.0; 3], DVec3::NEG_Z, 0.0);
    let coverage = &frame.coverage[3];
    let covered: f32 = coverage.iter().sum();
    // f32 sums of 4,096 multiples of 1/16: exact to ~1e-4.
    assert!((covered - 420.25).abs() < 1e-3, "covered {covered} px");
    let at = |x: usize, y: usize| coverage[y * 64 + x];
    assert_eq!(
        (at(21, 32), at(42, 32), at(32, 21), at(32, 42)),
        (0.25, 0.25, 0.25, 0.25),
        "edge pixels"
    );
    assert_eq!((at(21, 21), at(42, 42)), (0.0625, 0.0625), "corner pixels");
    assert_eq!(at(32, 32), 1.0, "interior");
    let partial = coverage.iter().filter(|&&c| c > 0.0 && c < 1.0).count();
    assert_eq!(
        partial,
        4 * 20 + 4,
        "every edge and corner pixel is partial"
    );
    // Grey at the edges: the colour is the mean over the samples.
    assert!((frame.rgb[3 * (32 * 64 + 21)] - 0.25).abs() < 1e-6);
}

#[test]
fn nearer_object_occludes_and_uvs_are_perspective_correct() {
    let cam = camera(64, 64);
    let (back_v, back_f, back_uv) = square(2.0, 6.0);
    let (front_v, front_f, front_uv) = square(0.3, 3.0);
    let red = |_uv: [f64; 2]| [1.0, 0.0, 0.0];
    // A slanted plane: z grows with x, UV u = (x + 1) / 2 along it.
    let slant_v = vec![
        DVec3::new(-1.0, -1.0, 2.0),
        DVec3::new(1.0, -1.0, 6.0),
        DVec3::new(1.0, 1.0, 6.0),
        DVec3::new(-1.0, 1.0, 2.0),
    ];
    let u_texture = |uv: [f64; 2]| [uv[0], 0.0, 0.0];
    let frame = render(
        &cam,
        &[
            Drawable {
                vertices: &back_v,
                faces: &back_f,
                uvs: &back_uv,
                object: 1,
                texture: &red,
                two_sided: true,
            },
            Drawable {
                vertices: &front_v,
                faces: &front_f,
                uvs: &front_uv,
                object: 2,
                texture: &red,
                two_sided: true,
            },
        ],
        1,
        [0.0; 3],
        DVec3::NEG_Z,
        1.0,
    );
    let centre = (32 * 64 + 32) as usize;
    assert_eq!(frame.coverage[2][centre], 1.0, "the nearer square wins");
    assert!((frame.depth[centre] - 3.0).abs() < 1e-6);

    let slant = render(
        &cam,
        &[Drawable {
            vertices: &slant_v,
            faces: &[[0, 2, 1], [0, 3, 2]],
            uvs: &[[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]],
            object: 1,
            texture: &u_texture,
            two_sided: true,
        }],
        1,
        [0.0; 3],
        DVec3::NEG_Z,
        1.0,
    );
    // Pixel column px: the ray x/z = (px + 0.5 - 32) / 100 meets z = 4 + 2x at
    // x = 4a / (1 - 2a); u = (x + 1) / 2. Affine interpolation would be off by ~0.1.
    for px in [20u32, 32, 44] {
        let a = (f64::from(px) + 0.5 - 32.0) / 100.0;
        let x = 4.0 * a / (1.0 - 2.0 * a);
        let u = (x + 1.0) / 2.0;
        let got = f64::from(slant.rgb[3 * (32 * 64 + px as usize)]);
        assert!((got - u).abs() < 1e-3, "column {px}: u {got}, expected {u}");
    }
}

#[test]
fn floor_through_the_near_plane_is_clipped_not_lost() {
    let cam = camera(48, 48);
    // A floor 1 m below the camera from 20 m behind it to 20 m ahead.
    let v = vec![
        DVec3::new(-20.0, 1.0, -20.0),
        DVec3::new(20.0, 1.0, -20.0),
        DVec3::new(20.0, 1.0, 20.0),
        DVec3::new(-20.0, 1.0, 20.0),
    ];
    let grey = |_uv: [f64; 2]| [0.5, 0.5, 0.5];
    let frame = render(
        &cam,
        &[Drawable {
            vertices: &v,
            faces: &[[0, 1, 2], [0, 2, 3]],
            uvs: &[[0.0; 2]; 4],
            object: 1,
            texture: &grey,
            two_sided: true,
        }],
        2,
        [0.0; 3],
        DVec3::NEG_Y,
        0.2,
    );
    assert!(frame.rgb.iter().all(|v| v.is_finite()));
    // The floor's far edge (z = 20, 1 m down) projects to row 24 + 100/20 = 29;
    // every row below it, down to the camera's feet, is floor.
    for y in 30..48 {
        assert_eq!(frame.coverage[1][(y * 48 + 24) as usize], 1.0, "row {y}");
    }
    assert_eq!(
        frame.coverage[1][(10 * 48 + 24) as usize],
        0.0,
        "sky above the horizon"
    );
}
