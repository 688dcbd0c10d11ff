//! NumPy object arrays (pickles): what the project writes, NumPy reads; what NumPy
//! writes, the project reads. The test command installs numpy for Python 3. ZJU-MoCap
//! annotations written by numpy itself (`tests/python/write_annots.py`, run by numpy
//! 2.x, the reference environment's, and by numpy 1.x, `scripts/clients-env.sh`'s;
//! np.save and pickle protocols 2 to 5) load through the ZJU
//! loader with the values numpy wrote; hostile pickles are refused without a panic.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;

use drape_tests::reference_python::{case_dir, clients_python, get, run, run_with};
use drape_trainer::dataset::zju::{ZjuAnnots, ZjuSmpl};
use drape_trainer::npy::Array;
use drape_trainer::pickle::{decode, decode_object_npy, encode_object_npy, PickleProblem, PyValue};

fn temp(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("drape-pickle-tests-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

fn annots() -> PyValue {
    let k = Array::f64(
        vec![3, 3],
        vec![500.0, 0.0, 256.0, 0.0, 501.0, 255.5, 0.0, 0.0, 1.0],
    );
    let d = Array::f64(vec![5, 1], vec![0.0; 5]);
    let r = Array::f64(
        vec![3, 3],
        vec![1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
    );
    let t = Array::f64(vec![3, 1], vec![10.0, -20.5, 3000.0]);
    PyValue::dict(vec![
        (
            "cams",
            PyValue::dict(vec![
                (
                    "K",
                    PyValue::List(vec![PyValue::Array(k.clone()), PyValue::Array(k)]),
                ),
                (
                    "D",
                    PyValue::List(vec![PyValue::Array(d.clone()), PyValue::Array(d)]),
                ),
                (
                    "R",
                    PyValue::List(vec![PyValue::Array(r.clone()), PyValue::Array(r)]),
                ),
                (
                    "T",
                    PyValue::List(vec![PyValue::Array(t.clone()), PyValue::Array(t)]),
                ),
            ]),
        ),
        (
            "ims",
            PyValue::List(
                (0..3)
                    .map(|f| {
                        PyValue::dict(vec![(
                            "ims",
                            PyValue::List(vec![
                                PyValue::Str(format!("Camera_B1/{f:06}.jpg")),
                                PyValue::Str(format!("Camera_B2/{f:06}.jpg")),
                            ]),
                        )])
                    })
                    .collect(),
            ),
        ),
    ])
}

#[test]
fn object_npy_round_trips_in_rust() {
    let v = annots();
    let bytes = encode_object_npy(&v);
    assert_eq!(decode_object_npy(&bytes, "annots.npy").unwrap(), v);
}

fn python(script: &str) -> std::process::Output {
    Command::new("python3")
        .arg("-c")
        .arg(script)
        .output()
        .expect("python3 runs")
}

#[test]
fn numpy_reads_what_we_write_and_we_read_what_numpy_writes() {
    let ours = temp("annots.npy");
    drape_io::write(&ours, encode_object_npy(&annots())).unwrap();
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
    assert!(
        out.status.success(),
        "numpy could not read our annots.npy: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v = decode_object_npy(&std::fs::read(&theirs).unwrap(), "annots_numpy.npy")
        .expect("we read numpy's pickle");
    let k = v
        .get("cams")
        .and_then(|c| c.get("K"))
        .and_then(|k| k.as_list())
        .and_then(|l| l[0].as_array())
        .expect("K");
    assert_eq!(k.shape, vec![3, 3]);
    assert_eq!(k.data[5], 5.0);
    let t = v
        .get("cams")
        .and_then(|c| c.get("T"))
        .and_then(|k| k.as_list())
        .and_then(|l| l[0].as_array())
        .expect("T");
    assert_eq!(t.shape, vec![3, 1]);
    assert_eq!(v.get("n"), Some(&PyValue::Int(7)));
    assert_eq!(v.get("f"), Some(&PyValue::Float(0.25)));
}

// ---- what numpy writes (tests/python/write_annots.py) ----

/// The files, written once per test binary by numpy 2.x (the reference environment) and
/// by numpy 1.x (`scripts/clients-env.sh`): (which numpy, its directory).
fn numpy_files() -> &'static [(String, PathBuf)] {
    static DIRS: OnceLock<Vec<(String, PathBuf)>> = OnceLock::new();
    DIRS.get_or_init(|| {
        let two = case_dir("pickle", "numpy_annots");
        run("write_annots.py", std::slice::from_ref(&two));
        let one = case_dir("pickle", "numpy1_annots");
        run_with(
            &clients_python(),
            "write_annots.py",
            std::slice::from_ref(&one),
        );
        let version = |py: &Path| {
            String::from_utf8_lossy(
                &Command::new(py)
                    .args(["-c", "import numpy; print(numpy.__version__)"])
                    .output()
                    .expect("python runs")
                    .stdout,
            )
            .trim()
            .to_string()
        };
        let (v2, v1) = (
            version(&drape_tests::reference_python::python()),
            version(&clients_python()),
        );
        assert!(
            v2.starts_with("2.") && v1.starts_with("1."),
            "numpy {v2} and {v1}: one 2.x and one 1.x expected"
        );
        vec![(format!("numpy {v2}"), two), (format!("numpy {v1}"), one)]
    })
}

/// The cases a script wrote, with their directories: `<numpy> <dtype>_<how>`, dtype
/// f64/f32/mixed, how save/p2..p5.
fn numpy_cases() -> Vec<(String, PathBuf)> {
    let mut out = Vec::new();
    for (numpy, dir) in numpy_files() {
        let text = std::fs::read_to_string(dir.join("cases.txt")).expect("cases.txt");
        let cases: Vec<&str> = text.lines().filter(|l| !l.is_empty()).collect();
        assert_eq!(
            cases.len(),
            15,
            "{numpy}: three dtypes by five ways of saving: {cases:?}"
        );
        out.extend(
            cases
                .into_iter()
                .map(|c| (format!("{numpy} {c}"), dir.join(c))),
        );
    }
    out
}

/// Compares `got` with `expected` exactly, noting the first difference in `failures`.
fn compare(failures: &mut Vec<String>, what: String, got: &[f64], expected: &[f64]) {
    if got.len() != expected.len() {
        failures.push(format!(
            "{what}: {} values, expected {}",
            got.len(),
            expected.len()
        ));
    } else if let Some(i) = (0..got.len()).find(|&i| got[i].to_bits() != expected[i].to_bits()) {
        failures.push(format!("{what}[{i}]: {} != {}", got[i], expected[i]));
    }
}

#[test]
fn numpy_written_annots_load_with_the_values_numpy_wrote() {
    let mut failures = Vec::new();
    for (case, dir) in numpy_cases() {
        let expected = dir.join("expected");
        let annots = match ZjuAnnots::read(&dir) {
            Ok(a) => a,
            Err(e) => {
                failures.push(format!("{case}: {e}"));
                continue;
            }
        };
        let cams = &annots.cameras;
        // Stacked per camera, as stored: T in millimetres, which the loader divides by 1000.
        let t_mm = get(&expected, "T");
        let t: Vec<f64> = t_mm.iter().map(|v| v / 1000.0).collect();
        compare(
            &mut failures,
            format!("{case} K"),
            &cams
                .iter()
                .flat_map(|c| c.k.iter().flatten().copied())
                .collect::<Vec<_>>(),
            &get(&expected, "K"),
        );
        compare(
            &mut failures,
            format!("{case} D"),
            &cams.iter().flat_map(|c| c.d).collect::<Vec<_>>(),
            &get(&expected, "D"),
        );
        compare(
            &mut failures,
            format!("{case} R"),
            &cams
                .iter()
                .flat_map(|c| c.r.iter().flatten().copied())
                .collect::<Vec<_>>(),
            &get(&expected, "R"),
        );
        compare(
            &mut failures,
            format!("{case} T"),
            &cams.iter().flat_map(|c| c.t).collect::<Vec<_>>(),
            &t,
        );
        let ims: Vec<Vec<String>> = std::fs::read_to_string(expected.join("ims.txt"))
            .expect("ims.txt")
            .lines()
            .map(|l| l.split('\t').map(str::to_string).collect())
            .collect();
        if annots.images != ims {
            failures.push(format!("{case} ims: {:?}, expected {ims:?}", annots.images));
        }
    }
    assert!(
        failures.is_empty(),
        "{} problems:\n{}",
        failures.len(),
        failures.join("\n")
    );
}

#[test]
fn numpy_written_smpl_params_load_with_the_values_numpy_wrote() {
    let mut failures = Vec::new();
    for (case, dir) in numpy_cases() {
        let expected = dir.join("expected");
        for frame in 0..2 {
            let p = match ZjuSmpl::read(&dir, frame) {
                Ok(p) => p,
                Err(e) => {
                    failures.push(format!("{case} frame {frame}: {e}"));
                    continue;
                }
            };
            compare(
                &mut failures,
                format!("{case} {frame} poses"),
                &p.poses,
                &get(&expected, &format!("smpl{frame}_poses")),
            );
            compare(
                &mut failures,
                format!("{case} {frame} Rh"),
                &p.rh,
                &get(&expected, &format!("smpl{frame}_Rh")),
            );
            compare(
                &mut failures,
                format!("{case} {frame} Th"),
                &p.th,
                &get(&expected, &format!("smpl{frame}_Th")),
            );
            compare(
                &mut failures,
                format!("{case} {frame} shapes"),
                &p.shapes,
                &get(&expected, &format!("smpl{frame}_shapes")),
            );
        }
    }
    assert!(
        failures.is_empty(),
        "{} problems:\n{}",
        failures.len(),
        failures.join("\n")
    );
}

// ---- Python's semantics and hostile input, on hand-made pickles ----

#[test]
fn memo_entries_are_references() {
    // pickle.loads gives ([1], [1]): an empty list, memoised, put in a tuple twice, then
    // fetched by BINGET and appended to; the tuple holds that same list.
    let bytes = b"\x80\x02(]q\x00h\x00th\x00K\x01a0.";
    let one = PyValue::List(vec![PyValue::Int(1)]);
    assert_eq!(
        decode(bytes, "memo").unwrap(),
        PyValue::Tuple(vec![one.clone(), one])
    );
}

/// Every truncation of `bytes` and every byte of it replaced by a few values: the reader
/// returns (an error or a value), it does not panic.
fn mutations_do_not_panic(name: &str, bytes: &[u8]) {
    for n in 0..bytes.len() {
        assert!(
            decode_object_npy(&bytes[..n], name).is_err(),
            "{name} cut to {n} bytes"
        );
    }
    let mut copy = bytes.to_vec();
    for i in 0..bytes.len() {
        for v in [0x00, 0xff, 0x80, bytes[i] ^ 0x01] {
            copy[i] = v;
            let _ = decode_object_npy(&copy, name);
        }
        copy[i] = bytes[i];
    }
}

#[test]
fn numpy_files_cut_or_altered_are_refused_without_panicking() {
    for (_, dir) in numpy_files() {
        for case in ["f64_save", "mixed_p2", "f32_p5"] {
            let bytes = std::fs::read(dir.join(case).join("annots.npy")).expect("annots.npy");
            mutations_do_not_panic(case, &bytes);
        }
    }
    let ours = encode_object_npy(&annots());
    mutations_do_not_panic("ours", &ours);
}

fn problem(bytes: &[u8]) -> PickleProblem {
    decode(bytes, "hostile").expect_err("refused").problem
}

#[test]
fn hostile_pickles_are_refused_with_what_is_wrong() {
    // Lengths past the end, including ones whose sum with the offset overflows.
    for op in [0x8du8, 0x8e, 0x96] {
        let mut b = vec![0x80, 5, op];
        b.extend_from_slice(&u64::MAX.to_le_bytes());
        assert!(
            matches!(problem(&b), PickleProblem::Truncated),
            "opcode 0x{op:02x}"
        );
    }
    assert!(matches!(
        problem(b"\x80\x02X\xff\xff\xff\xffab"),
        PickleProblem::Truncated
    ));
    // Lists nested 100 000 deep, and a list that holds itself.
    let mut deep = vec![0x80, 2];
    deep.extend(std::iter::repeat_n(b']', 100_000));
    deep.extend(std::iter::repeat_n(b'a', 99_999));
    deep.push(b'.');
    assert!(
        matches!(problem(&deep), PickleProblem::TooDeep { .. }),
        "{:?}",
        problem(&deep)
    );
    assert!(matches!(
        problem(b"\x80\x02]q\x00h\x00a."),
        PickleProblem::TooDeep { .. }
    ));
    // Each step makes a list of two references to the previous one: 2^40 leaves.
    let mut wide = b"\x80\x02]q\x00".to_vec();
    for _ in 0..40 {
        wide.extend_from_slice(b"](h\x00h\x00eq\x00");
    }
    wide.extend_from_slice(b"h\x00.");
    assert!(
        matches!(problem(&wide), PickleProblem::TooLarge { .. }),
        "{:?}",
        problem(&wide)
    );
    // An array whose shape's element count overflows, and one whose data is short.
    let frombuffer = |shape: &[u64], data: &[u8]| {
        let mut b = b"\x80\x04\x8c\x13numpy._core.numeric\x8c\x0b_frombuffer\x93(".to_vec();
        b.push(b'B');
        b.extend_from_slice(&(data.len() as u32).to_le_bytes());
        b.extend_from_slice(data);
        b.extend_from_slice(b"\x8c\x05numpy\x8c\x05dtype\x93\x8c\x02f8\x89\x88\x87R(K\x03\x8c\x01<NNNJ\xff\xff\xff\xffJ\xff\xff\xff\xffK\x00tb(");
        for &d in shape {
            b.extend_from_slice(b"\x8a\x08");
            b.extend_from_slice(&d.to_le_bytes());
        }
        b.extend_from_slice(b"t\x8c\x01CtR.");
        b
    };
    let ok = decode(
        &frombuffer(
            &[2],
            &[0, 0, 0, 0, 0, 0, 0xf0, 0x3f, 0, 0, 0, 0, 0, 0, 0, 0x40],
        ),
        "frombuffer",
    )
    .unwrap();
    assert_eq!(ok, PyValue::Array(Array::f64(vec![2], vec![1.0, 2.0])));
    assert!(matches!(
        problem(&frombuffer(&[1 << 62, 1 << 62], &[0; 8])),
        PickleProblem::Array { .. }
    ));
    assert!(matches!(
        problem(&frombuffer(&[3], &[0; 16])),
        PickleProblem::Array { .. }
    ));
    // Opcodes that reach below a MARK, and a MARK never closed.
    assert!(matches!(
        problem(b"\x80\x02K\x01(\x85."),
        PickleProblem::Opcode { .. }
    ));
    assert!(matches!(
        problem(b"\x80\x02](a."),
        PickleProblem::Opcode { .. }
    ));
    assert!(matches!(
        problem(b"\x80\x02(."),
        PickleProblem::Empty | PickleProblem::Opcode { .. }
    ));
    // A callable this reader does not call.
    assert!(matches!(
        problem(b"\x80\x02cos\nsystem\nX\x02\x00\x00\x00ls\x85R."),
        PickleProblem::Call { .. }
    ));
}
