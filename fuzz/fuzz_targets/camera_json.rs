//! `cargo fuzz run camera_json`: drape_trainer::fuzzing::camera_json on libFuzzer's inputs.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| drape_trainer::fuzzing::camera_json(data));
