//! The screenshot protocol of `--frames N --screenshot S.png`: after the last frame, the
//! library's render of that frame (`AvatarPlayer::render`, over black) is written to
//! S.png and `S.png.ready` is created; the viewer then keeps presenting the last frame
//! until `S.png.done` appears (or [`HOLD_TIMEOUT`] passes), so that a test can capture
//! the X window and compare the two.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::{anyhow, Context as _};
use drape_trainer::avatar::player::{AvatarPlayer, ViewCamera};

/// How long `--screenshot` keeps the window up waiting for `S.png.done`.
const HOLD_TIMEOUT: Duration = Duration::from_secs(30);

/// `--screenshot`'s state.
pub(super) struct Capture {
    /// S.png.
    shot: PathBuf,
    /// Since when the last frame is written and held (None while frames still render).
    holding: Option<Instant>,
}

impl Capture {
    pub(super) fn new(shot: PathBuf) -> Self {
        Self {
            shot,
            holding: None,
        }
    }

    /// Whether the screenshot is written and the last frame is being held.
    pub(super) fn holding(&self) -> bool {
        self.holding.is_some()
    }

    /// While holding: whether to stop, because `.done` exists or the hold timed out
    /// (which it reports).
    pub(super) fn hold_over(&self) -> bool {
        let Some(since) = self.holding else {
            return false;
        };
        if marker(&self.shot, "done").exists() {
            return true;
        }
        if since.elapsed() > HOLD_TIMEOUT {
            eprintln!(
                "view: {} did not appear within {} s; exiting",
                marker(&self.shot, "done").display(),
                HOLD_TIMEOUT.as_secs()
            );
            return true;
        }
        false
    }

    /// Writes the library's render of the player's current frame from `cam` and the
    /// `.ready` marker, and starts holding.
    pub(super) fn write_and_hold(
        &mut self,
        player: &mut AvatarPlayer,
        cam: &ViewCamera,
        width: u32,
        height: u32,
    ) -> anyhow::Result<()> {
        let rgba = player.render(cam, width, height)?;
        write_png16(&self.shot, width, height, &rgba)?;
        drape_io::write(marker(&self.shot, "ready"), b"")
            .with_context(|| format!("{}", marker(&self.shot, "ready").display()))?;
        eprintln!(
            "view: wrote {}; presenting the last frame until {} exists",
            self.shot.display(),
            marker(&self.shot, "done").display()
        );
        self.holding = Some(Instant::now());
        Ok(())
    }
}

fn marker(shot: &Path, what: &str) -> PathBuf {
    let mut s = shot.as_os_str().to_os_string();
    s.push(format!(".{what}"));
    PathBuf::from(s)
}

/// Premultiplied RGBA floats (over black: the colour as it is) as a 16-bit RGB PNG.
fn write_png16(path: &Path, w: u32, h: u32, rgba: &[f32]) -> anyhow::Result<()> {
    let mut data = Vec::with_capacity(3 * (w * h) as usize);
    for px in rgba.chunks_exact(4) {
        for &c in &px[..3] {
            data.push((c.clamp(0.0, 1.0) * 65535.0).round() as u16);
        }
    }
    let img = image::ImageBuffer::<image::Rgb<u16>, _>::from_raw(w, h, data)
        .ok_or_else(|| anyhow!("screenshot: {} floats for {w}x{h}", rgba.len()))?;
    img.save(path)
        .with_context(|| format!("writing {}", path.display()))?;
    Ok(())
}
