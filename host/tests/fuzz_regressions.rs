//! Inputs the fuzz targets (`fuzz/`) found crashing, replayed through the same readers with the
//! same checks: each must give a value that holds the target's invariants or an error, never a
//! panic. One folder per target under `tests/fuzz-regressions/`; a new crash is added by
//! copying its artifact there.

use std::path::{Path, PathBuf};

fn inputs(target: &str) -> Vec<(PathBuf, Vec<u8>)> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fuzz-regressions")
        .join(target);
    let mut out: Vec<_> = match std::fs::read_dir(&dir) {
        Ok(entries) => entries
            .map(|e| e.unwrap().path())
            .map(|p| {
                let bytes = std::fs::read(&p).unwrap();
                (p, bytes)
            })
            .collect(),
        Err(_) => Vec::new(),
    };
    out.sort();
    out
}

#[test]
fn ply_regressions_are_errors_or_consistent_meshes() {
    let all = inputs("ply");
    assert!(!all.is_empty(), "the ply regression inputs are missing");
    for (path, bytes) in all {
        match himap::mesh::ply::read_ply_from(bytes.as_slice()) {
            Ok(mesh) => {
                let nv = mesh.vertices.len();
                assert!(
                    mesh.faces.iter().flatten().all(|&i| (i as usize) < nv),
                    "{}",
                    path.display()
                );
                assert!(
                    mesh.colors.as_ref().is_none_or(|c| c.len() == nv),
                    "{}: {nv} vertices, {:?} colours",
                    path.display(),
                    mesh.colors.as_ref().map(|c| c.len())
                );
            }
            Err(e) => assert!(!format!("{e:#}").is_empty()),
        }
    }
}

/// The first crash (fuzz target `ply`, 2026-12-01): a header with two `vertex` elements; the
/// second one's vertices were appended while its colours replaced the first one's, so the mesh
/// had 396 vertices and 392 colours.
#[test]
fn two_vertex_elements_are_refused() {
    let text = "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n\
        property float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\n\
        element vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n\
        0 0 0 1 2 3\n1 1 1\n";
    let e = himap::mesh::ply::read_ply_from(text.as_bytes()).unwrap_err();
    assert!(
        format!("{e:#}").contains("more than one 'vertex' element"),
        "{e:#}"
    );
}
