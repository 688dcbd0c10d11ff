//! `cargo fuzz run checkpoint`: drape_trainer::fuzzing::checkpoint on libFuzzer's inputs.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| drape_trainer::fuzzing::checkpoint(data));
