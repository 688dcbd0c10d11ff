//! `cargo fuzz run image`: drape_trainer::fuzzing::image on libFuzzer's inputs.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| drape_trainer::fuzzing::image(data));
