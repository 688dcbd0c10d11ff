//! `cargo fuzz run obj`: drape_trainer::fuzzing::obj on libFuzzer's inputs.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| drape_trainer::fuzzing::obj(data));
