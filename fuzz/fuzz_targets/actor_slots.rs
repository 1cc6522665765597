#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| mapless_replay::fuzzing::actor_slots(data));
