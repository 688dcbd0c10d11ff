//! The runs of a benchmark loop: untimed warm-ups, then timed runs.
//!
//! A GPU's clocks rest low when it idles and ramp up under load, so a fixed count of
//! warm-up runs of a short frame can end before the clocks are up, and the timed runs
//! then measure an idle-clocked GPU (docs/performance.md, "Devices and how to read the
//! figures"). Warm-ups therefore go on until both `--warmup` runs are done and
//! `--warm-seconds` have passed since the loop began.

use std::sync::OnceLock;
use std::time::{Duration, Instant};

static WARM_FOR: OnceLock<Duration> = OnceLock::new();

/// Sets the least warm-up time of every loop (once, from the command line).
pub fn set_warm_seconds(seconds: f64) {
    let _ = WARM_FOR.set(Duration::from_secs_f64(seconds.max(0.0)));
}

/// The least warm-up time of every loop, in seconds (for the JSON output).
pub fn warm_seconds() -> f64 {
    WARM_FOR.get().copied().unwrap_or_default().as_secs_f64()
}

/// Yields `false` for each warm-up run and `true` for each of the `runs` timed ones.
pub struct Runs {
    warmup: u32,
    runs: u32,
    warm_for: Duration,
    start: Option<Instant>,
    warmed: u32,
    timed: u32,
}

impl Runs {
    pub fn new(warmup: u32, runs: u32) -> Self {
        Self {
            warmup,
            runs,
            warm_for: WARM_FOR.get().copied().unwrap_or_default(),
            start: None,
            warmed: 0,
            timed: 0,
        }
    }
}

impl Iterator for Runs {
    type Item = bool;

    fn next(&mut self) -> Option<bool> {
        let start = *self.start.get_or_insert_with(Instant::now);
        if self.timed == 0 && (self.warmed < self.warmup || start.elapsed() < self.warm_for) {
            self.warmed += 1;
            return Some(false);
        }
        if self.timed < self.runs {
            self.timed += 1;
            return Some(true);
        }
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn warm_ups_then_the_timed_runs() {
        let runs: Vec<bool> = Runs {
            warmup: 2,
            runs: 3,
            warm_for: Duration::ZERO,
            start: None,
            warmed: 0,
            timed: 0,
        }
        .collect();
        assert_eq!(runs, [false, false, true, true, true]);
    }

    #[test]
    fn warm_ups_last_at_least_the_warm_time() {
        let mut runs = Runs {
            warmup: 1,
            runs: 2,
            warm_for: Duration::from_millis(30),
            start: None,
            warmed: 0,
            timed: 0,
        };
        let t0 = Instant::now();
        let mut warm = 0;
        while runs.next() == Some(false) {
            warm += 1;
            std::thread::sleep(Duration::from_millis(5));
        }
        assert!(
            t0.elapsed() >= Duration::from_millis(30),
            "warmed for {:?}",
            t0.elapsed()
        );
        assert!(warm >= 6, "{warm} warm-up runs of 5 ms in 30 ms");
        // The loop's last call took the first timed run.
        assert_eq!((runs.next(), runs.next()), (Some(true), None));
    }
}
