//! `align_similarity`: recovery of known similarities (scales from 1e-3 to 1e3, rotations
//! up to a half turn, planar points), least-squares optimality under noise, the inverse,
//! moved poses, and the inputs it refuses.

use neural_fields::camera::{align_similarity, Similarity};
use neural_fields::glam::{DAffine3, DMat3, DQuat, DVec3};
use neural_fields::rng::SplitMix64;
use proptest::prelude::*;

fn cloud(rng: &mut SplitMix64, n: usize) -> Vec<DVec3> {
    (0..n)
        .map(|_| DVec3::new(rng.normal(), rng.normal(), rng.normal()))
        .collect()
}

fn unit_quat(rng: &mut SplitMix64) -> DQuat {
    DQuat::from_xyzw(rng.normal(), rng.normal(), rng.normal(), rng.normal()).normalize()
}

fn residual(s: &Similarity, from: &[DVec3], to: &[DVec3]) -> f64 {
    from.iter()
        .zip(to)
        .map(|(&x, &y)| (s.transform_point(x) - y).length_squared())
        .sum()
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    #[test]
    fn a_known_similarity_is_recovered(
        seed in 0u64..10_000,
        log_scale in -3.0f64..3.0,
        n in 3usize..60,
        offset in prop::sample::select(vec![0.0, 1.0, 1e3]),
    ) {
        let mut rng = SplitMix64::new(seed);
        let truth = Similarity {
            scale: 10f64.powf(log_scale),
            rotation: unit_quat(&mut rng),
            translation: DVec3::new(rng.normal(), rng.normal(), rng.normal()) * offset,
        };
        let from = cloud(&mut rng, n);
        let to: Vec<DVec3> = from.iter().map(|&p| truth.transform_point(p)).collect();
        let s = align_similarity(&from, &to).unwrap();
        prop_assert!((s.scale / truth.scale - 1.0).abs() < 1e-9, "{} vs {}", s.scale, truth.scale);
        prop_assert!(s.rotation.angle_between(truth.rotation) < 1e-7);
        let tol = 1e-8 * (1.0 + truth.translation.length());
        prop_assert!((s.translation - truth.translation).length() < tol);
    }

    /// Under noise the result is a least-squares minimum: nudging scale, rotation or
    /// translation does not lower the residual.
    #[test]
    fn the_result_is_a_least_squares_minimum(seed in 0u64..10_000) {
        let mut rng = SplitMix64::new(seed);
        let truth = Similarity { scale: 1.7, rotation: unit_quat(&mut rng), translation: DVec3::new(0.3, -1.0, 2.0) };
        let from = cloud(&mut rng, 20);
        let to: Vec<DVec3> = from
            .iter()
            .map(|&p| truth.transform_point(p) + DVec3::new(rng.normal(), rng.normal(), rng.normal()) * 0.1)
            .collect();
        let s = align_similarity(&from, &to).unwrap();
        let best = residual(&s, &from, &to);
        for k in 0..12 {
            let e = 1e-4;
            let mut t = s;
            match k % 4 {
                0 => t.scale *= 1.0 + if k < 4 { e } else { -e },
                1 => t.rotation = DQuat::from_axis_angle(unit_quat(&mut rng).xyz().normalize(), e) * t.rotation,
                2 => t.translation.x += if k < 4 { e } else { -e },
                _ => t.translation.z -= if k < 4 { e } else { -e },
            }
            prop_assert!(residual(&t, &from, &to) >= best * (1.0 - 1e-12));
        }
    }
}

#[test]
fn a_half_turn_and_planar_points_are_recovered() {
    let from = [DVec3::ZERO, DVec3::X, DVec3::Y, DVec3::new(2.0, 1.0, 0.0)];
    for rotation in [
        DQuat::from_rotation_z(std::f64::consts::PI),
        DQuat::from_rotation_x(std::f64::consts::PI),
        DQuat::IDENTITY,
    ] {
        let truth = Similarity {
            scale: 0.5,
            rotation,
            translation: DVec3::new(4.0, 5.0, 6.0),
        };
        let to: Vec<DVec3> = from.iter().map(|&p| truth.transform_point(p)).collect();
        let s = align_similarity(&from, &to).unwrap();
        assert!(
            s.rotation.angle_between(rotation) < 1e-9,
            "{rotation:?}: {:?}",
            s.rotation
        );
        assert!((s.scale - 0.5).abs() < 1e-12);
    }
}

#[test]
fn the_inverse_undoes_the_map_and_moved_poses_stay_rigid() {
    let s = Similarity {
        scale: 3.0,
        rotation: DQuat::from_axis_angle(DVec3::new(1.0, 2.0, 3.0).normalize(), 0.7),
        translation: DVec3::new(-1.0, 0.5, 2.0),
    };
    let p = DVec3::new(0.2, -0.4, 1.1);
    assert!((s.inverse().transform_point(s.transform_point(p)) - p).length() < 1e-12);
    let pose =
        DAffine3::from_rotation_translation(DQuat::from_rotation_y(0.3), DVec3::new(0.0, 0.0, 4.0));
    let moved = s.transform_pose(&pose);
    let r = moved.matrix3;
    assert!((r.transpose() * r - DMat3::IDENTITY)
        .to_cols_array()
        .iter()
        .all(|v| v.abs() < 1e-12));
    assert!((moved.translation - s.transform_point(pose.translation)).length() < 1e-12);
    assert_eq!(Similarity::IDENTITY.transform_point(p), p);
}

/// A mirror image has no proper rotation onto it: the result is still a rotation (the
/// best proper one), never a reflection.
#[test]
fn a_mirrored_cloud_gets_a_proper_rotation() {
    let mut rng = SplitMix64::new(5);
    let from = cloud(&mut rng, 12);
    let to: Vec<DVec3> = from.iter().map(|p| DVec3::new(-p.x, p.y, p.z)).collect();
    let s = align_similarity(&from, &to).unwrap();
    assert!((DMat3::from_quat(s.rotation).determinant() - 1.0).abs() < 1e-12);
}

#[test]
fn degenerate_inputs_are_refused_naming_the_argument() {
    let good = [DVec3::X, DVec3::Y, DVec3::Z];
    let cases: [(&[DVec3], &[DVec3], &str); 6] = [
        (&good, &good[..2], "to"),
        (&good[..2], &good[..2], "from"),
        (&[DVec3::ONE; 3], &good, "from"),
        (&good, &[DVec3::ONE; 3], "to"),
        (&[DVec3::ZERO, DVec3::X, DVec3::X * 2.0], &good, "from"),
        (
            &[DVec3::X, DVec3::Y, DVec3::new(f64::NAN, 0.0, 0.0)],
            &good,
            "from",
        ),
    ];
    for (from, to, arg) in cases {
        let e = align_similarity(from, to).unwrap_err();
        assert!(e.to_string().contains(arg), "expected `{arg}` in: {e}");
    }
    let inf = [DVec3::X, DVec3::Y, DVec3::splat(f64::INFINITY)];
    assert!(align_similarity(&good, &inf)
        .unwrap_err()
        .to_string()
        .contains("to"));
}
