//! `cargo fuzz run motion`: drape_trainer::fuzzing::motion on libFuzzer's inputs.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| drape_trainer::fuzzing::motion(data));
