//! PLY reading (ASCII and binary): a mesh whose faces all index its vertices, or an error.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(mesh) = himap::mesh::ply::read_ply_from(data) {
        let nv = mesh.vertices.len();
        assert!(mesh.faces.iter().flatten().all(|&i| (i as usize) < nv));
        assert!(mesh.colors.as_ref().is_none_or(|c| c.len() == nv));
    }
});
