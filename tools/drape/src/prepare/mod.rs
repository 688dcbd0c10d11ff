//! `drape prepare VIDEO... --out DIR`: from a person's videos to a sequence drape
//! trains on, in stages whose outputs a user can look at and rerun from (issue 55).
//! Built so far: the five stages for a calibrated rig of two views or more; one view
//! (the assumed lens, SfM, a monocular fit) stops at the body stage with an error.
//!
//! Stages, in order, each writing under `DIR`:
//! 1. `frames`: each video decoded (`frames`: ffmpeg) to
//!    `frames/<camera>/<source frame index, 6 digits>.png`, `--frames A:B` (B not
//!    included), every `--every`-th, scaled to `--height`, rotated as displayed.
//! 2. `cameras`: the `--calibration` (a Qualisys `.qca.txt` or a Pose2Sim / Sports2D
//!    `Calib*.toml`: `drape_trainer::dataset::calibration`) matched to the videos and
//!    scaled to the frames, written as `cameras.json` (its format: [`cameras`]). Without
//!    a calibration this stage writes nothing (one static camera's assumed lens and SfM
//!    for a moving one are not built yet).
//! 3. `landmarks`: mediapipe's person mask and 33 landmarks per frame,
//!    `landmarks/<camera>/` (`masks/*.png`, `landmarks.npy`, `world_landmarks.npy`,
//!    `detected.npy`, `frames.txt`: `tools/drape/python/landmarks.py`'s outputs), run in
//!    the environment `scripts/prepare-env.sh` makes once (mediapipe 0.10.21 under
//!    `target/prepare-venv`, or `$DRAPE_PREPARE_VENV`).
//! 4. `body`: the landmarks triangulated across the calibrated views and drape's
//!    SMPL-format body (with limb lengths) fitted to them, `body/` (`landmarks3d.npy`,
//!    `smpl_params.npz`, `body_model.npz`, `report.json`: [`body`]). Needs
//!    `cameras.json` and two views or more.
//! 5. `sequence`: the frames, masks, cameras and body as one ZJU-MoCap sequence in the
//!    refined layout, `sequence/` ([`sequence`]), which `drape inspect DIR` and `drape
//!    train --data DIR` read.
//!
//! Inputs are all checked before anything is written (the calibration read and
//! matched, every video probed): a bad one is one `error:` line naming the file, and
//! `DIR` is not created. `DIR` must be missing, empty, or an earlier `drape prepare`
//! output (it has `prepare.json`, the record of the last run's arguments).
//!
//! Each stage's output is written whole (a directory per camera through
//! `drape_io::StagedDir`, `cameras.json` through `drape_io::write`) with a stamp of what
//! made it (`stage.json` in the directory; `cameras.json` records its inputs itself). A
//! rerun skips a stage whose stamp matches its inputs; `--redo STAGE` runs that stage
//! and those after it again; `--until STAGE` stops after it. Progress goes to stderr.

mod body;
mod cameras;
mod frames;
mod landmarks;
mod sequence;
mod sheet;
mod triangulate;

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context as _};
use clap::{Args, ValueEnum};
use drape_trainer::dataset::calibration::{self, Calibration};
use serde_json::json;

use frames::{Selection, VideoInfo};

/// The stages, in order.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, ValueEnum)]
pub enum Stage {
    Frames,
    Cameras,
    Landmarks,
    Body,
    Sequence,
}

impl Stage {
    fn name(self) -> &'static str {
        match self {
            Self::Frames => "frames",
            Self::Cameras => "cameras",
            Self::Landmarks => "landmarks",
            Self::Body => "body",
            Self::Sequence => "sequence",
        }
    }
}

#[derive(Args, Debug, Clone)]
#[command(after_long_help = "\
Stages (each writes under DIR, is skipped on a rerun when its stamp matches, and can be \
rerun with --redo):
  frames     DIR/frames/<camera>/<source frame, 6 digits>.png  (ffmpeg, installed separately)
  cameras    DIR/cameras.json  (with --calibration; K scaled to the frames)
  landmarks  DIR/landmarks/<camera>/  person masks and 33 landmarks per frame (mediapipe, in a
             Python environment scripts/prepare-env.sh makes once, about 400 MB)
  body       DIR/body/  landmarks triangulated across the views, the body (limb lengths, \
             per-frame pose) fitted to them, report.json of the reprojection errors \
             (needs --calibration and two views or more)
  sequence   DIR/sequence/  a ZJU-MoCap sequence (zju-refined): annots.npy, images/, mask/, \
             smpl_params/, body_model.npz; drape inspect DIR and drape train --data DIR read it
Not built yet: garment masks (drape train then has no cloth layer, and says so), one video \
(an assumed lens or SfM, and a fit to one view's landmarks).

Example (Pose2Sim's demo; scripts/pose2sim-footage.sh fetches it):
  drape prepare Demo_SinglePerson/videos/cam01.mp4 Demo_SinglePerson/videos/cam03.mp4 \\
      --calibration Demo_SinglePerson/calibration/Calib.qca.txt --frames 0:60 --every 2 \\
      --height 540 --out prepared/
  drape train --data prepared/ --train-cameras 0 --test-cameras 1 --out run/")]
pub struct PrepareArgs {
    /// The videos: several synchronised views of a calibrated rig (one per camera; named
    /// after their cameras, as cam01.mp4, or given in the calibration's order), or one
    /// video.
    #[arg(required = true, value_name = "VIDEO")]
    pub videos: Vec<PathBuf>,
    /// The output directory: missing, empty, or an earlier `drape prepare` output.
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
    /// The rig's calibration: a Qualisys .qca.txt (converted as Pose2Sim does) or a
    /// Pose2Sim / Sports2D Calib*.toml. Cameras are matched to videos by name, else
    /// in order.
    #[arg(long, value_name = "FILE")]
    pub calibration: Option<PathBuf>,
    /// The Qualisys binning factor (2 when a 1080p sensor filmed 540p); a TOML
    /// ignores it.
    #[arg(long, default_value_t = 1, value_name = "B", value_parser = clap::value_parser!(u32).range(1..=16))]
    pub qca_binning: u32,
    /// Source frames A up to B (B not included; `A:` to the end), by index in the video.
    #[arg(long, value_name = "A:B", value_parser = Selection::parse_range)]
    pub frames: Option<(u64, Option<u64>)>,
    /// Keep every N-th frame of the range.
    #[arg(long, default_value_t = 1, value_name = "N", value_parser = clap::value_parser!(u64).range(1..=100_000))]
    pub every: u64,
    /// Scale frames to this height in pixels (the width keeps the aspect ratio, rounded
    /// to even); the default keeps the video's size.
    #[arg(long, value_name = "H", value_parser = clap::value_parser!(u32).range(16..=8192))]
    pub height: Option<u32>,
    /// Whom to follow when several people are in view: `auto` (the one person the
    /// detector finds; one person in view) or a person's number (not built yet).
    #[arg(long, default_value = "auto", value_name = "auto|N")]
    pub person: String,
    /// Run this stage and the ones after it again, even where their stamps match.
    #[arg(long, value_enum, value_name = "STAGE")]
    pub redo: Option<Stage>,
    /// Stop after this stage (exit 0).
    #[arg(long, value_enum, value_name = "STAGE")]
    pub until: Option<Stage>,
}

/// The record of this run that marks `DIR` as prepare's output.
const RECORD: &str = "prepare.json";

fn progress(line: &str) {
    eprintln!("prepare: {line}");
}

/// One camera's inputs, checked: its name (the calibration's, else the video's stem),
/// its video and the size its frames are written at.
struct View {
    name: String,
    video: VideoInfo,
    size: (u32, u32),
}

pub fn run(args: &PrepareArgs) -> anyhow::Result<()> {
    // Everything is checked before DIR is touched.
    if args.person != "auto" {
        match args.person.parse::<u32>() {
            Ok(_) => bail!("--person {}: choosing among several people is not built yet (one person in view: --person auto)", args.person),
            Err(_) => bail!("--person {}: must be auto or a person's number", args.person),
        }
    }
    let calibration: Option<(PathBuf, Calibration)> = match &args.calibration {
        Some(file) => Some((file.clone(), calibration::read(file, args.qca_binning)?)),
        None => None,
    };
    let mut videos = Vec::new();
    for path in &args.videos {
        let info = frames::probe(path)?;
        progress(&format!(
            "{}: {}x{}, {} frames at {:.2} fps, {}{}",
            path.display(),
            info.width,
            info.height,
            info.frames,
            info.fps,
            info.codec,
            if info.rotation == 0 {
                String::new()
            } else {
                format!(", rotated {} degrees as displayed", info.rotation)
            }
        ));
        videos.push(info);
    }
    let (start, end) = args.frames.unwrap_or((0, None));
    let selection = Selection {
        start,
        end,
        every: args.every,
    };
    for v in &videos {
        if selection.indices(v.frames).is_empty() {
            bail!(
                "{}: --frames {start}:{} selects none of its {} frames",
                v.path.display(),
                end.map_or(String::new(), |e| e.to_string()),
                v.frames
            );
        }
    }
    // The calibration's camera for each video, and its camera at the frames' size.
    let sizes: Vec<(u32, u32)> = videos
        .iter()
        .map(|v| frames::output_size(v.width, v.height, args.height))
        .collect();
    let fitted = match &calibration {
        Some((file, cal)) => {
            let rigs = cameras::match_videos(cal, file, &videos)?;
            let mut out = Vec::new();
            for ((rig, video), size) in rigs.into_iter().zip(&videos).zip(&sizes) {
                out.push((rig, cameras::fit(rig, file, video, *size)?));
            }
            Some(out)
        }
        None => None,
    };
    let names: Vec<String> = match &fitted {
        Some(f) => f.iter().map(|(rig, _)| rig.name.clone()).collect(),
        None => stems(&videos),
    };
    let views: Vec<View> = names
        .into_iter()
        .zip(videos)
        .zip(sizes)
        .map(|((name, video), size)| View { name, video, size })
        .collect();
    let out = &args.out;
    open_output(out)?;

    let redo = |stage: Stage| args.redo.is_some_and(|r| r <= stage);
    let stop = |stage: Stage| {
        let done = args.until == Some(stage);
        if done {
            progress(&format!("stopped after {} (--until)", stage.name()));
        }
        done
    };

    // 1. frames
    let mut frame_keys = Vec::new();
    for view in &views {
        frame_keys.push(frames_stage(out, view, &selection, redo(Stage::Frames))?);
    }
    if stop(Stage::Frames) {
        return Ok(());
    }

    // 2. cameras
    match (&calibration, &fitted) {
        (Some((file, cal)), Some(fitted)) => {
            for (_, f) in fitted {
                if let Some(w) = &f.warning {
                    eprintln!("{w}");
                }
            }
            let list: Vec<_> = fitted
                .iter()
                .zip(&views)
                .map(|((rig, f), view)| (*rig, &view.video, f))
                .collect();
            let doc = cameras::document(cal, file, &list);
            let path = out.join("cameras.json");
            // Compared as text: the document is written the same way each time (and
            // serde_json's parser does not promise to round-trip every float).
            let text = serde_json::to_string_pretty(&doc)? + "\n";
            if std::fs::read(&path).ok().as_deref() == Some(text.as_bytes()) && !redo(Stage::Cameras) {
                progress("cameras: cameras.json is up to date (skipped)");
            } else {
                drape_io::write(&path, text)
                    .with_context(|| format!("{}", path.display()))?;
                progress(&format!(
                    "cameras: {} cameras from {} ({}) to {}",
                    list.len(),
                    file.display(),
                    cal.format,
                    path.display()
                ));
            }
        }
        _ => progress("cameras: no --calibration, so no cameras.json (the assumed lens of one static camera and SfM for a moving one are not built yet)"),
    }
    if stop(Stage::Cameras) {
        return Ok(());
    }

    // 3. landmarks
    landmarks::stage(out, &views, &frame_keys, redo(Stage::Landmarks))?;
    if stop(Stage::Landmarks) {
        return Ok(());
    }
    // 4. body
    let names: Vec<String> = views.iter().map(|v| v.name.clone()).collect();
    body::stage(out, &names, redo(Stage::Body))?;
    if stop(Stage::Body) {
        return Ok(());
    }
    // 5. sequence
    sequence::stage(out, &names, redo(Stage::Sequence))?;
    progress(&format!(
        "done: {} is a sequence (drape inspect {0}; drape train --data {0})",
        out.display()
    ));
    Ok(())
}

/// Names for views without a calibration: the videos' file stems, numbered where two
/// are the same.
fn stems(videos: &[VideoInfo]) -> Vec<String> {
    let raw: Vec<String> = videos
        .iter()
        .map(|v| {
            v.path
                .file_stem()
                .and_then(|s| s.to_str())
                .filter(|s| {
                    !s.is_empty()
                        && s.chars()
                            .all(|c| c.is_ascii_alphanumeric() || "-_.".contains(c))
                })
                .unwrap_or("view")
                .to_string()
        })
        .collect();
    raw.iter()
        .enumerate()
        .map(|(i, s)| {
            if raw.iter().filter(|o| *o == s).count() > 1 {
                format!("{s}-{}", i + 1)
            } else {
                s.clone()
            }
        })
        .collect()
}

/// Refuses a `DIR` that is no earlier prepare output, then records this run's
/// arguments in it.
fn open_output(out: &Path) -> anyhow::Result<()> {
    if out.exists() {
        if !out.is_dir() {
            bail!("--out {}: exists and is not a directory", out.display());
        }
        let empty = std::fs::read_dir(out)
            .with_context(|| format!("--out {}: cannot read", out.display()))?
            .next()
            .is_none();
        if !empty && !out.join(RECORD).is_file() {
            bail!(
                "--out {}: exists, is not empty and is no earlier drape prepare output (it has no {RECORD}); choose another directory",
                out.display()
            );
        }
    }
    std::fs::create_dir_all(out)
        .with_context(|| format!("--out {}: cannot create", out.display()))?;
    let record = json!({
        "command": "drape prepare",
        "version": env!("CARGO_PKG_VERSION"),
        "arguments": std::env::args().skip(1).collect::<Vec<_>>(),
    });
    drape_io::write(
        out.join(RECORD),
        serde_json::to_string_pretty(&record)? + "\n",
    )
    .with_context(|| format!("--out {}", out.display()))?;
    Ok(())
}

/// What a stage's output was made from: equal stamps, equal outputs.
fn read_stamp(dir: &Path) -> Option<serde_json::Value> {
    let bytes = std::fs::read(dir.join("stage.json")).ok()?;
    serde_json::from_slice::<serde_json::Value>(&bytes).ok()
}

/// Writes a stage's stamp (`stage.json`, the inputs that made it) into its staged
/// directory and commits the directory whole: what [`read_stamp`] compares on a rerun.
fn commit_stage(
    staged: drape_io::StagedDir,
    dir: &Path,
    key: &serde_json::Value,
) -> anyhow::Result<()> {
    drape_io::write(
        staged.path().join("stage.json"),
        serde_json::to_string_pretty(key)? + "\n",
    )?;
    staged
        .commit()
        .with_context(|| format!("{}", dir.display()))?;
    Ok(())
}

/// The frames of one view: skipped when `frames/<name>/stage.json` matches.
fn frames_stage(
    out: &Path,
    view: &View,
    selection: &Selection,
    redo: bool,
) -> anyhow::Result<serde_json::Value> {
    let dir = out.join("frames").join(&view.name);
    let meta = std::fs::metadata(&view.video.path)
        .with_context(|| format!("{}", view.video.path.display()))?;
    let modified = meta
        .modified()
        .ok()
        .and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok())
        .map_or(0, |d| d.as_nanos() as u64);
    let indices = selection.indices(view.video.frames);
    let key = json!({
        "video": view.video.path.canonicalize().unwrap_or(view.video.path.clone()).display().to_string(),
        "video_bytes": meta.len(),
        "video_modified_ns": modified,
        "start": selection.start,
        "end": selection.end,
        "every": selection.every,
        "size": [view.size.0, view.size.1],
        "rotation": view.video.rotation,
        "frames": indices,
    });
    if !redo && read_stamp(&dir).is_some_and(|s| s == key) {
        progress(&format!(
            "frames: {}: {} frames up to date (skipped)",
            view.name,
            indices.len()
        ));
        return Ok(key);
    }
    let t0 = Instant::now();
    let staged = drape_io::StagedDir::new(&dir).with_context(|| format!("{}", dir.display()))?;
    let written = frames::decode(&view.video, selection, view.size, staged.path())?;
    commit_stage(staged, &dir, &key)?;
    progress(&format!(
        "frames: {}: {} frames ({}..{}) at {}x{} to {} in {:.1} s",
        view.name,
        written.len(),
        written.first().unwrap_or(&0),
        written.last().unwrap_or(&0),
        view.size.0,
        view.size.1,
        dir.display(),
        t0.elapsed().as_secs_f64()
    ));
    Ok(key)
}
