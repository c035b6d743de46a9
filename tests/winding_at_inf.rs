//! `occupancy::winding_numbers` at an infinite or NaN point returned NaN as if it were a
//! winding number; it is now an error naming `points`.

use neural_fields::mesh::Mesh;
use neural_fields::occupancy::{winding_numbers, WindingConfig};

#[test]
fn a_non_finite_point_is_refused_naming_points() {
    let tet = Mesh::new(
        vec![[0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        vec![[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]],
    )
    .unwrap();
    for force_reference in [false, true] {
        let config = WindingConfig { force_reference };
        for bad in [f64::INFINITY, f64::NEG_INFINITY, f64::NAN] {
            let points = [[0.1, 0.1, 0.1], [bad, 0.0, 0.0]];
            let e = winding_numbers(&tet, &points, &config)
                .unwrap_err()
                .to_string();
            assert!(e.starts_with("points: ") && e.contains("index 1"), "{e}");
        }
        let w = winding_numbers(&tet, &[[0.1, 0.1, 0.1], [5.0, 5.0, 5.0]], &config).unwrap();
        assert!(
            (w[0].abs() - 1.0).abs() < 1e-6 && w[1].abs() < 1e-6,
            "{w:?}"
        );
    }
}
