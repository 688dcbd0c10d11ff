//! The landmarks stage: `tools/drape/python/landmarks.py` (mediapipe's legacy Pose:
//! person masks and 33 landmarks) once per camera, in the environment
//! `scripts/prepare-env.sh` makes. Both are found in drape's repository: the checkout
//! this binary was built from, else a directory above the executable that holds them.
//! An installed drape without its repository says how to get them.

use std::io::BufRead as _;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::Instant;

use anyhow::{bail, Context as _};
use serde_json::json;

use super::{commit_stage, progress, read_stamp, View};

const SCRIPT: &str = "tools/drape/python/landmarks.py";
const ENV_SCRIPT: &str = "scripts/prepare-env.sh";

/// drape's repository: where the scripts are.
fn repository() -> anyhow::Result<PathBuf> {
    let holds = |d: &Path| d.join(SCRIPT).is_file() && d.join(ENV_SCRIPT).is_file();
    let built_from = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    if holds(&built_from) {
        return Ok(built_from.canonicalize().unwrap_or(built_from));
    }
    let exe = std::env::current_exe().ok();
    if let Some(found) = exe
        .as_deref()
        .and_then(|e| e.ancestors().skip(1).find(|d| holds(d)))
    {
        return Ok(found.to_path_buf());
    }
    bail!(
        "the landmarks stage needs drape's repository ({ENV_SCRIPT} and {SCRIPT}), found neither where this drape was built ({}) nor above it ({}): run drape from a checkout of the repository, or make the environment there with {ENV_SCRIPT} (python3.11 and about 400 MB)",
        built_from.display(),
        exe.map_or("?".into(), |e| e.display().to_string())
    )
}

/// Runs `command`, echoing its stderr lines as progress (prefixed) and keeping the last
/// one for an error; returns its stdout.
fn run_echoing(mut command: Command, prefix: &str, what: &str) -> anyhow::Result<String> {
    let mut child = command
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .with_context(|| format!("{what}: cannot run"))?;
    let stdout = child.stdout.take();
    let reader = std::thread::spawn(move || {
        let mut s = String::new();
        if let Some(mut o) = stdout {
            let _ = std::io::Read::read_to_string(&mut o, &mut s);
        }
        s
    });
    let mut last = String::new();
    if let Some(err) = child.stderr.take() {
        for line in std::io::BufReader::new(err).lines().map_while(Result::ok) {
            let line = line.trim().to_string();
            if line.is_empty() {
                continue;
            }
            // The scripts' own progress lines (`landmarks: ...`, `prepare-env: ...`) are
            // echoed; mediapipe's and TensorFlow Lite's log lines are not. Whatever the
            // last line is explains a failure.
            if let Some(own) = ["landmarks: ", "prepare-env: "]
                .iter()
                .find_map(|p| line.strip_prefix(p))
            {
                progress(&format!("{prefix}{own}"));
            }
            last = line;
        }
    }
    let status = child
        .wait()
        .with_context(|| format!("{what}: cannot run"))?;
    let stdout = reader.join().unwrap_or_default();
    if !status.success() {
        let reason = last.strip_prefix("error: ").unwrap_or(&last);
        bail!("{what} failed ({status}): {reason}");
    }
    Ok(stdout)
}

/// The environment's Python, made once by `scripts/prepare-env.sh`.
fn python(repo: &Path) -> anyhow::Result<PathBuf> {
    let script = repo.join(ENV_SCRIPT);
    progress(&format!(
        "landmarks: the mediapipe environment ({}; made once, about 30 s and 400 MB)",
        script.display()
    ));
    let stdout = run_echoing(
        Command::new(&script),
        "landmarks: ",
        &script.display().to_string(),
    )?;
    let py = stdout
        .lines()
        .map(str::trim)
        .rfind(|l| !l.is_empty())
        .map(PathBuf::from)
        .with_context(|| format!("{}: printed no Python path", script.display()))?;
    if !py.is_file() {
        bail!(
            "{}: its Python {} does not exist",
            script.display(),
            py.display()
        );
    }
    Ok(py)
}

/// Landmarks for every view (module header); `frame_keys` are the frames stage's
/// stamps, so new frames make new landmarks.
pub fn stage(
    out: &Path,
    views: &[View],
    frame_keys: &[serde_json::Value],
    redo: bool,
) -> anyhow::Result<()> {
    let mut env: Option<(PathBuf, PathBuf)> = None;
    for (view, frames_key) in views.iter().zip(frame_keys) {
        let dir = out.join("landmarks").join(&view.name);
        let key = json!({"frames": frames_key, "script": SCRIPT, "person": "auto"});
        if !redo && read_stamp(&dir).is_some_and(|s| s == key) {
            progress(&format!("landmarks: {}: up to date (skipped)", view.name));
            continue;
        }
        if env.is_none() {
            let repo = repository()?;
            let py = python(&repo)?;
            env = Some((repo, py));
        }
        let Some((repo, py)) = &env else {
            unreachable!("set above")
        };
        let t0 = Instant::now();
        let staged =
            drape_io::StagedDir::new(&dir).with_context(|| format!("{}", dir.display()))?;
        let mut command = Command::new(py);
        command
            .arg(repo.join(SCRIPT))
            .arg(out.join("frames").join(&view.name))
            .arg(staged.path());
        run_echoing(
            command,
            &format!("landmarks: {}: ", view.name),
            &format!("{SCRIPT} on {}", view.name),
        )?;
        commit_stage(staged, &dir, &key)?;
        progress(&format!(
            "landmarks: {}: written to {} in {:.1} s",
            view.name,
            dir.display(),
            t0.elapsed().as_secs_f64()
        ));
    }
    Ok(())
}
