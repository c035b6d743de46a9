//! Regression: a `Mesh` built as a struct literal with a face index past its vertices
//! panicked (index out of bounds) in the geometric accessors instead of returning an
//! error naming the mesh.

use neural_fields::mesh::Mesh;
use neural_fields::Error;

fn names_mesh<T: std::fmt::Debug>(r: Result<T, Error>) {
    match r {
        Err(Error::InvalidArgument { arg, expected, got }) => {
            assert_eq!(arg, "mesh");
            assert!(expected.contains("face indices"), "{expected}");
            assert!(
                got.contains("face 1") && got.contains("vertex 7 of 3"),
                "{got}"
            );
        }
        other => panic!("expected an error naming the mesh, got {other:?}"),
    }
}

#[test]
fn mesh_literal_with_out_of_range_face_index_is_an_error_not_a_panic() {
    let mesh = Mesh {
        vertices: vec![[0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
        faces: vec![[0, 1, 2], [0, 2, 7]],
        normals: None,
        colors: None,
    };
    names_mesh(mesh.vertex_normals());
    names_mesh(mesh.signed_volume());
    names_mesh(mesh.sample_surface(10, 0));
    names_mesh(mesh.validate());
    // The valid prefix still works.
    let ok = Mesh {
        faces: vec![[0, 1, 2]],
        ..mesh
    };
    assert_eq!(ok.vertex_normals().unwrap(), vec![[0.0, 0.0, 1.0]; 3]);
}
