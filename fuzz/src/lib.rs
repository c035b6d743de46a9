//! What every mesh-reader fuzz target checks.

use neural_fields::mesh::{Mesh, MeshFormat, PointCloud};

/// Reads `data` as a mesh and as a point cloud in `format`: any bytes must give `Ok` or
/// `Err`, in time and memory bounded by their size. What loads must be valid, write back,
/// and hold no more faces than the input has bytes (every triangle consumes an index).
/// Writing in the read format may refuse only coordinates that format's 32-bit floats
/// cannot hold.
pub fn check_readers(data: &[u8], format: MeshFormat) {
    if let Ok(mesh) = Mesh::from_bytes(data, format) {
        mesh.validate().expect("a mesh that loads is valid");
        assert!(mesh.faces.len() <= data.len(), "more faces than bytes");
        mesh.to_bytes(MeshFormat::Obj).expect("a mesh that loads writes back as OBJ");
        // PLY and binary STL store 32-bit floats: a text file (ASCII STL, a PLY `double`)
        // may hold coordinates they cannot, and then writing must refuse, not overflow.
        let beyond_f32 = mesh
            .vertices
            .iter()
            .chain(mesh.normals.iter().flatten())
            .flatten()
            .any(|c| c.abs() > f64::from(f32::MAX));
        if let Err(e) = mesh.to_bytes(format) {
            assert!(beyond_f32, "a mesh that loads writes back: {e}");
        }
    }
    if let Ok(cloud) = PointCloud::from_bytes(data, format) {
        assert!(!cloud.points().is_empty());
    }
}
