//! NumPy object arrays (pickles): what the project writes, NumPy reads; what NumPy
//! writes, the project reads. The test command installs numpy for Python 3.

use std::path::PathBuf;
use std::process::Command;

use drape_trainer::npy::Array;
use drape_trainer::pickle::{decode_object_npy, encode_object_npy, PyValue};

fn temp(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("drape-pickle-tests-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

fn annots() -> PyValue {
    let k = Array::f64(vec![3, 3], vec![500.0, 0.0, 256.0, 0.0, 501.0, 255.5, 0.0, 0.0, 1.0]);
    let d = Array::f64(vec![5, 1], vec![0.0; 5]);
    let r = Array::f64(vec![3, 3], vec![1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]);
    let t = Array::f64(vec![3, 1], vec![10.0, -20.5, 3000.0]);
    PyValue::dict(vec![
        ("cams", PyValue::dict(vec![
            ("K", PyValue::List(vec![PyValue::Array(k.clone()), PyValue::Array(k)])),
            ("D", PyValue::List(vec![PyValue::Array(d.clone()), PyValue::Array(d)])),
            ("R", PyValue::List(vec![PyValue::Array(r.clone()), PyValue::Array(r)])),
            ("T", PyValue::List(vec![PyValue::Array(t.clone()), PyValue::Array(t)])),
        ])),
        ("ims", PyValue::List((0..3).map(|f| PyValue::dict(vec![("ims", PyValue::List(vec![
            PyValue::Str(format!("Camera_B1/{f:06}.jpg")),
            PyValue::Str(format!("Camera_B2/{f:06}.jpg")),
        ]))])).collect())),
    ])
}

#[test]
fn object_npy_round_trips_in_rust() {
    let v = annots();
    let bytes = encode_object_npy(&v);
    assert_eq!(decode_object_npy(&bytes, "annots.npy").unwrap(), v);
}

fn python(script: &str) -> std::process::Output {
    Command::new("python3").arg("-c").arg(script).output().expect("python3 runs")
}

#[test]
fn numpy_reads_what_we_write_and_we_read_what_numpy_writes() {
    let ours = temp("annots.npy");
    std::fs::write(&ours, encode_object_npy(&annots())).unwrap();
    let theirs = temp("annots_numpy.npy");
    let script = format!(
        r#"
import numpy as np
a = np.load({ours:?}, allow_pickle=True).item()
assert set(a) == {{'cams', 'ims'}}, a.keys()
assert a['cams']['K'][1].shape == (3, 3) and a['cams']['K'][0][1, 2] == 255.5
assert a['cams']['T'][0].shape == (3, 1) and a['cams']['T'][0][2, 0] == 3000.0
assert a['ims'][2]['ims'][1] == 'Camera_B2/000002.jpg'
b = {{'cams': {{'K': [np.arange(9.0).reshape(3, 3)], 'T': [np.ones((3, 1), dtype=np.float32)]}}, 'ims': [{{'ims': ['x.jpg']}}], 'n': 7, 'f': 0.25}}
np.save({theirs:?}, b)
"#
    );
    let out = python(&script);
    assert!(out.status.success(), "numpy could not read our annots.npy: {}", String::from_utf8_lossy(&out.stderr));
    let v = decode_object_npy(&std::fs::read(&theirs).unwrap(), "annots_numpy.npy").expect("we read numpy's pickle");
    let k = v.get("cams").and_then(|c| c.get("K")).and_then(|k| k.as_list()).and_then(|l| l[0].as_array()).expect("K");
    assert_eq!(k.shape, vec![3, 3]);
    assert_eq!(k.data[5], 5.0);
    let t = v.get("cams").and_then(|c| c.get("T")).and_then(|k| k.as_list()).and_then(|l| l[0].as_array()).expect("T");
    assert_eq!(t.shape, vec![3, 1]);
    assert_eq!(v.get("n"), Some(&PyValue::Int(7)));
    assert_eq!(v.get("f"), Some(&PyValue::Float(0.25)));
}
