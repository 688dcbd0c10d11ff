//! `cargo fuzz run ply`: drape_trainer::fuzzing::ply on libFuzzer's inputs.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| drape_trainer::fuzzing::ply(data));
