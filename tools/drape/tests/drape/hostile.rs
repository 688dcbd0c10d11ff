//! Hostile input, table-driven: every case in `tests/hostile/cases.txt` builds its
//! input in a directory of its own (from a small synthetic sequence, a tiny trained run
//! and the operations below), runs one `drape` command and checks what a user needs:
//! a non-zero exit, no panic, exactly one `error:` line naming the file or option, and
//! the case directory byte-for-byte as it was (no partial or stale output). Dataset
//! cases also run `drape inspect`, which must report the same first problem as
//! `drape train`. A case that hangs is killed after [`HANG_SECONDS`].
//!
//! Table format, one case per line, four columns separated by ` | `:
//!
//! ```text
//! id | op; op; ... | arguments of drape ({d} is the case directory) | expectation
//! ```
//!
//! Operations (paths relative to the case directory):
//! - `neuman` / `zju` / `synth`: copy the base sequence's `neuman/`, `zju/` (to `data/`)
//!   or the whole `drape synth` output (to `data/`); `run`: copy the tiny trained run to
//!   `run/`; `ply`: the run's body PLY as `scene.ply`; `obj`: a garment OBJ as
//!   `garment.obj`; `motion F [D]`: a motion file `motion.npz` of F frames at 30 fps (its
//!   root walking D metres along x).
//! - `text P TEXT` (escapes `\n`, `\t`, `\\`), `hex P HEX`, `cp P Q`, `rm P`, `mkdir P`, `trunc P N`,
//!   `repeat P N TEXT` (TEXT N times).
//! - `field P LINE COL VALUE`: the LINE-th line of a text file that is not a `#` comment,
//!   its COL-th space-separated field, set to VALUE; `line P LINE TEXT`: that line
//!   replaced; `append P TEXT`.
//! - `npz P KEY set I V` (element I of the array; `all` for every element), `npz P KEY
//!   shape D,D,..` (zeros of that shape; `-` for a 0-d array), `npz P KEY del`; `npy P ...`
//!   the same on a single `.npy` file (KEY is `-`).
//! - `annots CAM FIELD I V`: ZJU `annots.npy` camera CAM's K/D/R/T element I set to V
//!   (re-pickled by drape's writer); `annots-drop CAM`: the camera removed.
//! - `png P W H DEPTH COLOUR`: a PNG of only a header (signature, IHDR, IEND) declaring
//!   that size, bit depth and colour type.
//!
//! Expectations: `error NEEDLE` (the error line contains NEEDLE), `same NEEDLE` (the
//! arguments are ignored; `inspect data` and `train --data data` both fail with the same
//! message, containing NEEDLE), `ok` (the case is accepted: exit 0), `ok P,Q` (accepted,
//! and the files P and Q exist afterwards; `!P`: P does not).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Mutex, OnceLock};
use std::time::{Duration, Instant};

use drape_trainer::npy::{self, Array, Dtype};

/// A case still running after this long is a hang: well past the slowest accepted
/// cases, cloth simulations of up to ten frames after 2 settling ones
/// (docs/performance.md, "Host-side timings").
const HANG_SECONDS: u64 = 60;

/// Read when the test runs (not compiled in), so cases can be added without a rebuild.
const TABLE: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/hostile/cases.txt");

/// The training configuration dataset cases train with (they fail before training).
fn tiny() -> String {
    crate::fixtures::tiny_body_config(
        "[schedule]\nsteps = 2\nfit_steps = 2\ncheckpoint_every = 1\nlog_every = 1\n",
    )
}

/// One directory per test process, so that two runs never share fixtures.
fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_TARGET_TMPDIR"))
        .join("hostile")
        .join(std::process::id().to_string())
}

fn drape() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_drape"));
    c.stdin(Stdio::null()).env("RUST_BACKTRACE", "0");
    c
}

/// The synthetic sequence and a tiny run trained on it, made once per test binary.
fn base() -> &'static Path {
    static BASE: OnceLock<PathBuf> = OnceLock::new();
    BASE.get_or_init(|| {
        let b = root().join("base");
        let _ = std::fs::remove_dir_all(&b);
        std::fs::create_dir_all(&b).unwrap();
        let o = drape()
            .args(["synth", "--out"])
            .arg(b.join("synth"))
            .args([
                "--size",
                "32",
                "--frames",
                "5",
                "--cameras",
                "2",
                "--samples",
                "1",
            ])
            .output()
            .unwrap();
        assert!(
            o.status.success(),
            "base synth: {}",
            String::from_utf8_lossy(&o.stderr)
        );
        drape_io::write(b.join("tiny.toml"), tiny()).unwrap();
        let o = drape()
            .args(["train", "--data"])
            .arg(b.join("synth"))
            .arg("--out")
            .arg(b.join("run"))
            .arg("--config")
            .arg(b.join("tiny.toml"))
            .output()
            .unwrap();
        assert!(
            o.status.success(),
            "base run: {}",
            String::from_utf8_lossy(&o.stderr)
        );
        b
    })
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        let t = to.join(e.file_name());
        if e.file_type().unwrap().is_dir() {
            copy_dir(&e.path(), &t);
        } else {
            std::fs::copy(e.path(), &t).unwrap();
        }
    }
}

/// Every file under `dir` with a hash of its bytes: "unchanged" means equal snapshots.
fn snapshot(dir: &Path) -> BTreeMap<String, u64> {
    use std::hash::{Hash, Hasher};
    let mut out = BTreeMap::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let e = e.unwrap();
            let rel = e.path().strip_prefix(dir).unwrap().display().to_string();
            if e.file_type().unwrap().is_dir() {
                out.insert(format!("{rel}/"), 0);
                stack.push(e.path());
            } else {
                let mut h = std::collections::hash_map::DefaultHasher::new();
                std::fs::read(e.path()).unwrap_or_default().hash(&mut h);
                out.insert(rel, h.finish());
            }
        }
    }
    out
}

fn unescape(s: &str) -> Vec<u8> {
    let mut out = Vec::new();
    let mut chars = s.chars();
    while let Some(c) = chars.next() {
        if c != '\\' {
            let mut b = [0; 4];
            out.extend_from_slice(c.encode_utf8(&mut b).as_bytes());
            continue;
        }
        match chars.next() {
            Some('n') => out.push(b'\n'),
            Some('t') => out.push(b'\t'),
            Some('r') => out.push(b'\r'),
            Some('0') => out.push(0),
            Some('x') => {
                let h: String = chars.by_ref().take(2).collect();
                out.push(u8::from_str_radix(&h, 16).expect("\\xNN"));
            }
            Some(o) => out.push(o as u8),
            None => out.push(b'\\'),
        }
    }
    out
}

fn number(s: &str) -> f64 {
    match s {
        "nan" => f64::NAN,
        "inf" => f64::INFINITY,
        "-inf" => f64::NEG_INFINITY,
        _ => s.parse().unwrap_or_else(|_| panic!("not a number: {s}")),
    }
}

/// The lines of a text file that are not `#` comments, by index into all lines.
fn data_line(lines: &[String], n: usize) -> usize {
    lines
        .iter()
        .enumerate()
        .filter(|(_, l)| !l.starts_with('#'))
        .nth(n)
        .unwrap_or_else(|| panic!("no data line {n}"))
        .0
}

fn edit_lines(path: &Path, f: impl FnOnce(&mut Vec<String>)) {
    let text = std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let mut lines: Vec<String> = text.split('\n').map(str::to_string).collect();
    f(&mut lines);
    drape_io::write(path, lines.join("\n")).unwrap();
}

fn edit_array(a: &mut Array, how: &[&str]) {
    match how {
        ["set", "all", v] => a.data.iter_mut().for_each(|x| *x = number(v)),
        ["set", i, v] => a.data[i.parse::<usize>().unwrap()] = number(v),
        ["shape", dims] => {
            let shape: Vec<usize> = if *dims == "-" {
                vec![]
            } else {
                dims.split(',').map(|d| d.parse().unwrap()).collect()
            };
            *a = Array::new(a.dtype, shape.clone(), vec![0.0; shape.iter().product()]);
        }
        other => panic!("array edit {other:?}"),
    }
}

fn png_header(w: u32, h: u32, depth: u8, colour: u8) -> Vec<u8> {
    fn chunk(out: &mut Vec<u8>, kind: &[u8; 4], data: &[u8]) {
        out.extend_from_slice(&(data.len() as u32).to_be_bytes());
        let start = out.len();
        out.extend_from_slice(kind);
        out.extend_from_slice(data);
        let crc = crc32(&out[start..]);
        out.extend_from_slice(&crc.to_be_bytes());
    }
    let mut out = b"\x89PNG\r\n\x1a\n".to_vec();
    let mut ihdr = Vec::new();
    ihdr.extend_from_slice(&w.to_be_bytes());
    ihdr.extend_from_slice(&h.to_be_bytes());
    ihdr.extend_from_slice(&[depth, colour, 0, 0, 0]);
    chunk(&mut out, b"IHDR", &ihdr);
    chunk(&mut out, b"IEND", &[]);
    out
}

fn crc32(bytes: &[u8]) -> u32 {
    let mut c = 0xFFFF_FFFFu32;
    for &b in bytes {
        c ^= u32::from(b);
        for _ in 0..8 {
            c = if c & 1 != 0 {
                0xEDB8_8320 ^ (c >> 1)
            } else {
                c >> 1
            };
        }
    }
    !c
}

fn apply(d: &Path, op: &str) {
    let words: Vec<&str> = op.split_whitespace().collect();
    let p = |i: usize| d.join(words[i]);
    let rest = |n: usize| {
        op.splitn(n + 1, char::is_whitespace)
            .nth(n)
            .unwrap_or("")
            .to_string()
    };
    let b = base();
    match words[0] {
        "neuman" => copy_dir(&b.join("synth/neuman"), &d.join("data")),
        "zju" => copy_dir(&b.join("synth/zju"), &d.join("data")),
        "synth" => copy_dir(&b.join("synth"), &d.join("data")),
        "run" => copy_dir(&b.join("run"), &d.join("run")),
        "ply" => {
            let ply = std::fs::read_dir(b.join("run"))
                .unwrap()
                .map(|e| e.unwrap().path())
                .find(|p| p.extension().is_some_and(|e| e == "ply"))
                .expect("the run's PLY");
            std::fs::copy(ply, d.join("scene.ply")).unwrap();
        }
        "obj" => {
            std::fs::copy(
                b.join("synth/gt/garments/tshirt_0000.obj"),
                d.join("garment.obj"),
            )
            .unwrap();
        }
        "motion" => {
            let frames: usize = words[1].parse().unwrap();
            // `motion F D`: the root walks D metres along x over the F frames.
            let distance: f64 = words.get(2).map_or(0.0, |w| number(w));
            let trans: Vec<f64> = (0..frames)
                .flat_map(|f| [distance * f as f64 / (frames.max(2) - 1) as f64, 0.0, 0.0])
                .collect();
            let mut a = BTreeMap::new();
            a.insert(
                "poses".to_string(),
                Array::f64(vec![frames, 72], vec![0.0; frames * 72]),
            );
            a.insert("trans".to_string(), Array::f64(vec![frames, 3], trans));
            a.insert("fps".to_string(), Array::f64(vec![], vec![30.0]));
            npy::write_npz(&d.join("motion.npz"), &a).unwrap();
        }
        "text" => {
            if let Some(parent) = p(1).parent() {
                std::fs::create_dir_all(parent).unwrap();
            }
            drape_io::write(p(1), unescape(&rest(2))).unwrap()
        }
        "hex" => {
            let hex: String = rest(2).split_whitespace().collect();
            let bytes: Vec<u8> = (0..hex.len())
                .step_by(2)
                .map(|i| u8::from_str_radix(&hex[i..i + 2], 16).unwrap())
                .collect();
            drape_io::write(p(1), bytes).unwrap()
        }
        "repeat" => {
            let n: usize = words[2].parse().unwrap();
            drape_io::write(p(1), unescape(&rest(3)).repeat(n)).unwrap()
        }
        "cp" => {
            std::fs::copy(p(1), p(2)).unwrap();
        }
        "rm" => {
            let path = p(1);
            if path.is_dir() {
                std::fs::remove_dir_all(path).unwrap()
            } else {
                std::fs::remove_file(path).unwrap()
            }
        }
        "mkdir" => std::fs::create_dir_all(p(1)).unwrap(),
        // `export RUN FILE`: `drape export RUN --out FILE`.
        "export" => {
            let o = drape()
                .arg("export")
                .arg(p(1))
                .arg("--out")
                .arg(p(2))
                .output()
                .unwrap();
            assert!(
                o.status.success(),
                "export: {}",
                String::from_utf8_lossy(&o.stderr)
            );
        }
        // `avatar-header FILE KEY JSON`: the avatar file's header.json KEY set to JSON.
        "avatar-header" => {
            let bytes = std::fs::read(p(1)).unwrap();
            let value: serde_json::Value = serde_json::from_str(&rest(3)).unwrap();
            let edited = drape_trainer::testing::edit_avatar_header(&bytes, |h| {
                h[words[2]] = value;
            });
            drape_io::write(p(1), edited).unwrap();
        }
        "trunc" => {
            let bytes = std::fs::read(p(1)).unwrap();
            drape_io::write(
                p(1),
                &bytes[..words[2].parse::<usize>().unwrap().min(bytes.len())],
            )
            .unwrap()
        }
        "field" => {
            let (line, col): (usize, usize) =
                (words[2].parse().unwrap(), words[3].parse().unwrap());
            let value = rest(4);
            edit_lines(&p(1), |lines| {
                let i = data_line(lines, line);
                let mut fields: Vec<String> = lines[i].split(' ').map(str::to_string).collect();
                fields[col] = value;
                lines[i] = fields.join(" ");
            })
        }
        "line" => {
            let line: usize = words[2].parse().unwrap();
            let text = rest(3);
            edit_lines(&p(1), |lines| {
                let i = data_line(lines, line);
                lines[i] = text;
            })
        }
        "append" => {
            let mut bytes = std::fs::read(p(1)).unwrap();
            bytes.extend(unescape(&rest(2)));
            drape_io::write(p(1), bytes).unwrap()
        }
        "npz" => {
            let mut arrays = npy::read_npz(&p(1)).unwrap();
            match &words[3..] {
                ["del"] => {
                    arrays.remove(words[2]).expect("key to delete");
                }
                ["shape", _] if !arrays.contains_key(words[2]) => {
                    let mut a = Array::new(Dtype::F64, vec![], vec![0.0]);
                    edit_array(&mut a, &words[3..]);
                    arrays.insert(words[2].to_string(), a);
                }
                how => edit_array(
                    arrays
                        .get_mut(words[2])
                        .unwrap_or_else(|| panic!("no key {}", words[2])),
                    how,
                ),
            }
            npy::write_npz(&p(1), &arrays).unwrap()
        }
        "npy" => {
            let bytes = std::fs::read(p(1)).unwrap();
            let mut a = npy::decode(&bytes, words[1], None).unwrap();
            edit_array(&mut a, &words[3..]);
            drape_io::write(p(1), npy::encode(&a)).unwrap()
        }
        "annots" => {
            use drape_trainer::dataset::zju::ZjuAnnots;
            let dir = d.join("data");
            let mut annots = ZjuAnnots::read(&dir).unwrap();
            let cam = &mut annots.cameras[words[1].parse::<usize>().unwrap()];
            let i: usize = words[3].parse().unwrap();
            let v = number(words[4]);
            match words[2] {
                "K" => cam.k[i / 3][i % 3] = v,
                "D" => cam.d[i] = v,
                "R" => cam.r[i / 3][i % 3] = v,
                "T" => cam.t[i] = v,
                f => panic!("annots field {f}"),
            }
            annots.write(&dir).unwrap()
        }
        "annots-drop" => {
            use drape_trainer::dataset::zju::ZjuAnnots;
            let dir = d.join("data");
            let mut annots = ZjuAnnots::read(&dir).unwrap();
            let cam: usize = words[1].parse().unwrap();
            annots.cameras.remove(cam);
            annots.images.iter_mut().for_each(|f| {
                f.remove(cam);
            });
            annots.write(&dir).unwrap()
        }
        "ply-set" => {
            use drape_trainer::ply;
            let path = d.join("scene.ply");
            let mut cloud = ply::read(&path).unwrap();
            let v = number(words[3]) as f32;
            let (values, stride, offset) = match words[2] {
                "x" => (&mut cloud.means, 3, 0),
                "z" => (&mut cloud.means, 3, 2),
                "scale" => (&mut cloud.log_scales, 3, 0),
                "opacity" => (&mut cloud.opacity_logits, 1, 0),
                "quat" => (&mut cloud.quats, 4, 0),
                f => panic!("ply field {f}"),
            };
            let n = values.len() / stride;
            let which: Vec<usize> = if words[1] == "all" {
                (0..n).collect()
            } else {
                vec![words[1].parse().unwrap()]
            };
            for i in which {
                values[stride * i + offset] = v;
                if words[2] == "quat" {
                    values[stride * i + 1..stride * i + 4].fill(v);
                }
            }
            ply::write(&path, &cloud).unwrap()
        }
        "png" => {
            let n = |i: usize| words[i].parse::<u32>().unwrap();
            drape_io::write(p(1), png_header(n(2), n(3), n(4) as u8, n(5) as u8)).unwrap()
        }
        other => panic!("unknown operation '{other}'"),
    }
}

struct Case {
    line: usize,
    id: String,
    ops: Vec<String>,
    args: String,
    expect: String,
}

fn parse_table() -> Vec<Case> {
    let table = std::fs::read_to_string(TABLE).unwrap_or_else(|e| panic!("{TABLE}: {e}"));
    let mut cases = Vec::new();
    for (n, line) in table.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let cols: Vec<&str> = line.split(" | ").map(str::trim).collect();
        assert_eq!(
            cols.len(),
            4,
            "cases.txt:{}: four columns separated by ' | ' expected: {line}",
            n + 1
        );
        cases.push(Case {
            line: n + 1,
            id: cols[0].to_string(),
            ops: cols[1]
                .split("; ")
                .map(str::trim)
                .filter(|o| !o.is_empty() && *o != "-")
                .map(str::to_string)
                .collect(),
            args: cols[2].to_string(),
            expect: cols[3].to_string(),
        });
    }
    cases
}

/// Runs drape with a hang watchdog; returns (exit code, stdout, stderr, seconds).
fn run_drape(args: &[String]) -> Result<(Option<i32>, String, String, f64), String> {
    let t0 = Instant::now();
    let mut child = drape()
        .args(args)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .map_err(|e| e.to_string())?;
    // The pipes are drained on threads so a chatty command cannot block on them.
    let mut so = child.stdout.take().unwrap();
    let mut se = child.stderr.take().unwrap();
    let out_t = std::thread::spawn(move || {
        let mut s = String::new();
        let _ = std::io::Read::read_to_string(&mut so, &mut s);
        s
    });
    let err_t = std::thread::spawn(move || {
        let mut s = Vec::new();
        let _ = std::io::Read::read_to_end(&mut se, &mut s);
        String::from_utf8_lossy(&s).to_string()
    });
    let status = loop {
        if let Some(s) = child.try_wait().map_err(|e| e.to_string())? {
            break s;
        }
        if t0.elapsed() > Duration::from_secs(HANG_SECONDS) {
            let _ = child.kill();
            let _ = child.wait();
            return Err(format!("hung: killed after {HANG_SECONDS} s"));
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    Ok((
        status.code(),
        out_t.join().unwrap(),
        err_t.join().unwrap(),
        t0.elapsed().as_secs_f64(),
    ))
}

fn split_args(d: &Path, args: &str) -> Vec<String> {
    args.split_whitespace()
        .map(|a| a.replace("{d}", d.to_str().unwrap()))
        .collect()
}

/// The one `error:` line, checked: exit non-zero, no panic, one error line.
fn one_error(
    what: &str,
    (code, _out, err, _): &(Option<i32>, String, String, f64),
) -> Result<String, String> {
    if code == &Some(0) {
        return Err(format!(
            "{what}: exit 0, an error was expected; stderr: {err}"
        ));
    }
    if err.contains("panicked") || code.is_none() || code == &Some(101) || code == &Some(134) {
        return Err(format!("{what}: crashed (exit {code:?}): {err}"));
    }
    let errors: Vec<&str> = err.lines().filter(|l| l.starts_with("error")).collect();
    if errors.len() != 1 {
        return Err(format!(
            "{what}: {} error lines, one expected: {err}",
            errors.len()
        ));
    }
    Ok(errors[0].to_string())
}

fn run_case(case: &Case) -> Result<(), String> {
    let d = root().join("cases").join(&case.id);
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    drape_io::write(d.join("tiny.toml"), tiny()).unwrap();
    for op in &case.ops {
        apply(&d, &op.replace("{d}", d.to_str().unwrap()));
    }
    let before = snapshot(&d);
    let (kind, needle) = case
        .expect
        .split_once(' ')
        .unwrap_or((case.expect.as_str(), ""));
    let result: Result<(), String> = match kind {
        "ok" => {
            let r = run_drape(&split_args(&d, &case.args))?;
            if r.0 != Some(0) || r.2.contains("panicked") {
                return Err(format!("accepted case failed (exit {:?}): {}", r.0, r.2));
            }
            for f in needle.split(',').map(str::trim).filter(|f| !f.is_empty()) {
                match f.strip_prefix('!') {
                    Some(stale) if d.join(stale).exists() => {
                        return Err(format!(
                            "accepted, but {stale} of an earlier output is still there"
                        ))
                    }
                    None if !d.join(f).exists() => {
                        return Err(format!("accepted, but {f} was not written"))
                    }
                    _ => {}
                }
            }
            Ok(())
        }
        "error" => {
            let r = run_drape(&split_args(&d, &case.args))?;
            let line = one_error("drape", &r)?;
            if !line.contains(needle) {
                return Err(format!("the error does not name '{needle}': {line}"));
            }
            Ok(())
        }
        "same" => {
            let data = d.join("data");
            let inspect = run_drape(&["inspect".into(), data.display().to_string()])?;
            one_error("inspect", &inspect)?;
            let problem = inspect
                .1
                .lines()
                .find_map(|l| l.trim().strip_prefix("problem: "))
                .unwrap_or("")
                .to_string();
            let train = run_drape(&split_args(
                &d,
                "train --data {d}/data --out {d}/out --config {d}/tiny.toml",
            ))?;
            let line = one_error("train", &train)?;
            let message = line.strip_prefix("error: ").unwrap_or(&line);
            if problem != message {
                return Err(format!(
                    "inspect and train disagree:\n  inspect: {problem}\n  train:   {message}"
                ));
            }
            if !message.contains(needle) {
                return Err(format!("the error does not name '{needle}': {line}"));
            }
            Ok(())
        }
        other => panic!("cases.txt:{}: unknown expectation '{other}'", case.line),
    };
    result?;
    if kind != "ok" {
        let after = snapshot(&d);
        if before != after {
            let changed: Vec<&String> = after
                .keys()
                .filter(|k| before.get(*k) != after.get(*k))
                .chain(before.keys().filter(|k| !after.contains_key(*k)))
                .collect();
            return Err(format!("the case directory changed: {changed:?}"));
        }
    }
    let _ = std::fs::remove_dir_all(&d);
    Ok(())
}

#[test]
fn hostile_inputs_fail_in_one_line_and_change_nothing() {
    let cases = parse_table();
    let mut ids = std::collections::HashSet::new();
    for c in &cases {
        assert!(
            ids.insert(c.id.clone()),
            "cases.txt:{}: duplicate id {}",
            c.line,
            c.id
        );
    }
    let only = std::env::var("DRAPE_HOSTILE_ONLY").ok();
    let cases: Vec<&Case> = cases
        .iter()
        .filter(|c| {
            only.as_deref()
                .is_none_or(|o| o.split(',').any(|o| c.id.starts_with(o)))
        })
        .collect();
    base();
    let next = AtomicUsize::new(0);
    let failures = Mutex::new(Vec::new());
    let times = Mutex::new(Vec::new());
    let threads = std::thread::available_parallelism()
        .map_or(2, |n| n.get())
        .min(4);
    std::thread::scope(|s| {
        for _ in 0..threads {
            s.spawn(|| loop {
                let i = next.fetch_add(1, Ordering::Relaxed);
                let Some(case) = cases.get(i) else { break };
                let t0 = Instant::now();
                let r = std::panic::catch_unwind(|| run_case(case)).unwrap_or_else(|p| {
                    Err(format!(
                        "the test's own set-up panicked: {:?}",
                        p.downcast_ref::<String>()
                            .cloned()
                            .or(p.downcast_ref::<&str>().map(|s| s.to_string()))
                    ))
                });
                times
                    .lock()
                    .unwrap()
                    .push((t0.elapsed().as_secs_f64(), case.id.as_str()));
                if let Err(e) = r {
                    failures
                        .lock()
                        .unwrap()
                        .push(format!("{} (cases.txt:{}): {e}", case.id, case.line));
                }
            });
        }
    });
    let failures = failures.into_inner().unwrap();
    // The slowest cases, set-up included: where the table's time goes.
    let mut times = times.into_inner().unwrap();
    times.sort_by(|a, b| b.0.total_cmp(&a.0));
    let total: f64 = times.iter().map(|t| t.0).sum();
    eprintln!("hostile cases: {total:.0} s in all; the slowest:");
    for (secs, id) in times.iter().take(12) {
        eprintln!("  {secs:6.1} s  {id}");
    }
    if failures.is_empty() {
        let _ = std::fs::remove_dir_all(root());
    }
    eprintln!(
        "{} hostile cases run, {} failed",
        cases.len(),
        failures.len()
    );
    assert!(
        failures.is_empty(),
        "{} of {} hostile cases failed:\n{}",
        failures.len(),
        cases.len(),
        failures.join("\n")
    );
}
