//! `cargo fuzz run npz`: drape_trainer::fuzzing::npz on libFuzzer's inputs.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| drape_trainer::fuzzing::npz(data));
