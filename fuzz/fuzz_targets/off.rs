//! Fuzzes the OFF reader: `Mesh::from_bytes` and `PointCloud::from_bytes` must return
//! `Ok` or `Err` for any bytes, in time and memory bounded by the input's size.
#![no_main]

use libfuzzer_sys::fuzz_target;
use neural_fields::occupancy::{Mesh, MeshFormat, PointCloud};

fuzz_target!(|data: &[u8]| {
    if let Ok(mesh) = Mesh::from_bytes(data, MeshFormat::Off) {
        // What loads is valid and writes back.
        mesh.validate().expect("a mesh that loads is valid");
        assert!(mesh.faces.len() <= data.len(), "more faces than bytes");
        mesh.to_bytes(MeshFormat::Off).expect("a mesh that loads writes back");
    }
    if let Ok(cloud) = PointCloud::from_bytes(data, MeshFormat::Off) {
        assert!(!cloud.is_empty());
    }
});
