//! `Mesh::normalize_unit_cube` on vertices at ±1e308: the extent `hi − lo` overflowed to
//! +∞, the scale became 0 and every vertex landed at the origin. The extent is now formed
//! without overflow, so the mesh is normalised like any other.

use neural_fields::mesh::Mesh;

#[test]
fn a_mesh_spanning_plus_minus_1e308_is_normalised_not_collapsed() {
    let mut m = Mesh::new(
        vec![
            [-1e308, -1e308, -1e308],
            [1e308, -1e308, -1e308],
            [-1e308, 1e308, -1e308],
            [-1e308, -1e308, 1e308],
        ],
        vec![[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]],
    )
    .unwrap();
    let (centre, scale) = m.normalize_unit_cube().unwrap();
    assert_eq!(centre, [0.0; 3]);
    assert!(scale > 0.0 && scale.is_finite(), "scale {scale}");
    assert!((scale * 1e308 - 0.5).abs() < 1e-12, "scale {scale}"); // 1 / (2·1e308)
    assert_eq!(m.vertices[0], [-0.5; 3]);
    assert_eq!(m.vertices[1], [0.5, -0.5, -0.5]);
    assert_eq!(m.vertices[3], [-0.5, -0.5, 0.5]);
}

#[test]
fn the_largest_finite_box_and_an_offset_one_normalise_into_the_unit_cube() {
    for (lo, hi) in [
        (-f64::MAX, f64::MAX),
        (1e300, f64::MAX),
        (-f64::MAX, -1e300),
    ] {
        let mut m = Mesh::new(
            vec![[lo, lo, lo], [hi, lo, lo], [lo, hi, lo], [lo, lo, hi]],
            vec![[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]],
        )
        .unwrap();
        let (_, scale) = m.normalize_unit_cube().unwrap();
        assert!(scale > 0.0 && scale.is_finite());
        for v in &m.vertices {
            assert!(
                v.iter().all(|x| (-0.5..=0.5).contains(x)),
                "{v:?} for {lo}, {hi}"
            );
        }
        assert_eq!(m.vertices[1][0], 0.5);
        assert_eq!(m.vertices[0][0], -0.5);
    }
}

#[test]
fn a_subnormal_box_is_refused_and_left_unchanged() {
    let tiny = 1e-320;
    let v = vec![
        [0.0; 3],
        [tiny, 0.0, 0.0],
        [0.0, tiny, 0.0],
        [0.0, 0.0, tiny],
    ];
    let mut m = Mesh::new(v.clone(), vec![[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]).unwrap();
    assert!(m.normalize_unit_cube().is_err());
    assert_eq!(m.vertices, v);
}
