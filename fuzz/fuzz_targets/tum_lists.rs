//! TUM `rgb.txt` / `depth.txt` and `groundtruth.txt`: the same text through both parsers.
#![no_main]
use libfuzzer_sys::fuzz_target;
use std::path::Path;

fuzz_target!(|data: &[u8]| {
    if let Ok(text) = std::str::from_utf8(data) {
        let root = Path::new("seq");
        if let Ok(list) = himap::dataset::tum::parse_file_list(text, Path::new("rgb.txt"), root) {
            assert!(list.iter().all(|(t, _)| t.is_finite()));
        }
        if let Ok(gt) = himap::dataset::tum::parse_groundtruth(text, Path::new("groundtruth.txt")) {
            assert!(gt.windows(2).all(|w| w[0].0 <= w[1].0));
            assert!(gt
                .iter()
                .all(|(_, p)| p.m.iter().flatten().all(|x| x.is_finite())));
        }
    }
});
