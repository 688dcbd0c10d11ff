//! A context-wide profile: while it is on, every submission adds its passes' GPU time
//! (from the timestamp queries the recorder already writes) and its own host wall time
//! (end of recording to the end of the wait) under its label, and callers may add host
//! phases of their own. It answers "where does a training step go" without threading
//! timings through every op's API.
//!
//! Off by default: then a submission pays one uncontended mutex lock and nothing else.

use std::collections::BTreeMap;

/// Sum and count of one named entry.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct ProfileEntry {
    /// Times the entry was recorded.
    pub calls: u64,
    /// Milliseconds summed over them.
    pub ms: f64,
}

impl ProfileEntry {
    fn add(&mut self, ms: f64) {
        self.calls += 1;
        self.ms += ms;
    }
}

/// What was measured since the profile was started.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct Profile {
    /// GPU milliseconds per pass name (summed over every submission).
    pub gpu_passes: BTreeMap<String, ProfileEntry>,
    /// GPU milliseconds per scope (`Recording::set_scope`: a layer, a render), each
    /// submission's passes of the scope counted once where they ran side by side.
    pub gpu_scopes: BTreeMap<String, ProfileEntry>,
    /// Host wall milliseconds per submission label, submit to end of wait: GPU time
    /// plus the queue's latency.
    pub submissions: BTreeMap<String, ProfileEntry>,
    /// Host phases the caller timed itself ([`crate::Context::profile_host`]).
    pub host: BTreeMap<String, ProfileEntry>,
}

impl Profile {
    pub(crate) fn add_pass(&mut self, name: &str, ms: f64) {
        self.gpu_passes.entry(name.to_string()).or_default().add(ms);
    }

    pub(crate) fn add_scope(&mut self, scope: &str, ms: f64) {
        self.gpu_scopes
            .entry(scope.to_string())
            .or_default()
            .add(ms);
    }

    pub(crate) fn add_submission(&mut self, label: &str, ms: f64) {
        self.submissions
            .entry(label.to_string())
            .or_default()
            .add(ms);
    }

    pub(crate) fn add_host(&mut self, name: &str, ms: f64) {
        self.host.entry(name.to_string()).or_default().add(ms);
    }

    /// GPU time summed by the pass name's prefix up to its first `.` (`splat.rasterize`
    /// → `splat`), largest first: the stage split of a step.
    pub fn gpu_by_stage(&self) -> Vec<(String, ProfileEntry)> {
        let mut stages: BTreeMap<String, ProfileEntry> = BTreeMap::new();
        for (name, e) in &self.gpu_passes {
            let stage = name.split('.').next().unwrap_or(name);
            let s = stages.entry(stage.to_string()).or_default();
            s.calls += e.calls;
            s.ms += e.ms;
        }
        sorted(stages)
    }

    /// Pass entries, largest GPU time first.
    pub fn passes_by_time(&self) -> Vec<(String, ProfileEntry)> {
        sorted(self.gpu_passes.clone())
    }

    /// A plain-text table: per submission label (host wall), per stage and the top
    /// `top` passes (GPU), per host phase; each with its share of `total_ms` and its
    /// time per `per` (e.g. per step).
    pub fn table(&self, total_ms: f64, per: u64, top: usize) -> String {
        use std::fmt::Write;
        let per = per.max(1) as f64;
        let mut s = String::new();
        let mut section = |title: &str, rows: Vec<(String, ProfileEntry)>| {
            if rows.is_empty() {
                return;
            }
            let _ = writeln!(
                s,
                "{title:<44} {:>10} {:>12} {:>7} {:>8}",
                "calls", "ms/step", "share", "total s"
            );
            for (name, e) in rows {
                let _ = writeln!(
                    s,
                    "  {name:<42} {:>10} {:>12.2} {:>6.1}% {:>8.2}",
                    e.calls,
                    e.ms / per,
                    100.0 * e.ms / total_ms.max(1e-9),
                    e.ms / 1e3
                );
            }
        };
        section("submission (host wall)", sorted(self.submissions.clone()));
        section("host phase", sorted(self.host.clone()));
        section("GPU stage", self.gpu_by_stage());
        section(
            "GPU scope (layer or render)",
            sorted(self.gpu_scopes.clone()),
        );
        section(
            &format!("GPU pass (top {top})"),
            self.passes_by_time().into_iter().take(top).collect(),
        );
        s
    }
}

fn sorted(map: BTreeMap<String, ProfileEntry>) -> Vec<(String, ProfileEntry)> {
    let mut v: Vec<_> = map.into_iter().collect();
    v.sort_by(|a, b| b.1.ms.total_cmp(&a.1.ms).then_with(|| a.0.cmp(&b.0)));
    v
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stages_group_by_prefix_and_sort_by_time() {
        let mut p = Profile::default();
        p.add_pass("splat.rasterize", 5.0);
        p.add_pass("splat.project", 1.0);
        p.add_pass("nn.gemm", 3.0);
        p.add_pass("nn.gemm", 4.0);
        p.add_pass("adam", 0.5);
        let stages = p.gpu_by_stage();
        let names: Vec<&str> = stages.iter().map(|(n, _)| n.as_str()).collect();
        assert_eq!(names, ["nn", "splat", "adam"]);
        assert_eq!(stages[0].1, ProfileEntry { calls: 2, ms: 7.0 });
        assert_eq!(stages[1].1, ProfileEntry { calls: 2, ms: 6.0 });
        let table = p.table(20.0, 2, 2);
        assert!(table.contains("nn.gemm"), "{table}");
        assert!(
            !table.contains("splat.project"),
            "top 2 passes only: {table}"
        );
    }
}
