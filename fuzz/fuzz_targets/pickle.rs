//! `cargo fuzz run pickle`: drape_trainer::fuzzing::pickle on libFuzzer's inputs.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| drape_trainer::fuzzing::pickle(data));
