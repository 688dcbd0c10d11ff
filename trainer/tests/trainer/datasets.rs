//! Dataset formats: COLMAP's text model, NeuMan's SMPL file, ZJU-MoCap's annotations and
//! SMPL parameters (round trips, numpy reading what drape writes, bad values named), and
//! the split protocols.

use std::collections::BTreeMap;
use std::path::PathBuf;

use drape_trainer::dataset::colmap::{ColmapCamera, ColmapImage, ColmapModel, ColmapPoint};
use drape_trainer::dataset::neuman::SmplSequence;
use drape_trainer::dataset::split::{neuman_80_10_10, neuman_every_fifth, zju_by_camera, Split};
use drape_trainer::motion::{procedural, MotionKind};

fn temp(name: &str) -> PathBuf {
    let dir = std::env::temp_dir()
        .join(format!("drape-dataset-tests-{}", std::process::id()))
        .join(name);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

fn model() -> ColmapModel {
    let mut m = ColmapModel::default();
    m.cameras.insert(
        1,
        ColmapCamera {
            id: 1,
            model: "PINHOLE".into(),
            width: 640,
            height: 480,
            params: vec![525.5, 524.25, 319.75, 239.5],
        },
    );
    m.cameras.insert(
        2,
        ColmapCamera {
            id: 2,
            model: "OPENCV".into(),
            width: 512,
            height: 512,
            params: vec![500.0, 501.0, 256.0, 255.5, 0.01, -0.002, 0.0001, 0.0],
        },
    );
    for id in 1..=3u32 {
        let a = 0.1 * f64::from(id);
        m.images.insert(
            id,
            ColmapImage {
                id,
                qvec: [(a / 2.0).cos(), 0.0, (a / 2.0).sin(), 0.0],
                tvec: [0.1 * f64::from(id), -0.25, 3.0 + 1.0 / 3.0],
                camera_id: 1 + id % 2,
                name: format!("{:05}.png", id - 1),
                points2d: vec![(10.5, 20.25, 1), (100.125, 7.0, -1)],
            },
        );
    }
    m.points.insert(
        1,
        ColmapPoint {
            id: 1,
            xyz: [0.1, -0.2, 1.0 / 7.0],
            rgb: [10, 200, 30],
            error: 0.5,
            track: vec![(1, 0), (2, 0), (3, 0)],
        },
    );
    m.points.insert(
        7,
        ColmapPoint {
            id: 7,
            xyz: [1e-8, 2.5e3, -3.0],
            rgb: [0, 0, 255],
            error: 0.0,
            track: vec![],
        },
    );
    m
}

#[test]
fn colmap_text_model_round_trips_exactly() {
    let dir = temp("colmap");
    let m = model();
    m.write_text(&dir).unwrap();
    let back = ColmapModel::read_text(&dir).unwrap();
    assert_eq!(
        back, m,
        "every number, name and track is parsed back identically"
    );
    assert_eq!(
        back.cameras[&2].pinhole(),
        Some((500.0, 501.0, 256.0, 255.5))
    );
}

#[test]
fn colmap_errors_name_file_and_line() {
    let dir = temp("colmap-bad");
    model().write_text(&dir).unwrap();
    let images = dir.join("images.txt");
    let text = std::fs::read_to_string(&images)
        .unwrap()
        .replace(" 1 00001.png", " 9 00001.png");
    drape_io::write(&images, text).unwrap();
    let err = ColmapModel::read_text(&dir).unwrap_err().to_string();
    assert!(
        err.contains("images.txt:") && err.contains("camera 9"),
        "{err}"
    );
    let cams = dir.join("cameras.txt");
    drape_io::write(&cams, "1 PINHOLE 640 abc 1 2 3 4\n").unwrap();
    let err = ColmapModel::read_text(&dir).unwrap_err().to_string();
    assert!(
        err.contains("cameras.txt:1") && err.contains("HEIGHT 'abc'"),
        "{err}"
    );
}

#[test]
fn neuman_smpl_file_round_trips() {
    let motion = procedural(MotionKind::Walk, 20, 30.0, 1.0);
    let seq = SmplSequence {
        poses: motion.poses.clone(),
        betas: vec![vec![0.5, -0.25, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]; 20],
        translations: motion.translations.clone(),
        scales: vec![1.25; 20],
    };
    let path = temp("neuman")
        .join("4d_humans")
        .join("smpl_optimized_aligned_scale.npz");
    seq.write_npz(&path).unwrap();
    assert_eq!(SmplSequence::read_npz(&path).unwrap(), seq);
}

#[test]
fn neuman_smpl_file_with_a_nan_names_the_key() {
    let path = temp("neuman-nan").join("smpl.npz");
    let mut arrays = BTreeMap::new();
    use drape_trainer::npy::Array;
    arrays.insert(
        "global_orient".to_string(),
        Array::f64(vec![2, 3], vec![0.0, f64::NAN, 0.0, 0.0, 0.0, 0.0]),
    );
    arrays.insert(
        "body_pose".to_string(),
        Array::f64(vec![2, 69], vec![0.0; 138]),
    );
    arrays.insert("betas".to_string(), Array::f64(vec![2, 10], vec![0.0; 20]));
    arrays.insert("transl".to_string(), Array::f64(vec![2, 3], vec![0.0; 6]));
    arrays.insert("scale".to_string(), Array::f64(vec![1], vec![1.0]));
    drape_trainer::npy::write_npz(&path, &arrays).unwrap();
    let err = SmplSequence::read_npz(&path).unwrap_err().to_string();
    assert!(
        err.contains("smpl.npz") && err.contains("global_orient") && err.contains("not finite"),
        "{err}"
    );
}

#[test]
fn split_protocols() {
    let s = neuman_every_fifth(12);
    let test: Vec<usize> = s
        .iter()
        .enumerate()
        .filter(|(_, x)| **x == Split::Test)
        .map(|(i, _)| i)
        .collect();
    assert_eq!(test, vec![2, 7]);
    let s = neuman_80_10_10(100);
    assert_eq!(s.iter().filter(|x| **x == Split::Train).count(), 80);
    assert_eq!(s.iter().filter(|x| **x == Split::Val).count(), 10);
    assert_eq!(s[99], Split::Test);
    let s = zju_by_camera(23, 0);
    assert_eq!(s[0], Split::Train);
    assert_eq!(s.iter().filter(|x| **x == Split::Test).count(), 22);
}

mod zju {
    use super::temp;
    use drape_trainer::dataset::zju::{
        mask_path, read_vertices, write_vertices, ZjuAnnots, ZjuCamera, ZjuSmpl,
    };

    fn annots() -> ZjuAnnots {
        let rot = |a: f64| {
            [
                [a.cos(), 0.0, a.sin()],
                [0.0, 1.0, 0.0],
                [-a.sin(), 0.0, a.cos()],
            ]
        };
        ZjuAnnots {
            cameras: (0..3)
                .map(|c| ZjuCamera {
                    k: [[500.0, 0.0, 256.0], [0.0, 500.0, 256.0], [0.0, 0.0, 1.0]],
                    d: [0.0; 5],
                    r: rot(0.5 * f64::from(c)),
                    t: [0.1, -0.2, 3.5 + f64::from(c)],
                })
                .collect(),
            images: (0..4)
                .map(|f| {
                    (0..3)
                        .map(|c| format!("images/Camera_B{}/{f:06}.jpg", c + 1))
                        .collect()
                })
                .collect(),
        }
    }

    #[test]
    fn annots_round_trip_with_t_in_millimetres() {
        let dir = temp("zju");
        let a = annots();
        a.write(&dir).unwrap();
        let back = ZjuAnnots::read(&dir).unwrap();
        assert_eq!(back.images, a.images);
        for (x, y) in back.cameras.iter().zip(&a.cameras) {
            // Metres -> millimetres -> metres: within rounding.
            for k in 0..3 {
                assert!((x.t[k] - y.t[k]).abs() < 1e-12);
            }
            assert_eq!(x.r, y.r);
            assert_eq!(x.k, y.k);
        }
        assert_eq!(mask_path(&a.images[0][1]), "mask/Camera_B2/000000.png");
    }

    #[test]
    fn numpy_reads_annots_smpl_params_and_vertices() {
        let dir = temp("zju-numpy");
        annots().write(&dir).unwrap();
        ZjuSmpl {
            poses: [0.1; 72],
            rh: [0.0, 1.0, 0.0],
            th: [0.0, 0.0, 0.5],
            shapes: [0.0; 10],
        }
        .write(&dir, 0)
        .unwrap();
        write_vertices(&dir, 0, &[[0.0, 1.0, 2.0], [3.0, 4.0, 5.0]]).unwrap();
        let script = format!(
            r#"
import numpy as np
a = np.load({a:?}, allow_pickle=True).item()
assert len(a['cams']['K']) == 3 and a['cams']['T'][2].shape == (3, 1)
assert abs(a['cams']['T'][2][2, 0] - 5500.0) < 1e-9, a['cams']['T'][2]
assert len(a['ims']) == 4 and a['ims'][3]['ims'][2] == 'images/Camera_B3/000003.jpg'
p = np.load({p:?}, allow_pickle=True).item()
assert p['poses'].shape == (1, 72) and p['Rh'].shape == (1, 3) and p['Th'].shape == (1, 3) and p['shapes'].shape == (1, 10)
v = np.load({v:?})
assert v.shape == (2, 3) and v[1, 2] == 5.0
"#,
            a = dir.join("annots.npy").display().to_string(),
            p = dir.join("smpl_params/0.npy").display().to_string(),
            v = dir.join("vertices/0.npy").display().to_string(),
        );
        let out = std::process::Command::new("python3")
            .arg("-c")
            .arg(script)
            .output()
            .expect("python3 runs");
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        assert_eq!(ZjuSmpl::read(&dir, 0).unwrap().th, [0.0, 0.0, 0.5]);
        assert_eq!(read_vertices(&dir, 0).unwrap()[1], [3.0, 4.0, 5.0]);
    }

    #[test]
    fn singular_rotation_and_nan_pose_are_named() {
        let dir = temp("zju-bad");
        let mut a = annots();
        a.cameras[1].r = [[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]];
        a.write(&dir).unwrap();
        let err = ZjuAnnots::read(&dir).unwrap_err().to_string();
        assert!(
            err.contains("annots.npy") && err.contains("cams['R'][1]"),
            "{err}"
        );
        let mut p = ZjuSmpl {
            poses: [0.0; 72],
            rh: [0.0; 3],
            th: [0.0; 3],
            shapes: [0.0; 10],
        };
        p.poses[5] = f64::NAN;
        p.write(&dir, 3).unwrap();
        let err = ZjuSmpl::read(&dir, 3).unwrap_err().to_string();
        assert!(
            err.contains("3.npy") && err.contains("'poses'") && err.contains("not finite"),
            "{err}"
        );
    }
}
