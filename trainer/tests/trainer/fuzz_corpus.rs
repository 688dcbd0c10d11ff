//! The fuzz corpus and every past crasher, replayed on stable: each file under
//! `fuzz/corpus/<target>/` and `fuzz/regressions/<target>/` goes through the loader
//! entry point `drape_trainer::fuzzing::<target>`, which must return (any error is
//! fine) without a panic. An abort or a stack overflow ends the test binary, which
//! fails the run just the same; a loop that does not end is caught by the hang guard.

use std::path::PathBuf;
use std::time::{Duration, Instant};

/// An input that takes this long is a hang (the slowest corpus file, a deep pickle,
/// takes well under a second).
const HANG: Duration = Duration::from_secs(20);

#[test]
fn every_corpus_file_and_past_crasher_loads_or_fails_cleanly() {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../fuzz");
    let mut failures = Vec::new();
    let mut counts = Vec::new();
    for (name, target) in drape_trainer::fuzzing::TARGETS {
        let mut n = 0;
        for folder in ["corpus", "regressions"] {
            let dir = root.join(folder).join(name);
            let Ok(entries) = std::fs::read_dir(&dir) else {
                continue;
            };
            let mut files: Vec<PathBuf> = entries
                .flatten()
                .map(|e| e.path())
                .filter(|p| p.is_file())
                .collect();
            files.sort();
            for path in files {
                let bytes = std::fs::read(&path).unwrap();
                let t0 = Instant::now();
                let result = std::panic::catch_unwind(|| target(&bytes));
                let took = t0.elapsed();
                n += 1;
                if let Err(p) = result {
                    let message = p
                        .downcast_ref::<String>()
                        .cloned()
                        .or_else(|| p.downcast_ref::<&str>().map(|s| s.to_string()))
                        .unwrap_or_default();
                    failures.push(format!("{name}: {}: panicked: {message}", path.display()));
                } else if took > HANG {
                    failures.push(format!(
                        "{name}: {}: took {:.1} s",
                        path.display(),
                        took.as_secs_f64()
                    ));
                }
            }
        }
        assert!(
            n > 0,
            "fuzz target '{name}' has no corpus in {}",
            root.join("corpus").join(name).display()
        );
        counts.push(format!("{name} {n}"));
    }
    eprintln!("replayed: {}", counts.join(", "));
    assert!(
        failures.is_empty(),
        "{} inputs failed:\n{}",
        failures.len(),
        failures.join("\n")
    );
}
