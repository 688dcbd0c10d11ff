//! Frame statistics: the frame rate and the GPU time per scope the window's title shows
//! while the viewer runs, and the summary line it prints at the end (the rate from the
//! first frame's start, the steady rate after the first frame, the mean GPU busy time).

use std::time::Instant;

use drape_engine::PassTimings;

/// Times and counts of the frames rendered so far.
pub(super) struct Stats {
    started: Instant,
    /// The title's window: since when, and how many frames in it.
    title_at: Instant,
    title_frames: u64,
    /// The latest completed frame's GPU timings.
    timings: Option<PassTimings>,
    busy_ms_sum: f64,
    busy_count: u64,
    /// The end of the first and of the latest rendered frame (not the --screenshot hold).
    first_frame_at: Option<Instant>,
    last_frame_at: Instant,
}

impl Stats {
    pub(super) fn new(now: Instant) -> Self {
        Self {
            started: now,
            title_at: now,
            title_frames: 0,
            timings: None,
            busy_ms_sum: 0.0,
            busy_count: 0,
            first_frame_at: None,
            last_frame_at: now,
        }
    }

    /// The GPU timings of a completed frame, if the engine had them.
    pub(super) fn record_timings(&mut self, timings: Option<PassTimings>) {
        if let Some(t) = timings {
            self.busy_ms_sum += t.busy_ms();
            self.busy_count += 1;
            self.timings = Some(t);
        }
    }

    /// A frame rendered and presented.
    pub(super) fn frame_done(&mut self) {
        self.title_frames += 1;
        // The rate counts from the end of the first frame (start-up and first-use costs out).
        let now = Instant::now();
        self.first_frame_at.get_or_insert(now);
        self.last_frame_at = now;
    }

    /// The window's title, at most every half second (None in between): FPS, GPU time
    /// per scope, motion frame `k` of `n`.
    pub(super) fn title(&mut self, k: usize, n: usize, paused: bool) -> Option<String> {
        let elapsed = self.title_at.elapsed().as_secs_f64();
        if elapsed < 0.5 {
            return None;
        }
        let fps = self.title_frames as f64 / elapsed;
        self.title_at = Instant::now();
        self.title_frames = 0;
        let gpu = match &self.timings {
            Some(t) => {
                let scopes: Vec<String> = t
                    .by_scope()
                    .iter()
                    .map(|(s, ms)| format!("{s} {ms:.1}"))
                    .collect();
                format!("GPU {:.1} ms ({})", t.busy_ms(), scopes.join(", "))
            }
            None => "GPU -".into(),
        };
        let paused = if paused { " [paused]" } else { "" };
        Some(format!(
            "drape view | {fps:.1} FPS | {gpu} | frame {}/{n}{paused}",
            k + 1
        ))
    }

    /// The line `drape view` prints at the end, for `frames` frames rendered at
    /// `width` x `height` on `device` with `in_flight` frames in flight.
    pub(super) fn summary(
        &self,
        frames: u64,
        (width, height): (u32, u32),
        device: &str,
        in_flight: usize,
    ) -> String {
        // Up to the last rendered frame (not the --screenshot hold).
        let secs = self
            .last_frame_at
            .duration_since(self.started)
            .as_secs_f64();
        let steady = match self.first_frame_at {
            Some(t) if frames > 1 => format!(
                ", {:.2} FPS after the first",
                (frames - 1) as f64 / self.last_frame_at.duration_since(t).as_secs_f64().max(1e-9)
            ),
            _ => String::new(),
        };
        let gpu = if self.busy_count > 0 {
            format!(
                ", GPU busy {:.1} ms per frame",
                self.busy_ms_sum / self.busy_count as f64
            )
        } else {
            String::new()
        };
        format!("view: {frames} frames at {width}x{height} on {device} ({in_flight} frames in flight): {:.2} FPS over {:.1} s from the first frame's start{steady}{gpu}", frames as f64 / secs.max(1e-9), secs)
    }
}
