//! The synthetic ground-truth generator (`drape synth`): the default body in the
//! T-shirt and pants, animated by a motion, cloth simulated, textured, in a textured
//! room under fixed lighting, rendered by the CPU rasterizer for a handheld-like
//! moving camera (written in NeuMan's layout) and a ring of static cameras (written in
//! ZJU-MoCap's layout), with person / upper / lower garment masks, depth, and the
//! ground truth: SMPL parameters, posed body vertices and simulated garment meshes.
//!
//! World: y up, the person faces +z and walks along +z; metres.

use std::f64::consts::{PI, TAU};
use std::path::Path;

use glam::DVec3;

use crate::body::kinematics::{pose_body, Pose};
use crate::body::procedural::{default_body, BodyOptions};
use crate::body::SmplModel;
use crate::camera::Camera;
use crate::cloth::{simulate_with_progress, ClothParams};
use crate::dataset::colmap::{ColmapCamera, ColmapImage, ColmapModel, ColmapPoint};
use crate::dataset::image::{write_mask, write_mask_values, write_rgb};
use crate::dataset::neuman::SmplSequence;
use crate::dataset::raster::{render, Drawable};
use crate::dataset::zju::{write_vertices, ZjuAnnots, ZjuCamera, ZjuSmpl};
use crate::error::TrainerError;
use crate::garment::{pants, write_obj, Garment, GarmentFit};
use crate::motion::{procedural, MotionKind};
use crate::npy::{self, Array};

/// What to generate.
#[derive(Clone, Copy, Debug)]
pub struct SynthOptions {
    pub width: u32,
    pub height: u32,
    pub frames: usize,
    /// Cameras of the static ring (ZJU-MoCap layout).
    pub cameras: usize,
    pub motion: MotionKind,
    /// Varies the handheld camera's path and the room's colours.
    pub seed: u64,
    /// Supersampling per axis.
    pub samples: u32,
    /// The T-shirt's fit (the pants are the same for both).
    pub garment: GarmentFit,
}

impl Default for SynthOptions {
    fn default() -> Self {
        Self {
            width: 128,
            height: 128,
            frames: 30,
            cameras: 4,
            motion: MotionKind::Walk,
            seed: 1,
            samples: 2,
            garment: GarmentFit::Tight,
        }
    }
}

/// Object ids in the rasterizer's coverage.
const SCENE: u16 = 1;
const BODY: u16 = 2;
const UPPER: u16 = 3;
const LOWER: u16 = 4;

/// The static room: floor, three walls and two boxes, with UVs in metres.
struct Room {
    vertices: Vec<DVec3>,
    faces: Vec<[u32; 3]>,
    uvs: Vec<[f64; 2]>,
}

fn quad(room: &mut Room, corners: [DVec3; 4], uv_size: [f64; 2]) {
    let b = room.vertices.len() as u32;
    room.vertices.extend(corners);
    room.uvs.extend([
        [0.0, 0.0],
        [uv_size[0], 0.0],
        [uv_size[0], uv_size[1]],
        [0.0, uv_size[1]],
    ]);
    room.faces.extend([[b, b + 1, b + 2], [b, b + 2, b + 3]]);
}

fn room() -> Room {
    let mut r = Room {
        vertices: vec![],
        faces: vec![],
        uvs: vec![],
    };
    // Floor, back wall (z = -4), side walls (x = +-4).
    quad(
        &mut r,
        [
            DVec3::new(-4.0, 0.0, -4.0),
            DVec3::new(4.0, 0.0, -4.0),
            DVec3::new(4.0, 0.0, 9.0),
            DVec3::new(-4.0, 0.0, 9.0),
        ],
        [8.0, 13.0],
    );
    quad(
        &mut r,
        [
            DVec3::new(-4.0, 0.0, -4.0),
            DVec3::new(-4.0, 3.0, -4.0),
            DVec3::new(4.0, 3.0, -4.0),
            DVec3::new(4.0, 0.0, -4.0),
        ],
        [3.0, 8.0],
    );
    quad(
        &mut r,
        [
            DVec3::new(-4.0, 0.0, -4.0),
            DVec3::new(-4.0, 0.0, 9.0),
            DVec3::new(-4.0, 3.0, 9.0),
            DVec3::new(-4.0, 3.0, -4.0),
        ],
        [13.0, 3.0],
    );
    quad(
        &mut r,
        [
            DVec3::new(4.0, 0.0, -4.0),
            DVec3::new(4.0, 3.0, -4.0),
            DVec3::new(4.0, 3.0, 9.0),
            DVec3::new(4.0, 0.0, 9.0),
        ],
        [3.0, 13.0],
    );
    // Two boxes.
    for (c, s) in [
        (DVec3::new(-1.8, 0.4, -2.5), 0.4),
        (DVec3::new(2.0, 0.3, 0.5), 0.3),
    ] {
        let p = |dx: f64, dy: f64, dz: f64| DVec3::new(c.x + dx * s, c.y + dy * s, c.z + dz * s);
        quad(
            &mut r,
            [
                p(-1.0, -1.0, 1.0),
                p(1.0, -1.0, 1.0),
                p(1.0, 1.0, 1.0),
                p(-1.0, 1.0, 1.0),
            ],
            [1.0, 1.0],
        );
        quad(
            &mut r,
            [
                p(1.0, -1.0, -1.0),
                p(-1.0, -1.0, -1.0),
                p(-1.0, 1.0, -1.0),
                p(1.0, 1.0, -1.0),
            ],
            [1.0, 1.0],
        );
        quad(
            &mut r,
            [
                p(-1.0, -1.0, -1.0),
                p(-1.0, -1.0, 1.0),
                p(-1.0, 1.0, 1.0),
                p(-1.0, 1.0, -1.0),
            ],
            [1.0, 1.0],
        );
        quad(
            &mut r,
            [
                p(1.0, -1.0, 1.0),
                p(1.0, -1.0, -1.0),
                p(1.0, 1.0, -1.0),
                p(1.0, 1.0, 1.0),
            ],
            [1.0, 1.0],
        );
        quad(
            &mut r,
            [
                p(-1.0, 1.0, 1.0),
                p(1.0, 1.0, 1.0),
                p(1.0, 1.0, -1.0),
                p(-1.0, 1.0, -1.0),
            ],
            [1.0, 1.0],
        );
    }
    r
}

fn room_texture(uv: [f64; 2]) -> [f64; 3] {
    // Tiles with a darker grout and a soft wood-like grain.
    let (u, v) = (uv[0], uv[1]);
    let tile = ((u * 2.0).floor() + (v * 2.0).floor()).rem_euclid(2.0);
    let grout = (u * 2.0).fract().min((v * 2.0).fract()) < 0.04;
    let grain = 0.05 * (u * 40.0 + 3.0 * (v * 7.0).sin()).sin();
    let base = if tile > 0.5 {
        [0.62, 0.52, 0.40]
    } else {
        [0.48, 0.40, 0.31]
    };
    if grout {
        [0.2, 0.2, 0.22]
    } else {
        base.map(|c| c + grain)
    }
}

/// Cylindrical UVs of the body in its rest pose (u: angle around y, v: height).
fn body_uvs(model: &SmplModel) -> Vec<[f64; 2]> {
    model
        .v_template
        .iter()
        .map(|v| [v[0].atan2(v[2]) / TAU + 0.5, v[1] / 1.8])
        .collect()
}

fn skin_texture(uv: [f64; 2]) -> [f64; 3] {
    let skin = [0.86, 0.66, 0.54];
    let (u, v) = (uv[0] - 0.5, uv[1] * 1.8);
    // The face looks along +z (u = 0): eyes, eyebrows and a mouth.
    if v > 1.5 && u.abs() < 0.12 {
        let eye = ((u.abs() - 0.045).powi(2) + (v - 1.60).powi(2)).sqrt() < 0.012;
        let brow = (u.abs() - 0.045).abs() < 0.022 && (v - 1.625).abs() < 0.004;
        let mouth = u.abs() < 0.035 && (v - 1.535).abs() < 0.005;
        if eye || brow {
            return [0.12, 0.08, 0.06];
        }
        if mouth {
            return [0.65, 0.25, 0.25];
        }
    }
    if v > 1.66 {
        return [0.25, 0.16, 0.1]; // hair
    }
    skin
}

fn shirt_texture(uv: [f64; 2]) -> [f64; 3] {
    // Horizontal stripes every 2.5 cm of height and a thin vertical pinstripe: motion
    // and wrinkles show.
    let stripe = (uv[1] * 1.8 / 0.025).floor().rem_euclid(2.0) < 0.5;
    let pin = (uv[0] * 120.0).fract() < 0.08;
    if pin {
        [0.95, 0.95, 0.9]
    } else if stripe {
        [0.8, 0.15, 0.15]
    } else {
        [0.92, 0.88, 0.8]
    }
}

fn pants_texture(uv: [f64; 2]) -> [f64; 3] {
    let check = ((uv[0] * 80.0).floor() + (uv[1] * 1.8 / 0.02).floor()).rem_euclid(2.0) < 0.5;
    if check {
        [0.12, 0.2, 0.45]
    } else {
        [0.18, 0.28, 0.55]
    }
}

/// The handheld camera of frame i: a slow arc in front of the person with a little
/// shake, looking at the chest.
pub fn handheld_camera(
    i: usize,
    frames: usize,
    centre: DVec3,
    seed: u64,
    width: u32,
    height: u32,
) -> Camera {
    let s = seed as f64;
    let t = i as f64 / frames.max(1) as f64;
    let angle = -0.5 + 0.8 * t + 0.1 * (s * 1.7).sin();
    let shake = DVec3::new(
        0.02 * (2.3 * i as f64 + s).sin(),
        0.015 * (3.1 * i as f64 + 2.0 * s).sin(),
        0.0,
    );
    let eye = centre + DVec3::new(3.2 * angle.sin(), 0.5, 3.2 * angle.cos()) + shake;
    Camera::look_at(eye, centre, DVec3::Y, 1.2 * f64::from(width), width, height)
}

/// Camera c of the static ring around `centre`.
pub fn ring_camera(c: usize, cameras: usize, centre: DVec3, width: u32, height: u32) -> Camera {
    let angle = TAU * c as f64 / cameras.max(1) as f64;
    let eye = centre + DVec3::new(3.6 * angle.sin(), 0.4, 3.6 * angle.cos());
    Camera::look_at(eye, centre, DVec3::Y, 1.2 * f64::from(width), width, height)
}

/// Rotates a vector by an axis-angle.
fn rotate(r: DVec3, v: DVec3) -> DVec3 {
    let m = crate::body::kinematics::rodrigues(r);
    DVec3::from_array(m.map(|row| row[0] * v[0] + row[1] * v[1] + row[2] * v[2]))
}

/// ZJU-MoCap's parameters of a pose: the root rotation moves to `Rh` and the body is
/// posed with a zero root, so that `posed = R(Rh) · SMPL(poses) + Th`; then
/// `Th = translation + J0 - R(Rh) J0` with `J0` the rest pelvis.
pub fn to_zju(pose: &Pose, translation: DVec3, pelvis: DVec3) -> ZjuSmpl {
    let mut poses = [0.0; 72];
    for j in 1..24 {
        poses[3 * j..3 * j + 3].copy_from_slice(&pose[j].to_array());
    }
    let th = translation + (pelvis - rotate(pose[0], pelvis));
    ZjuSmpl {
        poses,
        rh: pose[0].to_array(),
        th: th.to_array(),
        shapes: [0.0; 10],
    }
}

/// Posed vertices from ZJU-MoCap parameters.
pub fn posed_from_zju(model: &SmplModel, p: &ZjuSmpl) -> Vec<DVec3> {
    let mut pose: Pose = [DVec3::ZERO; 24];
    for j in 1..24 {
        pose[j] = DVec3::from_slice(&p.poses[3 * j..3 * j + 3]);
    }
    let (rh, th) = (DVec3::from_array(p.rh), DVec3::from_array(p.th));
    pose_body(model, &p.shapes, &pose, DVec3::ZERO)
        .vertices
        .into_iter()
        .map(|v| rotate(rh, v) + th)
        .collect()
}

/// Vertices as the arrays a vertex file holds.
fn vertex_arrays(vertices: &[DVec3]) -> Vec<[f64; 3]> {
    vertices.iter().map(|v| v.to_array()).collect()
}

/// What was generated.
#[derive(Clone, Debug)]
pub struct SynthSummary {
    pub frames: usize,
    pub ring_cameras: usize,
    pub seconds: f64,
}

fn masks(frame: &crate::dataset::raster::Frame) -> [Vec<bool>; 3] {
    let n = (frame.width * frame.height) as usize;
    let cov = |id: u16, i: usize| frame.coverage.get(id as usize).map_or(0.0, |c| c[i]);
    [
        (0..n)
            .map(|i| cov(BODY, i) + cov(UPPER, i) + cov(LOWER, i) >= 0.5)
            .collect(),
        (0..n).map(|i| cov(UPPER, i) >= 0.5).collect(),
        (0..n).map(|i| cov(LOWER, i) >= 0.5).collect(),
    ]
}

/// Generates the sequence into `out` (`neuman/`, `zju/` and `gt/`); `progress(stage,
/// done, total)` reports as it goes.
pub fn generate(
    out: &Path,
    o: &SynthOptions,
    progress: &mut dyn FnMut(&str, usize, usize),
) -> crate::Result<SynthSummary> {
    let t0 = std::time::Instant::now();
    for (what, value) in [
        ("width", o.width as usize),
        ("height", o.height as usize),
        ("frames", o.frames),
    ] {
        if value == 0 {
            return Err(TrainerError::invalid(what, "must be positive, got 0"));
        }
    }
    let model = default_body(&BodyOptions::default());
    let garments: [Garment; 2] = [o.garment.upper(&model), pants(&model)];
    let motion = procedural(o.motion, o.frames, 30.0, 1.0);
    let sim = simulate_with_progress(
        &model,
        &garments,
        &motion,
        ClothParams::default(),
        20,
        &mut |done, total| progress("simulating cloth", done, total),
    );
    if sim.any_nan {
        return Err(TrainerError::numeric(
            "synth",
            "the cloth simulation produced non-finite positions",
        ));
    }
    let room = room();
    let body_uv = body_uvs(&model);
    let light = DVec3::new(0.3, 1.0, 0.5);
    let background = [0.75, 0.8, 0.85];
    let pelvis = crate::body::kinematics::regress_joints(&model, &model.v_template)[0];
    let neuman = out.join("neuman");
    let zju = out.join("zju");
    let gt = out.join("gt");
    let mean_translation =
        motion.translations.iter().fold(DVec3::ZERO, |a, t| a + *t) * (1.0 / o.frames as f64);
    let ring_centre = mean_translation + DVec3::Y;
    let ring: Vec<Camera> = (0..o.cameras)
        .map(|c| ring_camera(c, o.cameras, ring_centre, o.width, o.height))
        .collect();
    let mut colmap = ColmapModel::default();
    let mut zju_images = Vec::with_capacity(o.frames);

    for f in 0..o.frames {
        progress("rendering", f, o.frames);
        let posed = pose_body(&model, &[], &motion.poses[f], motion.translations[f]);
        let shirt = &sim.frames[f][0];
        let trousers = &sim.frames[f][1];
        let draw = |cam: &Camera| {
            let items = [
                Drawable {
                    vertices: &room.vertices,
                    faces: &room.faces,
                    uvs: &room.uvs,
                    object: SCENE,
                    texture: &room_texture,
                    two_sided: true,
                },
                Drawable {
                    vertices: &posed.vertices,
                    faces: &model.faces,
                    uvs: &body_uv,
                    object: BODY,
                    texture: &skin_texture,
                    two_sided: false,
                },
                Drawable {
                    vertices: shirt,
                    faces: &garments[0].faces,
                    uvs: &garments[0].uvs,
                    object: UPPER,
                    texture: &shirt_texture,
                    two_sided: true,
                },
                Drawable {
                    vertices: trousers,
                    faces: &garments[1].faces,
                    uvs: &garments[1].uvs,
                    object: LOWER,
                    texture: &pants_texture,
                    two_sided: true,
                },
            ];
            render(cam, &items, o.samples, background, light, 0.35)
        };
        // NeuMan: the handheld camera.
        let cam = handheld_camera(
            f,
            o.frames,
            motion.translations[f] + DVec3::Y,
            o.seed,
            o.width,
            o.height,
        );
        let frame = draw(&cam);
        let name = format!("{f:05}.png");
        write_rgb(
            &neuman.join("images").join(&name),
            o.width,
            o.height,
            &frame.rgb,
        )?;
        let [person, upper, lower] = masks(&frame);
        // As released: Detectron2's masks, the person black on white; and HUGS's SAM
        // masks, the person white on black (which the loader then prefers).
        write_mask_values(
            &neuman.join("segmentations").join(&name),
            o.width,
            o.height,
            &person,
            0,
            255,
        )?;
        write_mask(
            &neuman
                .join("4d_humans")
                .join("sam_segmentations")
                .join(&name),
            o.width,
            o.height,
            &person,
        )?;
        write_mask(
            &neuman.join("masks_upper").join(&name),
            o.width,
            o.height,
            &upper,
        )?;
        write_mask(
            &neuman.join("masks_lower").join(&name),
            o.width,
            o.height,
            &lower,
        )?;
        let depth = Array::new(
            npy::Dtype::F32,
            vec![o.height as usize, o.width as usize],
            frame.depth.iter().map(|&d| f64::from(d)).collect(),
        );
        let depth_path = neuman.join("depths").join(format!("{f:05}.npy"));
        let depth_dir = depth_path.parent().expect("has a parent");
        std::fs::create_dir_all(depth_dir).map_err(|e| TrainerError::io(depth_dir, e))?;
        drape_io::write(&depth_path, npy::encode(&depth))
            .map_err(|e| TrainerError::io(&depth_path, e))?;
        // Every handheld frame has the same intrinsics: one COLMAP camera.
        colmap
            .cameras
            .entry(1)
            .or_insert_with(|| ColmapCamera::from_camera(1, &cam));
        colmap.images.insert(
            f as u32 + 1,
            ColmapImage::from_camera(f as u32 + 1, 1, name.clone(), &cam),
        );
        // ZJU-MoCap: the ring.
        let mut paths = Vec::with_capacity(o.cameras);
        for (c, rc) in ring.iter().enumerate() {
            let frame = draw(rc);
            // JPEG like the release (quality `image::ZJU_JPEG_QUALITY`).
            let rel = format!("images/Camera_B{}/{f:06}.jpg", c + 1);
            write_rgb(&zju.join(&rel), o.width, o.height, &frame.rgb)?;
            let [person, _, _] = masks(&frame);
            write_mask(
                &zju.join(crate::dataset::zju::mask_path(&rel)),
                o.width,
                o.height,
                &person,
            )?;
            paths.push(rel);
        }
        zju_images.push(paths);
        to_zju(&motion.poses[f], motion.translations[f], pelvis).write(&zju, f)?;
        write_vertices(&zju, f, &vertex_arrays(&posed.vertices))?;
        // Ground truth.
        write_vertices(&gt, f, &vertex_arrays(&posed.vertices))?;
        for (g, positions) in garments.iter().zip([shirt, trousers]) {
            let path = gt.join("garments").join(format!("{}_{f:04}.obj", g.name));
            let dir = path.parent().expect("has a parent");
            std::fs::create_dir_all(dir).map_err(|e| TrainerError::io(dir, e))?;
            write_obj(&path, positions, &g.faces, Some(&g.uvs))
                .map_err(|e| TrainerError::io(&path, e))?;
        }
    }
    // Sparse points on the room's surfaces (as COLMAP would triangulate them).
    let mut id = 1u64;
    for face in room.faces.iter().step_by(2) {
        let [a, b, c] = face.map(|i| room.vertices[i as usize]);
        let [ua, ub, uc] = face.map(|i| room.uvs[i as usize]);
        for k in 0..40 {
            let (s, t) = (
                (k as f64 * 0.618_034).fract(),
                (k as f64 * 0.414_213 + 0.5).fract(),
            );
            let (s, t) = if s + t > 1.0 {
                (1.0 - s, 1.0 - t)
            } else {
                (s, t)
            };
            let p = a + ((b - a) * s + (c - a) * t);
            let uv = [
                ua[0] + s * (ub[0] - ua[0]) + t * (uc[0] - ua[0]),
                ua[1] + s * (ub[1] - ua[1]) + t * (uc[1] - ua[1]),
            ];
            let rgb = room_texture(uv).map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8);
            colmap.points.insert(
                id,
                ColmapPoint {
                    id,
                    xyz: p.to_array(),
                    rgb,
                    error: 0.0,
                    track: vec![],
                },
            );
            id += 1;
        }
    }
    colmap.write_text(&neuman.join("sparse"))?;
    let seq = SmplSequence {
        poses: motion.poses.clone(),
        betas: vec![vec![0.0; 10]; o.frames],
        translations: motion.translations.clone(),
        scales: vec![1.0; o.frames],
    };
    seq.write_npz(
        &neuman
            .join("4d_humans")
            .join("smpl_optimized_aligned_scale.npz"),
    )?;
    seq.write_npz(&gt.join("smpl.npz"))?;
    let annots = ZjuAnnots {
        cameras: ring.iter().map(ZjuCamera::from_camera).collect(),
        images: zju_images,
    };
    annots.write(&zju)?;
    let _ = PI;
    progress("done", o.frames, o.frames);
    Ok(SynthSummary {
        frames: o.frames,
        ring_cameras: o.cameras,
        seconds: t0.elapsed().as_secs_f64(),
    })
}
