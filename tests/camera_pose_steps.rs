//! Camera registration by Levenberg–Marquardt: `retract_pose` (the pose step) and
//! `numerics::damped_solve` (the damped normal equations), alone and together registering
//! a camera from its pixels.

use neural_fields::camera::{retract_pose, Camera, Convention, Intrinsics};
use neural_fields::glam::{DAffine3, DMat3, DQuat, DVec2, DVec3};
use neural_fields::numerics::damped_solve;
use neural_fields::rng::SplitMix64;
use proptest::prelude::*;

fn vec3(rng: &mut SplitMix64) -> DVec3 {
    DVec3::new(rng.normal(), rng.normal(), rng.normal())
}

fn angle_between(a: &DMat3, b: &DMat3) -> f64 {
    DQuat::from_mat3(&(a.transpose() * *b))
        .normalize()
        .angle_between(DQuat::IDENTITY)
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    /// The step keeps the pose rigid, turns it by |ω| about ω (the camera centre fixed),
    /// shifts the centre by v, and two half turns about one axis make the whole turn.
    #[test]
    fn retract_pose_is_a_rigid_turn_about_the_centre_and_a_shift(
        seed in 0u64..10_000,
        log_scale in -6.0f64..3.0,
    ) {
        let mut rng = SplitMix64::new(seed);
        let pose = DAffine3::from_rotation_translation(
            DQuat::from_xyzw(rng.normal(), rng.normal(), rng.normal(), rng.normal()).normalize(),
            vec3(&mut rng) * 10f64.powf(log_scale),
        );
        let w = vec3(&mut rng).normalize() * 0.7;
        let v = vec3(&mut rng);
        let moved = retract_pose(&pose, [w.x, w.y, w.z, v.x, v.y, v.z]);
        let m = moved.matrix3;
        prop_assert!((m.transpose() * m - DMat3::IDENTITY).to_cols_array().iter().all(|x| x.abs() < 1e-12));
        prop_assert!((m.determinant() - 1.0).abs() < 1e-12);
        prop_assert!((angle_between(&pose.matrix3, &m) - 0.7).abs() < 1e-9);
        // The axis is a world axis: it is left where it is by the turn.
        prop_assert!(((m * pose.matrix3.transpose()) * w - w).length() < 1e-12);
        let tol = 1e-12 * (1.0 + pose.translation.length());
        prop_assert!((moved.translation - pose.translation - v).length() < tol);
        let h = w * 0.5;
        let twice = retract_pose(&retract_pose(&pose, [h.x, h.y, h.z, 0.0, 0.0, 0.0]), [h.x, h.y, h.z, 0.0, 0.0, 0.0]);
        prop_assert!(angle_between(&twice.matrix3, &m) < 1e-9);
        prop_assert_eq!(retract_pose(&pose, [0.0; 6]), pose);
    }

    /// With λ = 0 the step solves the normal equations; a larger λ gives a shorter step
    /// that tends to the scaled gradient step −g/(λ·diag H). Systems scaled by 1e±100.
    #[test]
    fn damped_solve_solves_the_damped_normal_equations(seed in 0u64..10_000, log_scale in -100.0f64..100.0) {
        let mut rng = SplitMix64::new(seed);
        let scale = 10f64.powf(log_scale);
        let rows: Vec<[f64; 6]> = (0..10).map(|_| std::array::from_fn(|_| rng.normal())).collect();
        let r: Vec<f64> = (0..10).map(|_| rng.normal()).collect();
        let mut h = [[0.0; 6]; 6];
        let mut g = [0.0; 6];
        for (j, &ri) in rows.iter().zip(&r) {
            for p in 0..6 {
                g[p] += j[p] * ri * scale;
                for q in 0..6 {
                    h[p][q] += j[p] * j[q] * scale;
                }
            }
        }
        let x = damped_solve(&h, &g, 0.0).unwrap();
        let gmax = g.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        for p in 0..6 {
            let hx: f64 = (0..6).map(|q| h[p][q] * x[q]).sum();
            prop_assert!((hx + g[p]).abs() < 1e-9 * gmax, "row {}: {} vs {}", p, hx, -g[p]);
        }
        let norm = |v: &[f64; 6]| v.iter().map(|a| a * a).sum::<f64>().sqrt();
        let damped = damped_solve(&h, &g, 1.0).unwrap();
        prop_assert!(norm(&damped) < norm(&x));
        let lambda = 1e8;
        let far = damped_solve(&h, &g, lambda).unwrap();
        let gradient_step: [f64; 6] = std::array::from_fn(|p| -g[p] / (lambda * h[p][p]));
        for p in 0..6 {
            prop_assert!((far[p] - gradient_step[p]).abs() < 1e-6 * norm(&gradient_step));
        }
    }
}

/// Levenberg–Marquardt with the two pieces registers a camera turned by about 9° and
/// shifted by 0.3 to the pixels of 40 points it sees, to 1e-8, with the Jacobian of each
/// projection by central differences of `retract_pose` (as `examples/dvr_multiview`'s
/// image alignment forms it).
#[test]
fn lm_registers_a_camera_to_the_pixels_of_known_points() {
    let k = Intrinsics::from_fov_y(64, 48, 0.9).unwrap();
    let truth = Camera::look_at(
        k,
        DVec3::new(3.0, -2.0, 1.0),
        DVec3::ZERO,
        DVec3::Z,
        Convention::OpenCv,
    )
    .unwrap();
    let mut rng = SplitMix64::new(7);
    let points: Vec<DVec3> = (0..40).map(|_| vec3(&mut rng) * 0.5).collect();
    let pixels: Vec<DVec2> = points
        .iter()
        .map(|&p| truth.project(p).unwrap().truncate())
        .collect();
    let camera = |pose: DAffine3| Camera::new(k, pose, Convention::OpenCv).unwrap();
    // Cost ½ Σ |π(X) − x|², its Gauss–Newton matrix and gradient at `pose`.
    let system = |pose: &DAffine3| {
        let cam = camera(*pose);
        let h_fd = 1e-6;
        let moved: Vec<[Camera; 2]> = (0..6)
            .map(|i| {
                let mut step = [0.0; 6];
                step[i] = h_fd;
                let plus = camera(retract_pose(pose, step));
                step[i] = -h_fd;
                [plus, camera(retract_pose(pose, step))]
            })
            .collect();
        let (mut h, mut g, mut cost) = ([[0.0; 6]; 6], [0.0; 6], 0.0);
        for (&p, &x) in points.iter().zip(&pixels) {
            let r = cam.project(p).unwrap().truncate() - x;
            let jac: Vec<DVec2> = moved
                .iter()
                .map(|[a, b]| {
                    (a.project(p).unwrap().truncate() - b.project(p).unwrap().truncate())
                        / (2.0 * h_fd)
                })
                .collect();
            cost += 0.5 * r.length_squared();
            for a in 0..6 {
                g[a] += jac[a].dot(r);
                for b in 0..6 {
                    h[a][b] += jac[a].dot(jac[b]);
                }
            }
        }
        (cost, h, g)
    };
    let start = retract_pose(&truth.cam_to_world(), [0.1, -0.12, 0.05, 0.2, 0.1, -0.2]);
    assert!(angle_between(&start.matrix3, &truth.cam_to_world().matrix3) > 0.1);
    let mut pose = start;
    let (mut cost, mut h, mut g) = system(&pose);
    let mut lambda = 1e-2;
    for _ in 0..30 {
        let Some(step) = damped_solve(&h, &g, lambda) else {
            break;
        };
        let trial = retract_pose(&pose, step);
        let (c, h2, g2) = system(&trial);
        if c < cost {
            (pose, cost, h, g) = (trial, c, h2, g2);
            lambda /= 3.0;
        } else {
            lambda *= 4.0;
        }
    }
    let angle = angle_between(&pose.matrix3, &truth.cam_to_world().matrix3);
    assert!(angle < 1e-8, "rotation error {angle}");
    assert!((pose.translation - truth.center()).length() < 1e-8);
}

#[test]
fn damped_solve_refuses_what_it_cannot_solve() {
    assert_eq!(damped_solve(&[[1.0]], &[1.0], -1.0), None);
    assert_eq!(damped_solve(&[[1.0]], &[1.0], f64::NAN), None);
    assert_eq!(damped_solve(&[[1.0]], &[f64::NAN], 1.0), None);
    assert_eq!(damped_solve(&[[0.0]], &[1.0], 1.0), None);
    // Indefinite: not a Gauss–Newton matrix.
    assert_eq!(
        damped_solve(&[[1.0, 2.0], [2.0, 1.0]], &[1.0, 1.0], 0.0),
        None
    );
    // A parameter without signal stays put instead of making the system singular.
    let step = damped_solve(&[[2.0, 0.0], [0.0, 0.0]], &[-2.0, 0.0], 1e-3).unwrap();
    assert!((step[0] - 1.0 / 1.001).abs() < 1e-12 && step[1] == 0.0);
}
