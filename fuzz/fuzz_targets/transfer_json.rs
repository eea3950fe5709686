#![no_main]
//! Fuzz target: see cao_xr::fuzzing::transfer_json (never panics; what it accepts is whole).

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = cao_xr::fuzzing::transfer_json(data);
});
