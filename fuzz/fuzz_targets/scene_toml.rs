#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| tofwave_fuzz::entry::scene_toml(data));
