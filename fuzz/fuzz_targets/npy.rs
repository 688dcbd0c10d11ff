//! `cargo fuzz run npy`: drape_trainer::fuzzing::npy on libFuzzer's inputs.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| drape_trainer::fuzzing::npy(data));
