//! `KdTree::nearest` of a NaN point answered `(0, ∞)`, as if point 0 were its nearest
//! neighbour; it now answers `None` for a NaN or ±∞ query, and the tree refuses
//! non-finite points when it is built.

use neural_fields::occupancy::KdTree;

#[test]
fn a_non_finite_query_has_no_nearest_point() {
    let tree = KdTree::new(&[[0.0; 3], [1.0, 0.0, 0.0], [0.0, 2.0, 0.0]]).unwrap();
    for bad in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
        assert_eq!(tree.nearest([bad, 0.0, 0.0]), None);
        assert_eq!(tree.nearest([0.0, 0.0, bad]), None);
    }
    assert_eq!(tree.nearest([0.9, 0.0, 0.0]).map(|n| n.0), Some(1));
}

#[test]
fn a_tree_of_non_finite_points_is_refused() {
    assert!(KdTree::new(&[[0.0; 3], [f64::NAN, 0.0, 0.0]]).is_err());
    assert!(KdTree::new(&[[f64::INFINITY, 0.0, 0.0]]).is_err());
}
