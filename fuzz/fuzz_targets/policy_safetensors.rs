#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| mapless_actor::fuzzing::policy_safetensors(data));
