//! What a run reports as it goes: its progress events, and its JSON files, each written
//! whole.

use std::path::Path;

use crate::error::TrainerError;

/// Progress of a run, for a progress line.
#[derive(Clone, Debug)]
pub enum Progress {
    Fit {
        layer: String,
        step: u32,
        total: u32,
        mse: f64,
    },
    Step {
        step: u32,
        total: u32,
        l1: f64,
        psnr: f64,
        it_per_s: f64,
    },
    Eval {
        done: usize,
        total: usize,
    },
    /// Simulating the garments through the sequence (frames, settling ones included).
    Simulate {
        done: usize,
        total: usize,
    },
    /// The layers were densified and pruned after `step` steps: (layer, before, after).
    Densify {
        step: u32,
        counts: Vec<(String, usize, usize)>,
    },
}

/// Writes `value` as pretty JSON to `path`.
pub(crate) fn write_json(path: &Path, value: &impl serde::Serialize) -> crate::Result<()> {
    let text = serde_json::to_string_pretty(value).map_err(|e| TrainerError::io(path, e.into()))?;
    drape_io::write(path, text + "\n").map_err(|e| TrainerError::io(path, e))
}
