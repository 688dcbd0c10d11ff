//! `cargo fuzz run colmap`: drape_trainer::fuzzing::colmap on libFuzzer's inputs.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| drape_trainer::fuzzing::colmap(data));
