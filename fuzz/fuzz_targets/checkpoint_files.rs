#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| mapless_learner::fuzzing::checkpoint_files(data));
