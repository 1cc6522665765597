#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| mapless_sim::fuzzing::map_files(data));
