//! Videos in, frames out, through the system's `ffprobe` and `ffmpeg` (Debian's 5.1
//! decodes the H.264 and VP9 of phones and of Pose2Sim's demos).
//!
//! - [`probe`]: the first video stream's size, frame count (packets counted, not the
//!   container's claim), frame rate and display rotation (a phone's portrait video is
//!   stored landscape with a rotation in the container: the `rotate` tag or the display
//!   matrix side data). [`VideoInfo::width`] and `height` are the displayed size, after
//!   the rotation.
//! - [`decode`]: source frames `start <= n < end`, every `every`-th, scaled to
//!   [`output_size`], rotated as displayed (ffmpeg's autorotation), to
//!   `<dir>/<source frame index, 6 digits>.png`. The file names are the source indices
//!   (`setpts=N` before `select`, written with `-frame_pts`), so a frame's name says
//!   which frame of the video it is whatever the selection; checked equal, bit for bit,
//!   to ffmpeg's plain sequential output of the same filter chain
//!   (docs/notes/prepare-footage.md).
//!
//! Scaling keeps the aspect ratio with an even width (`scale=-2:H` rounds the same
//! way), so x and y scale by different factors (1080x1920 to height 128: 72/1080 and
//! 128/1920); the cameras stage scales K per axis from the sizes written here.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use anyhow::{bail, Context as _};

/// What to install when the tools are missing.
const INSTALL: &str = "install ffmpeg (Debian/Ubuntu: apt-get install ffmpeg; macOS: brew install ffmpeg), which provides ffprobe and ffmpeg";

/// One video, as probed.
#[derive(Clone, Debug, PartialEq)]
pub struct VideoInfo {
    pub path: PathBuf,
    /// Displayed size (after the rotation).
    pub width: u32,
    pub height: u32,
    /// Frames in the stream (packets counted).
    pub frames: u64,
    /// Frames per second (the stream's average rate).
    pub fps: f64,
    /// The display rotation in degrees counter-clockwise (0, 90, 180 or 270), as the
    /// container holds it; ffmpeg applies it when decoding.
    pub rotation: u32,
    pub codec: String,
}

/// Runs a tool, turning "not installed" into the line that says what to install.
fn output(tool: &str, args: &[&std::ffi::OsStr]) -> anyhow::Result<std::process::Output> {
    Command::new(tool)
        .args(args)
        .stdin(Stdio::null())
        .output()
        .map_err(|e| match e.kind() {
            std::io::ErrorKind::NotFound => {
                anyhow::anyhow!("{tool} was not found on PATH: {INSTALL}")
            }
            _ => anyhow::anyhow!("{tool} could not be run: {e}"),
        })
}

/// The last non-empty line a tool wrote on stderr (its reason), or a placeholder.
fn last_line(stderr: &[u8]) -> String {
    String::from_utf8_lossy(stderr)
        .lines()
        .rev()
        .map(str::trim)
        .find(|l| !l.is_empty())
        .map_or("no message".into(), str::to_string)
}

/// Probes `path` (module header). An unreadable file, or one with no video stream,
/// is an error naming it.
pub fn probe(path: &Path) -> anyhow::Result<VideoInfo> {
    let shown = path.display();
    if !path.is_file() {
        bail!("{shown}: no such video file");
    }
    let out = output(
        "ffprobe",
        &[
            "-v".as_ref(),
            "error".as_ref(),
            "-select_streams".as_ref(),
            "v:0".as_ref(),
            "-count_packets".as_ref(),
            "-show_streams".as_ref(),
            "-of".as_ref(),
            "json".as_ref(),
            path.as_os_str(),
        ],
    )?;
    if !out.status.success() {
        bail!(
            "{shown}: not a video ffmpeg can read ({})",
            last_line(&out.stderr)
        );
    }
    let json: serde_json::Value = serde_json::from_slice(&out.stdout)
        .with_context(|| format!("{shown}: ffprobe's report is not JSON"))?;
    let Some(stream) = json["streams"].get(0) else {
        bail!("{shown}: no video stream in it");
    };
    parse_stream(path, stream)
}

fn parse_stream(path: &Path, s: &serde_json::Value) -> anyhow::Result<VideoInfo> {
    let shown = path.display();
    let size = |k: &str| {
        s[k].as_u64()
            .filter(|&v| v > 0 && v <= 65_536)
            .map(|v| v as u32)
            .with_context(|| format!("{shown}: the video stream has no usable {k} ({})", s[k]))
    };
    let (w, h) = (size("width")?, size("height")?);
    // Counted packets; the container's nb_frames where counting was not possible.
    let count = |k: &str| s[k].as_str().and_then(|v| v.parse::<u64>().ok());
    let frames = count("nb_read_packets")
        .or_else(|| count("nb_frames"))
        .filter(|&n| n > 0)
        .with_context(|| format!("{shown}: the video stream has no frames"))?;
    let rate = |k: &str| {
        let (n, d) = s[k].as_str()?.split_once('/')?;
        let (n, d): (f64, f64) = (n.parse().ok()?, d.parse().ok()?);
        let r = n / d;
        (r.is_finite() && r > 0.0).then_some(r)
    };
    let fps = rate("avg_frame_rate")
        .or_else(|| rate("r_frame_rate"))
        .unwrap_or(0.0);
    // The display matrix's rotation (ffmpeg 5+: degrees, counter-clockwise positive),
    // else the older `rotate` tag (degrees clockwise). ffmpeg applies it when decoding;
    // here it says whether width and height swap, and is reported.
    let side = s["side_data_list"]
        .as_array()
        .into_iter()
        .flatten()
        .find_map(|d| d["rotation"].as_f64());
    let tag = s["tags"]["rotate"]
        .as_str()
        .and_then(|r| r.parse::<f64>().ok());
    let degrees = side.or(tag).unwrap_or(0.0);
    if !degrees.is_finite() || degrees.rem_euclid(90.0) != 0.0 {
        bail!("{shown}: display rotation {degrees} degrees (only quarter turns are read)");
    }
    let rotation = degrees.rem_euclid(360.0) as u32;
    let (width, height) = if rotation % 180 == 90 { (h, w) } else { (w, h) };
    Ok(VideoInfo {
        path: path.to_path_buf(),
        width,
        height,
        frames,
        fps,
        rotation,
        codec: s["codec_name"].as_str().unwrap_or("?").to_string(),
    })
}

/// Which source frames to keep: `start <= n < end`, every `every`-th from `start`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Selection {
    pub start: u64,
    /// Exclusive; `None`: to the end.
    pub end: Option<u64>,
    pub every: u64,
}

impl Selection {
    /// Parses `A:B`, `A:` or `:B` (source frame indices, B exclusive, as a Python slice).
    pub fn parse_range(s: &str) -> Result<(u64, Option<u64>), String> {
        let (a, b) = s
            .split_once(':')
            .ok_or_else(|| format!("'{s}' is not A:B (frames A up to B, B not included)"))?;
        let num = |t: &str| {
            t.trim()
                .parse::<u64>()
                .map_err(|_| format!("'{t}' in '{s}' is not a frame index"))
        };
        let start = if a.trim().is_empty() { 0 } else { num(a)? };
        let end = if b.trim().is_empty() {
            None
        } else {
            Some(num(b)?)
        };
        if end.is_some_and(|e| e <= start) {
            return Err(format!("'{s}' selects no frame (B must be greater than A)"));
        }
        Ok((start, end))
    }

    /// The source indices this keeps of a video of `frames` frames.
    pub fn indices(&self, frames: u64) -> Vec<u64> {
        let end = self.end.map_or(frames, |e| e.min(frames));
        (self.start..end)
            .step_by(self.every.max(1) as usize)
            .collect()
    }
}

/// The size frames are written at: the displayed size, or scaled to `height` with the
/// width keeping the aspect ratio, rounded to an even number (as `scale=-2:H`).
pub fn output_size(width: u32, height: u32, to_height: Option<u32>) -> (u32, u32) {
    match to_height {
        None => (width, height),
        Some(h) => {
            let w = f64::from(width) * f64::from(h) / f64::from(height);
            let even = ((w / 2.0).round() as u32).max(1) * 2;
            (even, h)
        }
    }
}

/// Decodes the selected frames of `video` at `size` into `dir` (module header) and
/// checks that each expected file is there; returns the indices written.
pub fn decode(
    video: &VideoInfo,
    selection: &Selection,
    size: (u32, u32),
    dir: &Path,
) -> anyhow::Result<Vec<u64>> {
    let want = selection.indices(video.frames);
    if want.is_empty() {
        bail!(
            "{}: --frames {}:{} selects none of its {} frames",
            video.path.display(),
            selection.start,
            selection.end.map_or(String::new(), |e| e.to_string()),
            video.frames
        );
    }
    let last = *want.last().unwrap_or(&0);
    let mut filter = format!(
        "settb=1,setpts=N,select='between(n\\,{}\\,{last})*not(mod(n-{}\\,{}))'",
        selection.start,
        selection.start,
        selection.every.max(1)
    );
    if size != (video.width, video.height) {
        // Area averaging: the frames are shrunk, and area is what a camera would see.
        filter.push_str(&format!(",scale={}:{}:flags=area", size.0, size.1));
    }
    let pattern = dir.join("%06d.png");
    let out = output(
        "ffmpeg",
        &[
            "-nostdin".as_ref(),
            "-v".as_ref(),
            "error".as_ref(),
            "-i".as_ref(),
            video.path.as_os_str(),
            "-vf".as_ref(),
            filter.as_ref(),
            "-fps_mode".as_ref(),
            "passthrough".as_ref(),
            "-enc_time_base".as_ref(),
            "1".as_ref(),
            "-frame_pts".as_ref(),
            "1".as_ref(),
            pattern.as_os_str(),
        ],
    )?;
    if !out.status.success() {
        bail!(
            "{}: ffmpeg could not decode it ({})",
            video.path.display(),
            last_line(&out.stderr)
        );
    }
    let missing: Vec<u64> = want
        .iter()
        .copied()
        .filter(|i| !dir.join(frame_name(*i)).is_file())
        .collect();
    if !missing.is_empty() {
        bail!(
            "{}: ffmpeg decoded fewer frames than the stream holds (missing {} of {}, first {})",
            video.path.display(),
            missing.len(),
            want.len(),
            missing[0]
        );
    }
    Ok(want)
}

/// A frame's file name: its source index, 6 digits.
pub fn frame_name(index: u64) -> String {
    format!("{index:06}.png")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ranges_parse_as_python_slices() {
        assert_eq!(Selection::parse_range("0:6"), Ok((0, Some(6))));
        assert_eq!(Selection::parse_range("10:"), Ok((10, None)));
        assert_eq!(Selection::parse_range(":5"), Ok((0, Some(5))));
        assert!(Selection::parse_range("6:6").is_err());
        assert!(Selection::parse_range("7").is_err());
        assert!(Selection::parse_range("a:3").is_err());
        let s = Selection {
            start: 0,
            end: Some(6),
            every: 3,
        };
        assert_eq!(s.indices(100), [0, 3]);
        assert_eq!(s.indices(4), [0, 3]);
        let tail = Selection {
            start: 95,
            end: None,
            every: 2,
        };
        assert_eq!(tail.indices(100), [95, 97, 99]);
    }

    #[test]
    fn scaled_widths_are_even_as_ffmpeg_rounds_them() {
        // ffmpeg's scale=-2:540 gave 304x540 from 1080x1920 and 306x540 from 1088x1920
        // (docs/notes/prepare-footage.md).
        assert_eq!(output_size(1080, 1920, Some(540)), (304, 540));
        assert_eq!(output_size(1088, 1920, Some(540)), (306, 540));
        assert_eq!(output_size(1080, 1920, Some(128)), (72, 128));
        assert_eq!(output_size(1080, 1920, None), (1080, 1920));
    }

    #[test]
    fn rotation_swaps_the_displayed_size() {
        let s = serde_json::json!({
            "codec_name": "h264", "width": 64, "height": 32,
            "avg_frame_rate": "30000/1001", "nb_read_packets": "6",
            "side_data_list": [{"side_data_type": "Display Matrix", "rotation": -90}]
        });
        let v = parse_stream(Path::new("phone.mp4"), &s).unwrap();
        assert_eq!((v.width, v.height, v.rotation, v.frames), (32, 64, 270, 6));
        assert!((v.fps - 29.97).abs() < 0.01);
        let tagged = serde_json::json!({
            "width": 64, "height": 32, "r_frame_rate": "10/1", "nb_frames": "3",
            "tags": {"rotate": "180"}
        });
        let v = parse_stream(Path::new("upside.mp4"), &tagged).unwrap();
        assert_eq!((v.width, v.height, v.rotation), (64, 32, 180));
        let odd = serde_json::json!({"width": 64, "height": 32, "nb_frames": "3",
            "side_data_list": [{"rotation": 45}]});
        let e = parse_stream(Path::new("odd.mp4"), &odd)
            .unwrap_err()
            .to_string();
        assert!(e.contains("odd.mp4") && e.contains("45"), "{e}");
    }
}
