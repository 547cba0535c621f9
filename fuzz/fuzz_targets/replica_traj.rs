//! Replica `traj.txt`: any text gives poses or an error, never a panic.
#![no_main]
use libfuzzer_sys::fuzz_target;
use std::path::Path;

fuzz_target!(|data: &[u8]| {
    if let Ok(text) = std::str::from_utf8(data) {
        if let Ok(poses) = himap::dataset::replica::parse_traj(text, Path::new("traj.txt")) {
            for p in &poses {
                assert!(p.m.iter().flatten().all(|x| x.is_finite()));
            }
        }
    }
});
