//! `align_similarity`: recovery of known similarities (scales from 1e-3 to 1e3, rotations
//! up to a half turn, planar points), least-squares optimality under noise, the inverse,
//! moved poses, and the inputs it refuses. `align_cameras`: recovery from the views,
//! least-squares optimality of the reprojections, a scene placed by its views where the
//! centres' fit misplaces it, and the inputs it refuses. `reprojection_error`: zero
//! under the cameras' own frame, f·θ for a turn, far less for an orbit about the scene, and
//! the inputs it refuses.

use neural_fields::camera::{
    align_cameras, align_similarity, reprojection_error, Camera, Convention, Intrinsics, Similarity,
};
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
        .map(|(&x, &y)| (s.apply(x) - y).length_squared())
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
        let to: Vec<DVec3> = from.iter().map(|&p| truth.apply(p)).collect();
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
            .map(|&p| truth.apply(p) + DVec3::new(rng.normal(), rng.normal(), rng.normal()) * 0.1)
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
        let to: Vec<DVec3> = from.iter().map(|&p| truth.apply(p)).collect();
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
fn the_documented_inverse_undoes_the_map_and_moved_poses_stay_rigid() {
    let s = Similarity {
        scale: 3.0,
        rotation: DQuat::from_axis_angle(DVec3::new(1.0, 2.0, 3.0).normalize(), 0.7),
        translation: DVec3::new(-1.0, 0.5, 2.0),
    };
    let p = DVec3::new(0.2, -0.4, 1.1);
    // The inverse as the docs of `Similarity` state it.
    let r = s.rotation.inverse();
    let inverse = Similarity {
        scale: 1.0 / s.scale,
        rotation: r,
        translation: -(r * s.translation) / s.scale,
    };
    assert!((inverse.apply(s.apply(p)) - p).length() < 1e-12);
    let pose =
        DAffine3::from_rotation_translation(DQuat::from_rotation_y(0.3), DVec3::new(0.0, 0.0, 4.0));
    let moved = s.apply(pose);
    let r = moved.matrix3;
    assert!((r.transpose() * r - DMat3::IDENTITY)
        .to_cols_array()
        .iter()
        .all(|v| v.abs() < 1e-12));
    assert!((moved.translation - s.apply(pose.translation)).length() < 1e-12);
    assert_eq!(Similarity::IDENTITY.apply(p), p);
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

/// `n` cameras 3 units from the origin in random directions, looking at it (100 × 100
/// pixels, 0.6 rad field of view).
fn ring(rng: &mut SplitMix64, n: usize, convention: Convention) -> Vec<Camera> {
    let k = Intrinsics::from_fov_y(100, 100, 0.6).unwrap();
    (0..n)
        .map(|_| {
            let eye = DVec3::new(rng.normal(), rng.normal(), rng.normal()).normalize() * 3.0;
            Camera::look_at(k, eye, DVec3::ZERO, DVec3::new(0.1, 0.2, 1.0), convention).unwrap()
        })
        .collect()
}

fn moved(cameras: &[Camera], s: &Similarity) -> Vec<Camera> {
    cameras
        .iter()
        .map(|c| Camera::new(*c.intrinsics(), s.apply(c.cam_to_world()), c.convention()))
        .collect::<Result<_, _>>()
        .unwrap()
}

/// `align_cameras`' objective: squared pixel disagreements over the pairs `from` sees.
fn reprojection_cost(s: &Similarity, from: &[Camera], to: &[Camera], points: &[DVec3]) -> f64 {
    let mut cost = 0.0;
    for (f, t) in from.iter().zip(to) {
        for &y in points {
            let k = f.intrinsics();
            let Some(p) = f.project(y) else { continue };
            if !(0.0..=k.width as f64).contains(&p.x) || !(0.0..=k.height as f64).contains(&p.y) {
                continue;
            }
            let q = t.project(s.apply(y)).unwrap();
            cost += (q.truncate() - p.truncate()).length_squared();
        }
    }
    cost
}

/// How far `s` puts the scene from where `truth` does: RMS over `points`.
fn misplacement(s: &Similarity, truth: &Similarity, points: &[DVec3]) -> f64 {
    (points
        .iter()
        .map(|&y| (s.apply(y) - truth.apply(y)).length_squared())
        .sum::<f64>()
        / points.len() as f64)
        .sqrt()
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(16))]

    #[test]
    fn a_known_similarity_is_recovered_from_the_views(
        seed in 0u64..10_000,
        log_scale in -1.0f64..1.0,
        opengl in any::<bool>(),
    ) {
        let mut rng = SplitMix64::new(seed);
        let convention = if opengl { Convention::OpenGl } else { Convention::OpenCv };
        let from = ring(&mut rng, 12, convention);
        let truth = Similarity {
            scale: 10f64.powf(log_scale),
            rotation: unit_quat(&mut rng),
            translation: DVec3::new(rng.normal(), rng.normal(), rng.normal()),
        };
        let to = moved(&from, &truth);
        let points: Vec<DVec3> = cloud(&mut rng, 50).iter().map(|&p| p * 0.3).collect();
        let s = align_cameras(&from, &to, &points).unwrap();
        prop_assert!((s.scale / truth.scale - 1.0).abs() < 1e-7, "{} vs {}", s.scale, truth.scale);
        prop_assert!(s.rotation.angle_between(truth.rotation) < 1e-7);
        prop_assert!(misplacement(&s, &truth, &points) < 1e-7 * truth.scale);
    }

    /// With every reference camera off by its own small pose error, the result is a
    /// least-squares minimum of the reprojections: nudging it in any of the 7 directions
    /// does not lower the cost.
    #[test]
    fn the_views_fit_is_a_least_squares_minimum(seed in 0u64..10_000) {
        let mut rng = SplitMix64::new(seed);
        let from = ring(&mut rng, 10, Convention::OpenCv);
        let to: Vec<Camera> = from
            .iter()
            .map(|c| {
                let noise = Similarity {
                    scale: 1.0,
                    rotation: DQuat::from_axis_angle(unit_quat(&mut rng).xyz().normalize(), 0.01),
                    translation: DVec3::new(rng.normal(), rng.normal(), rng.normal()) * 0.03,
                };
                moved(&[*c], &noise)[0]
            })
            .collect();
        let points: Vec<DVec3> = cloud(&mut rng, 40).iter().map(|&p| p * 0.3).collect();
        let s = align_cameras(&from, &to, &points).unwrap();
        let best = reprojection_cost(&s, &from, &to, &points);
        let e = 1e-5;
        for k in 0..14 {
            let sign = if k < 7 { e } else { -e };
            let mut t = s;
            match k % 7 {
                0 => t.scale *= 1.0 + sign,
                1 => t.rotation = DQuat::from_rotation_x(sign) * t.rotation,
                2 => t.rotation = DQuat::from_rotation_y(sign) * t.rotation,
                3 => t.rotation = DQuat::from_rotation_z(sign) * t.rotation,
                4 => t.translation.x += sign,
                5 => t.translation.y += sign,
                _ => t.translation.z += sign,
            }
            let nudged = reprojection_cost(&t, &from, &to, &points);
            prop_assert!(nudged >= best * (1.0 - 1e-9), "direction {k}: {nudged} < {best}");
        }
    }
}

/// Cameras refined from images are worst along the orbit about what they look at: a
/// centre shifted across the line of sight with the matching turn keeps the scene's image
/// nearly in place. With each reference camera orbited about the scene by its own random
/// angle of about 1°, the centres' fit misplaces the scene by its centres' errors; the
/// views' fit places it by what the cameras see, several times closer.
#[test]
fn orbit_errors_misplace_the_scene_less_by_the_views_than_by_the_centres() {
    let (mut by_views, mut by_centres) = (0.0, 0.0);
    for seed in 0..8 {
        let mut rng = SplitMix64::new(seed);
        let from = ring(&mut rng, 20, Convention::OpenCv);
        let truth = Similarity {
            scale: 1.3,
            rotation: unit_quat(&mut rng),
            translation: DVec3::new(0.5, -0.2, 0.1),
        };
        let to: Vec<Camera> = moved(&from, &truth)
            .iter()
            .map(|c| {
                let axis = unit_quat(&mut rng).xyz().normalize();
                let orbit = Similarity {
                    scale: 1.0,
                    rotation: DQuat::from_axis_angle(axis, 1f64.to_radians()),
                    translation: DVec3::ZERO,
                };
                // About the scene's centre, which `truth` moved to its translation.
                let about = |s: Similarity| Similarity {
                    translation: truth.translation - s.rotation * truth.translation,
                    ..s
                };
                moved(&[*c], &about(orbit))[0]
            })
            .collect();
        let points: Vec<DVec3> = cloud(&mut rng, 200).iter().map(|&p| p * 0.3).collect();
        let centres = |c: &[Camera]| {
            c.iter()
                .map(|c| c.cam_to_world().translation)
                .collect::<Vec<_>>()
        };
        by_centres += misplacement(
            &align_similarity(&centres(&from), &centres(&to)).unwrap(),
            &truth,
            &points,
        );
        by_views += misplacement(
            &align_cameras(&from, &to, &points).unwrap(),
            &truth,
            &points,
        );
    }
    println!("misplacement: views {by_views:e}, centres {by_centres:e} (sums over 8 scenes)");
    assert!(
        by_views < 0.3 * by_centres,
        "mean misplacement by the views {}, by the centres {}",
        by_views / 8.0,
        by_centres / 8.0
    );
}

#[test]
fn align_cameras_refuses_bad_input_naming_the_argument() {
    let k = Intrinsics::from_fov_y(64, 64, 0.6).unwrap();
    let eyes = [DVec3::X, -DVec3::X, DVec3::Y, -DVec3::Y, DVec3::Z];
    let cams: Vec<Camera> = eyes
        .iter()
        .map(|&e| {
            Camera::look_at(
                k,
                e * 3.0,
                DVec3::ZERO,
                DVec3::new(0.1, 0.2, 1.0),
                Convention::OpenCv,
            )
            .unwrap()
        })
        .collect();
    let points = [DVec3::ZERO, DVec3::X * 0.2];
    type Case<'a> = (&'a [Camera], &'a [Camera], &'a [DVec3], &'a str);
    let cases: [Case; 5] = [
        (&cams, &cams[..4], &points, "to"),
        (&cams[..2], &cams[..2], &points, "from"),
        (&cams, &cams, &[], "points"),
        (&cams, &cams, &[DVec3::new(f64::NAN, 0.0, 0.0)], "points"),
        // Off every camera's image.
        (&cams, &cams, &[DVec3::splat(40.0)], "points"),
    ];
    for (from, to, pts, arg) in cases {
        let e = align_cameras(from, to, pts).unwrap_err();
        assert!(e.to_string().contains(arg), "expected `{arg}` in: {e}");
    }
    let s = align_cameras(&cams, &cams, &points).unwrap();
    assert!((s.scale - 1.0).abs() < 1e-12 && s.translation.length() < 1e-12);
}

/// `reprojection_error`: zero for the same cameras seen through their frame, f·θ
/// for a turn of θ, and a fraction of that for an orbit of θ about the scene.
#[test]
fn reprojection_error_is_zero_under_the_frame_and_small_for_an_orbit() {
    let k = Intrinsics::from_fov_y(100, 100, 0.7).unwrap();
    let cameras: Vec<Camera> = (0..6)
        .map(|i| {
            let a = i as f64 * std::f64::consts::TAU / 6.0;
            let eye = DVec3::new(4.0 * a.cos(), 4.0 * a.sin(), 1.0);
            Camera::look_at(k, eye, DVec3::ZERO, DVec3::Z, Convention::OpenGl).unwrap()
        })
        .collect();
    let mut rng = SplitMix64::new(7);
    let points: Vec<DVec3> = (0..300)
        .map(|_| DVec3::new(rng.normal(), rng.normal(), rng.normal()) * 0.25)
        .collect();
    let moved_by = |s: &Similarity| -> Vec<Camera> {
        cameras
            .iter()
            .map(|c| Camera::new(k, s.apply(c.cam_to_world()), c.convention()).unwrap())
            .collect()
    };
    // The same cameras in another frame, seen through that frame: no error.
    let s = Similarity {
        scale: 1.7,
        rotation: DQuat::from_rotation_y(0.3),
        translation: DVec3::new(0.2, -0.4, 0.1),
    };
    let e = reprojection_error(&cameras, &moved_by(&s), &points, &s).unwrap();
    assert!(e < 1e-9, "{e}");
    // Each camera turned by θ about its own vertical axis: every point moves by about
    // f·θ pixels.
    let theta = 0.2f64.to_radians();
    let turned: Vec<Camera> = cameras
        .iter()
        .map(|c| {
            let p = c.cam_to_world() * DAffine3::from_rotation_y(theta);
            Camera::new(k, p, c.convention()).unwrap()
        })
        .collect();
    let turn = reprojection_error(&cameras, &turned, &points, &Similarity::IDENTITY).unwrap();
    assert!(
        (turn / (k.fy * theta) - 1.0).abs() < 0.05,
        "{turn} px against {}",
        k.fy * theta
    );
    // Each camera orbited by θ about the scene's centre (turned to match): only
    // parallax, several times less.
    let orbit = Similarity {
        scale: 1.0,
        rotation: DQuat::from_rotation_z(theta),
        translation: DVec3::ZERO,
    };
    let orbit =
        reprojection_error(&cameras, &moved_by(&orbit), &points, &Similarity::IDENTITY).unwrap();
    assert!(orbit < 0.3 * turn, "orbit {orbit} px, turn {turn} px");
}

#[test]
fn reprojection_error_refuses_bad_input_naming_the_argument() {
    let k = Intrinsics::from_fov_y(64, 64, 0.6).unwrap();
    let cams: Vec<Camera> = [DVec3::X, -DVec3::X, DVec3::Y]
        .iter()
        .map(|&e| Camera::look_at(k, e * 3.0, DVec3::ZERO, DVec3::Z, Convention::OpenCv).unwrap())
        .collect();
    let points = [DVec3::ZERO, DVec3::X * 0.2];
    let id = Similarity::IDENTITY;
    let nan = Similarity {
        scale: f64::NAN,
        ..Similarity::IDENTITY
    };
    type Case<'a> = (&'a [Camera], &'a [DVec3], &'a Similarity, &'a str);
    let cases: [Case; 5] = [
        (&cams[..2], &points, &id, "to"),
        (&cams, &[], &id, "points"),
        (&cams, &[DVec3::new(0.0, f64::INFINITY, 0.0)], &id, "points"),
        // Off every camera's image.
        (&cams, &[DVec3::splat(40.0)], &id, "points"),
        (&cams, &points, &nan, "frame"),
    ];
    for (to, pts, frame, arg) in cases {
        let e = reprojection_error(&cams, to, pts, frame).unwrap_err();
        assert!(e.to_string().contains(arg), "expected `{arg}` in: {e}");
    }
}
