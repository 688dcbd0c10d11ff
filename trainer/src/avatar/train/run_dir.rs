//! The run directory's life cycle: what a directory holds before a run starts in it
//! ([`RunState`]), the refusal to start over another run, making a new run's directory,
//! removing what a run that failed before its first checkpoint left, loading the
//! checkpoint a resumed run continues from, and the marker of a finished run.

use std::path::Path;

use drape_engine::Context;

use crate::avatar::checkpoint;
use crate::avatar::config::TrainConfig;
use crate::avatar::model::Avatar;
use crate::avatar::pose_refine::PoseRefiner;
use crate::avatar::report::write_json;
use crate::avatar::run::RunInfo;
use crate::error::TrainerError;

/// The marker a finished run holds (its command run again has nothing to do).
pub const COMPLETE_MARKER: &str = "complete";
/// The note an unfinished run holds (how to continue it).
pub const INCOMPLETE_MARKER: &str = "incomplete";

/// What is in a run directory before a run starts in it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum RunState {
    /// Missing or empty: a new run can start.
    Fresh,
    /// A finished run ([`COMPLETE_MARKER`]).
    Complete,
    /// A run with a checkpoint and no [`COMPLETE_MARKER`]: `--resume` continues it.
    Resumable,
    /// Something else (files that are no drape run, or a run without a checkpoint).
    Occupied,
}

/// The checkpoint a run writes as it goes and resumes from.
pub(super) fn checkpoint_path(out: &Path) -> std::path::PathBuf {
    out.join("checkpoint.npz")
}

/// Classifies `out` (see [`RunState`]).
pub fn run_state(out: &Path) -> crate::Result<RunState> {
    if !out.exists() {
        return Ok(RunState::Fresh);
    }
    if !out.is_dir() {
        return Ok(RunState::Occupied);
    }
    if std::fs::read_dir(out)
        .map_err(|e| TrainerError::io(out, e))?
        .next()
        .is_none()
    {
        return Ok(RunState::Fresh);
    }
    Ok(if out.join(COMPLETE_MARKER).is_file() {
        RunState::Complete
    } else if checkpoint_path(out).is_file() && out.join("config.json").is_file() {
        RunState::Resumable
    } else {
        RunState::Occupied
    })
}

/// Refuses to start a new run in `out` unless it is missing or empty, saying what is
/// there and what to do instead.
pub fn check_fresh(out: &Path) -> crate::Result<()> {
    match run_state(out)? {
        RunState::Fresh => Ok(()),
        RunState::Complete => Err(TrainerError::run(out, "holds a complete run (it has the 'complete' marker); --force trains it again")),
        RunState::Resumable => Err(TrainerError::run(out, format!("holds an unfinished run (see its '{INCOMPLETE_MARKER}'): `drape train --resume {}` continues it; --force starts it again", out.display()))),
        RunState::Occupied => Err(TrainerError::run(out, "exists and is not empty, and is no drape run to resume; choose another --out")),
    }
}

/// Makes a new run's directory: `eval/`, `config.json`, `run.json` where `info` is
/// given (so that `--resume` and the other commands find the data of an unfinished
/// run), and the [`INCOMPLETE_MARKER`] note saying how to continue it.
pub(super) fn make(out: &Path, config: &TrainConfig, info: Option<&RunInfo>) -> crate::Result<()> {
    std::fs::create_dir_all(out.join("eval")).map_err(|e| TrainerError::io(out, e))?;
    write_json(&out.join("config.json"), config)?;
    if let Some(info) = info {
        info.write(out)?;
    }
    let note = out.join(INCOMPLETE_MARKER);
    drape_io::write(&note, format!("this run has not finished; `drape train --resume {}` continues it from checkpoint.npz\n", out.display())).map_err(|e| TrainerError::io(&note, e))
}

/// After a new run failed: before its first checkpoint it leaves nothing (`out` is
/// removed where the run `created` it, emptied where it was there, empty, before);
/// after it, the run stays resumable and nothing is removed.
pub(super) fn clean_up_failed(out: &Path, created: bool) {
    if checkpoint_path(out).exists() {
        return;
    }
    if created {
        let _ = std::fs::remove_dir_all(out);
    } else if let Ok(entries) = std::fs::read_dir(out) {
        for e in entries.flatten() {
            let p = e.path();
            let _ = if p.is_dir() {
                std::fs::remove_dir_all(&p)
            } else {
                std::fs::remove_file(&p)
            };
        }
    }
}

/// Loads the run's checkpoint into `avatar` (and the pose corrections into `refiner`);
/// the step it was taken at.
pub(super) fn resume_from(
    ctx: &Context,
    checkpoint_path: &Path,
    config: &TrainConfig,
    avatar: &mut Avatar,
    refiner: Option<&mut PoseRefiner>,
) -> crate::Result<u32> {
    let state = checkpoint::read(checkpoint_path, &avatar.shapes(), avatar.scene_sh_degree())?;
    if state.step > config.schedule.steps {
        return Err(TrainerError::checkpoint(
            checkpoint_path,
            "step",
            format!(
                "the checkpoint is at step {}, past the run's {} steps (raise --steps)",
                state.step, config.schedule.steps
            ),
        ));
    }
    avatar.restore(ctx, &state)?;
    if let (Some(r), Some(p)) = (refiner, state.poses) {
        r.restore(p)
            .map_err(|e| TrainerError::checkpoint(checkpoint_path, "poses", e.to_string()))?;
    }
    Ok(state.step)
}

/// Marks the run finished: the complete marker written, the incomplete one removed.
pub(super) fn mark_complete(out: &Path, steps: u32) -> crate::Result<()> {
    let marker = out.join(COMPLETE_MARKER);
    drape_io::write(&marker, format!("finished {steps} steps\n"))
        .map_err(|e| TrainerError::io(&marker, e))?;
    let _ = std::fs::remove_file(out.join(INCOMPLETE_MARKER));
    Ok(())
}
