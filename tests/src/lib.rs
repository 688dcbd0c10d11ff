//! Helpers shared by the cross-crate tests: a validated GPU context that fails the
//! test that caused any validation message, and input patterns.
#![forbid(unsafe_code)]

use std::ops::Deref;
use std::sync::Arc;

use drape_engine::validation::ValidationSink;
use drape_engine::{Context, ContextDesc};
use rand::{Rng, SeedableRng};

/// A context with validation on and poisoned buffers. When it is dropped (after every
/// buffer made from it, if declared first), it fails the test on any validation
/// message, including those of device and instance destruction.
pub struct TestGpu {
    ctx: Option<Context>,
    sink: Arc<ValidationSink>,
}

/// Opens the test device (lavapipe in CI; `DRAPE_DEVICE` overrides).
pub fn gpu() -> TestGpu {
    let ctx = Context::new(&ContextDesc::for_tests()).unwrap_or_else(|e| panic!("opening the test device: {e}"));
    let sink = ctx.validation_sink().expect("tests always run with validation");
    TestGpu { ctx: Some(ctx), sink }
}

impl Deref for TestGpu {
    type Target = Context;
    fn deref(&self) -> &Context {
        self.ctx.as_ref().expect("context present until drop")
    }
}

impl Drop for TestGpu {
    fn drop(&mut self) {
        drop(self.ctx.take());
        let messages = self.sink.drain();
        if !messages.is_empty() && !std::thread::panicking() {
            panic!("{} validation message(s):\n{}", messages.len(), messages.join("\n"));
        }
    }
}

/// Input orders every GPU op is tested on.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Pattern {
    Random,
    AllEqual,
    Sorted,
    ReverseSorted,
}

impl Pattern {
    pub const ALL: [Pattern; 4] = [Pattern::Random, Pattern::AllEqual, Pattern::Sorted, Pattern::ReverseSorted];

    /// `len` values below 2^bits (all 32 bits for 32) in this pattern, reproducible
    /// from `seed`.
    pub fn generate(self, len: usize, bits: u32, seed: u64) -> Vec<u32> {
        let mask = if bits >= 32 { u32::MAX } else { (1u32 << bits) - 1 };
        let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
        let mut v: Vec<u32> = match self {
            Pattern::AllEqual => vec![0x5A5A_5A5A & mask; len],
            _ => (0..len).map(|_| rng.random::<u32>() & mask).collect(),
        };
        match self {
            Pattern::Sorted => v.sort_unstable(),
            Pattern::ReverseSorted => v.sort_unstable_by(|a, b| b.cmp(a)),
            Pattern::Random | Pattern::AllEqual => {}
        }
        v
    }
}
