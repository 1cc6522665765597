#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| mapless_cli::fuzzing::episode_stats(data));
