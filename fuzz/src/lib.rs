//! What every mesh-reader fuzz target checks.

use neural_fields::occupancy::{Mesh, MeshFormat, PointCloud};

/// Reads `data` as a mesh and as a point cloud in `format`: any bytes must give `Ok` or
/// `Err`, in time and memory bounded by their size. What loads must be valid, write back,
/// and hold no more faces than the input has bytes (every triangle consumes an index).
pub fn check_readers(data: &[u8], format: MeshFormat) {
    if let Ok(mesh) = Mesh::from_bytes(data, format) {
        mesh.validate().expect("a mesh that loads is valid");
        assert!(mesh.faces.len() <= data.len(), "more faces than bytes");
        mesh.to_bytes(format).expect("a mesh that loads writes back");
    }
    if let Ok(cloud) = PointCloud::from_bytes(data, format) {
        assert!(!cloud.is_empty());
    }
}
