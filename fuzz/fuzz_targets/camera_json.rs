//! Replica `cam_params.json`: a camera that passes is one every image buffer can be sized from.
#![no_main]
use libfuzzer_sys::fuzz_target;
use std::path::Path;

fuzz_target!(|data: &[u8]| {
    if let Ok(text) = std::str::from_utf8(data) {
        let path = Path::new("cam_params.json");
        if let Ok((k, scale)) = himap::dataset::replica::parse_cam_params(text, path) {
            assert!(k.width >= 1 && k.width <= himap::dataset::MAX_IMAGE_SIDE);
            assert!(k.height >= 1 && k.height <= himap::dataset::MAX_IMAGE_SIDE);
            assert!(k.fx > 0.0 && k.fy > 0.0 && k.cx.is_finite() && k.cy.is_finite());
            assert!(scale.is_none_or(|s| s.is_finite() && s > 0.0));
        }
    }
});
