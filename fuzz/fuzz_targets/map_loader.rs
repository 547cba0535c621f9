//! The map loader (`map.safetensors`): the file's own configuration sizes the map, so it is
//! checked against the file before anything is allocated.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok((_, map, _)) = himap::mapper_cli::load_map_bytes(data) {
        let n: usize = map.params.iter().map(|p| p.len()).sum();
        assert!(12 * n <= data.len());
    }
});
