#![no_main]
//! Fuzz target: see cao_xr::fuzzing::dicom (never panics; what it accepts is whole).

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = cao_xr::fuzzing::dicom(data);
});
