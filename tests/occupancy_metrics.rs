//! Occupancy metrics: counts and scales that would abort or overflow are errors naming
//! the argument.
#![cfg(feature = "occupancy")]

use neural_fields::mesh::Mesh;

/// Pins an abort: `mesh_metrics` with `n = usize::MAX` requested that many points up
/// front (a capacity overflow). The count is now an error naming `n`.
#[test]
fn mesh_metrics_with_an_unallocatable_sample_count_is_an_error() {
    let tri = Mesh::new(
        vec![[0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
        vec![[0, 1, 2]],
    )
    .unwrap();
    for n in [usize::MAX, usize::MAX / 2] {
        let e = neural_fields::occupancy::mesh_metrics(&tri, &tri, n, 0.01, 0).unwrap_err();
        assert!(e.to_string().starts_with("n:"), "{e}");
    }
}

/// Pins silent non-finite metrics: meshes with coordinates near 1e300 gave Chamfer `inf`
/// and normal consistency NaN as `Ok`; a metric that f64 cannot represent is an error.
#[test]
fn surface_metrics_that_overflow_f64_are_errors_not_inf() {
    let far = [[1e300, 1e300, 1e300], [-1e300, -1e300, -1e300]];
    let near = [[0.0; 3], [1.0, 0.0, 0.0]];
    let e = neural_fields::occupancy::surface_metrics(&far, None, &near, None, 0.01).unwrap_err();
    assert!(e.to_string().starts_with("pred:"), "{e}");
    // The same sets at a representable scale give finite metrics.
    let ok = [[1e100, 1e100, 1e100], [-1e100, -1e100, -1e100]];
    let m = neural_fields::occupancy::surface_metrics(&ok, None, &near, None, 0.01).unwrap();
    assert!(m.chamfer_l1.is_finite());
}
