//! `cargo fuzz run config_toml`: drape_trainer::fuzzing::config_toml on libFuzzer's inputs.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| drape_trainer::fuzzing::config_toml(data));
