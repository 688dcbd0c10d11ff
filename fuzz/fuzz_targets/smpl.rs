//! `cargo fuzz run smpl`: drape_trainer::fuzzing::smpl on libFuzzer's inputs.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| drape_trainer::fuzzing::smpl(data));
