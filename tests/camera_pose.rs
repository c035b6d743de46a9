//! Camera poses: [`PoseParam`] and the rays [`pose_rays`] casts from a batch of them (and
//! their gradients), the pose step [`retract_pose`] alone and registering a camera by
//! Levenberg–Marquardt, and [`pose_error`].

mod common;

use candle_core::{DType, Device, Tensor, Var};
use common::v64;
use glam::{DAffine3, DMat3, DQuat, DVec2, DVec3};
use neural_fields::camera::{
    pose_error, pose_rays, retract_pose, Camera, Convention, Intrinsics, PoseParam,
};
use neural_fields::numerics::{levenberg_marquardt, LmConfig};
use neural_fields::rng::SplitMix64;
use neural_fields::Error;
use proptest::prelude::*;

const CONVENTIONS: [Convention; 2] = [Convention::OpenCv, Convention::OpenGl];
const DTYPES: [DType; 2] = [DType::F32, DType::F64];

fn dev() -> Device {
    Device::Cpu
}

fn v2(t: &Tensor) -> Vec<Vec<f64>> {
    t.to_dtype(DType::F64).unwrap().to_vec2::<f64>().unwrap()
}

/// The argument an `Err` names.
fn arg_of<T: std::fmt::Debug>(r: Result<T, Error>) -> &'static str {
    match r {
        Err(Error::InvalidArgument { arg, .. }) => arg,
        other => panic!("expected InvalidArgument, got {other:?}"),
    }
}

fn intr() -> Intrinsics {
    Intrinsics::new(50.0, 40.0, 32.0, 24.0, 64, 48).unwrap()
}

fn tol(dtype: DType) -> f64 {
    match dtype {
        DType::F32 => 1e-5,
        _ => 1e-12,
    }
}

fn close(a: f64, b: f64, eps: f64) -> bool {
    (a - b).abs() <= eps * (1.0 + a.abs().max(b.abs()))
}

/// `n` rays all of view 0.
fn zeros(n: usize) -> Tensor {
    Tensor::zeros(n, DType::U32, &dev()).unwrap()
}

/// `R(q/|q|)` (rows) read back through [`pose_rays`]: with unit intrinsics and OpenCV's
/// convention the pixel coordinate `(x, y)` has the camera-space direction `(x, y, 1)`, so
/// the rays through `(0, 0)`, `(1, 0)` and `(0, 1)` give `R`'s columns.
fn rotation_of(p: &PoseParam) -> neural_fields::Result<Vec<Vec<f64>>> {
    let k = Intrinsics::new(1.0, 1.0, 0.0, 0.0, 2, 2)?;
    let cam = Camera::new(k, DAffine3::IDENTITY, Convention::OpenCv)?;
    let like = p.translation.as_tensor();
    let px = Tensor::new(&[[0.0f64, 0.0], [1.0, 0.0], [0.0, 1.0]], like.device())?
        .to_dtype(like.dtype())?;
    let views = Tensor::zeros(3, DType::U32, like.device())?;
    let d = v2(pose_rays(std::slice::from_ref(p), &[cam], &views, &px)?.directions());
    let col = |k: usize| -> Vec<f64> {
        match k {
            2 => d[0].clone(),
            _ => (0..3).map(|i| d[k + 1][i] - d[0][i]).collect(),
        }
    };
    let cols = [col(0), col(1), col(2)];
    Ok((0..3)
        .map(|i| cols.iter().map(|c| c[i]).collect())
        .collect())
}

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

}

fn set_var(v: &Var, data: &[f64]) {
    v.set(&Tensor::new(data, &dev()).unwrap()).unwrap();
}

#[test]
fn pose_param_round_trips_and_matches_camera_rays() {
    let pose = DAffine3::from_rotation_translation(
        DQuat::from_axis_angle(DVec3::new(-0.3, 0.2, 1.0).normalize(), 2.9),
        DVec3::new(1.0, 2.0, -3.0),
    );
    for dtype in DTYPES {
        for conv in CONVENTIONS {
            let cam = Camera::new(intr(), pose, conv).unwrap();
            let p = PoseParam::from_affine(&cam.cam_to_world(), &dev(), dtype).unwrap();
            // the optimiser's variables (`PoseParam::vars()` is gone: the fields are public)
            assert_eq!(p.rotation.dims(), [4]);
            assert_eq!(p.translation.dims(), [3]);
            assert_eq!((p.rotation.dtype(), p.translation.dtype()), (dtype, dtype));
            let back = p.to_affine().unwrap();
            assert!(back.abs_diff_eq(pose, 10.0 * tol(dtype)), "{back:?}");
            let px = Tensor::new(&[[0.5f64, 0.5], [40.0, 7.25]], &dev())
                .unwrap()
                .to_dtype(dtype)
                .unwrap();
            let a = cam.rays_for_pixels(&px).unwrap();
            let b = pose_rays(std::slice::from_ref(&p), &[cam], &zeros(2), &px).unwrap();
            for (x, y) in v2(a.directions())
                .iter()
                .flatten()
                .zip(v2(b.directions()).iter().flatten())
            {
                assert!(close(*x, *y, 10.0 * tol(dtype)));
            }
            assert_eq!(v2(a.origins()), v2(b.origins()));
        }
    }
}

#[test]
fn pose_rays_turn_by_the_rotation_of_the_normalised_quaternion() {
    let p = PoseParam::from_affine(&DAffine3::IDENTITY, &dev(), DType::F64).unwrap();
    let raw = [0.3, -1.7, 0.4, 2.2];
    set_var(&p.rotation, &raw);
    let r = rotation_of(&p).unwrap();
    let q = DQuat::from_xyzw(raw[1], raw[2], raw[3], raw[0]).normalize();
    let m = DMat3::from_quat(q);
    for (i, row) in r.iter().enumerate() {
        for (j, x) in row.iter().enumerate() {
            assert!(close(*x, m.col(j)[i], 1e-14));
        }
    }
    // scale invariance, including tiny quaternions whose square underflows
    set_var(&p.rotation, &raw.map(|x| x * 1e-200));
    let r2 = rotation_of(&p).unwrap();
    for (a, b) in r.iter().flatten().zip(r2.iter().flatten()) {
        assert!(close(*a, *b, 1e-14));
    }
    // A unit quaternion of the same rotation (what an optimiser's drifting |q| is reset to).
    let p = PoseParam::from_affine(&p.to_affine().unwrap(), &dev(), DType::F64).unwrap();
    let unit = v64(&p.rotation);
    assert!(
        close(unit.iter().map(|x| x * x).sum::<f64>(), 1.0, 1e-15),
        "{unit:?}"
    );
    let r3 = rotation_of(&p).unwrap();
    for (a, b) in r.iter().flatten().zip(r3.iter().flatten()) {
        assert!(close(*a, *b, 1e-14));
    }
    set_var(&p.rotation, &[0.0; 4]);
    assert_eq!(arg_of(rotation_of(&p)), "rotation");
    assert_eq!(arg_of(p.to_affine()), "rotation");
}

/// `Σ w·(o + t·d)` for rays from `p`, as a function of the variables.
fn pose_objective(p: &PoseParam, px: &Tensor, t: &Tensor, w: &Tensor, conv: Convention) -> Tensor {
    let cam = Camera::new(intr(), DAffine3::IDENTITY, conv).unwrap();
    let rays = pose_rays(std::slice::from_ref(p), &[cam], &zeros(1), px).unwrap();
    let points =
        (rays.origins() + rays.directions().broadcast_mul(&t.unsqueeze(1).unwrap())).unwrap();
    (points * w).unwrap().sum_all().unwrap()
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    #[test]
    fn ray_point_gradient_wrt_pose_matches_finite_differences(
        q in prop::array::uniform4(-1.0f64..1.0),
        tr in prop::array::uniform3(-10.0f64..10.0),
        px in prop::array::uniform2(0.0f64..64.0),
        t in 0.0f64..20.0,
        w in prop::array::uniform3(-1.0f64..1.0),
        qscale in -3.0f64..3.0,
        gl in proptest::bool::ANY,
    ) {
        let norm = q.iter().map(|x| x * x).sum::<f64>().sqrt();
        prop_assume!(norm > 0.1);
        let q = q.map(|x| x * 10f64.powf(qscale));
        let conv = if gl { Convention::OpenGl } else { Convention::OpenCv };
        let p = PoseParam::from_affine(&DAffine3::IDENTITY, &dev(), DType::F64).unwrap();
        set_var(&p.rotation, &q);
        set_var(&p.translation, &tr);
        let pxt = Tensor::new(&[px], &dev()).unwrap();
        let tt = Tensor::new(&[t], &dev()).unwrap();
        let wt = Tensor::new(&[w], &dev()).unwrap();
        let g = pose_objective(&p, &pxt, &tt, &wt, conv).backward().unwrap();
        let gq = v64(g.get(&p.rotation).unwrap());
        let gt = v64(g.get(&p.translation).unwrap());
        let eval = |q: &[f64], tr: &[f64]| {
            set_var(&p.rotation, q);
            set_var(&p.translation, tr);
            pose_objective(&p, &pxt, &tt, &wt, conv).to_scalar::<f64>().unwrap()
        };
        // relative error against the gradient's largest entry (FD noise scales with it)
        let fd_check = |g: &[f64], k: usize, fd: f64, what: &str| -> Result<(), TestCaseError> {
            let gmax = g.iter().fold(1e-300f64, |a, b| a.max(b.abs()));
            prop_assert!((g[k] - fd).abs() / gmax <= 1e-6, "{what}: grad {} fd {fd}", g[k]);
            Ok(())
        };
        let qnorm = q.iter().map(|x| x * x).sum::<f64>().sqrt();
        for k in 0..4 {
            let h = 1e-5 * qnorm;
            let (mut a, mut b) = (q, q);
            a[k] += h;
            b[k] -= h;
            let fd = (eval(&a, &tr) - eval(&b, &tr)) / (2.0 * h);
            fd_check(&gq, k, fd, &format!("q[{k}]"))?;
        }
        for k in 0..3 {
            let h = 1e-5 * tr[k].abs().max(1.0);
            let (mut a, mut b) = (tr, tr);
            a[k] += h;
            b[k] -= h;
            let fd = (eval(&q, &a) - eval(&q, &b)) / (2.0 * h);
            fd_check(&gt, k, fd, &format!("t[{k}]"))?;
        }
    }
}

#[test]
fn pose_param_rejects_bad_arguments() {
    let p = PoseParam::from_affine(&DAffine3::IDENTITY, &dev(), DType::F32).unwrap();
    let cam = Camera::new(intr(), DAffine3::IDENTITY, Convention::OpenCv).unwrap();
    let px64 = Tensor::zeros((2, 2), DType::F64, &dev()).unwrap();
    let px3 = Tensor::zeros((2, 3), DType::F32, &dev()).unwrap();
    let pxu = Tensor::zeros((2, 2), DType::U32, &dev()).unwrap();
    for px in [&px64, &px3, &pxu] {
        assert_eq!(
            arg_of(pose_rays(std::slice::from_ref(&p), &[cam], &zeros(2), px)),
            "pixels"
        );
    }
    let wrong_rot = PoseParam {
        rotation: Var::zeros(3, DType::F32, &dev()).unwrap(),
        translation: p.translation.clone(),
    };
    assert_eq!(arg_of(rotation_of(&wrong_rot)), "rotation");
    assert_eq!(arg_of(wrong_rot.to_affine()), "rotation");
    let wrong_tr = PoseParam {
        rotation: p.rotation.clone(),
        translation: Var::zeros(3, DType::F64, &dev()).unwrap(),
    };
    assert_eq!(arg_of(rotation_of(&wrong_tr)), "translation");
    let wrong_shape_tr = PoseParam {
        rotation: p.rotation.clone(),
        translation: Var::zeros(4, DType::F32, &dev()).unwrap(),
    };
    assert_eq!(arg_of(wrong_shape_tr.to_affine()), "translation");
}

/// Levenberg–Marquardt on the pose step registers a camera turned by about 9° and shifted
/// by 0.3 to the pixels of 40 points it sees, to 1e-8, with the Jacobian of each
/// projection by central differences of `retract_pose` (as the photometric registration
/// forms it).
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
    // Residuals π(X) − x and their Jacobian w.r.t. the pose step at `pose`.
    let linearize = |pose: &DAffine3| {
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
        let (mut r, mut jac) = (Vec::new(), Vec::new());
        for (&p, &x) in points.iter().zip(&pixels) {
            let e = cam.project(p).unwrap().truncate() - x;
            let d: Vec<DVec2> = moved
                .iter()
                .map(|[a, b]| {
                    (a.project(p).unwrap().truncate() - b.project(p).unwrap().truncate())
                        / (2.0 * h_fd)
                })
                .collect();
            r.extend([e.x, e.y]);
            jac.push(std::array::from_fn(|a| d[a].x));
            jac.push(std::array::from_fn(|a| d[a].y));
        }
        Ok(Some((r, jac)))
    };
    let start = retract_pose(&truth.cam_to_world(), [0.1, -0.12, 0.05, 0.2, 0.1, -0.2]);
    assert!(angle_between(&start.matrix3, &truth.cam_to_world().matrix3) > 0.1);
    let config = LmConfig {
        iterations: 30,
        lambda: 1e-2,
        tolerance: 0.0,
        ..LmConfig::default()
    };
    let (pose, cost) =
        levenberg_marquardt(start, &config, linearize, |p, s| retract_pose(p, *s)).unwrap();
    let angle = angle_between(&pose.matrix3, &truth.cam_to_world().matrix3);
    assert!(angle < 1e-8, "rotation error {angle}");
    assert!((pose.translation - truth.cam_to_world().translation).length() < 1e-8);
    assert!(cost < 1e-12, "{cost}");
}

/// One batch of rays from several poses, each ray through its own view's camera: the
/// cameras' own rays when the poses sit at the cameras, whatever the views' intrinsics
/// and conventions; refused arguments name themselves.
#[test]
fn pose_rays_cast_each_ray_from_its_views_pose() {
    let k2 = Intrinsics::new(30.0, 33.0, 10.0, 12.0, 20, 24).unwrap();
    let cams = [
        Camera::look_at(
            intr(),
            DVec3::new(3.0, 0.5, 1.0),
            DVec3::ZERO,
            DVec3::Z,
            Convention::OpenCv,
        ),
        Camera::look_at(
            k2,
            DVec3::new(-1.0, 2.5, 0.5),
            DVec3::ZERO,
            DVec3::Z,
            Convention::OpenGl,
        ),
    ]
    .map(Result::unwrap);
    for dtype in DTYPES {
        let poses: Vec<PoseParam> = cams
            .iter()
            .map(|c| PoseParam::from_affine(&c.cam_to_world(), &dev(), dtype).unwrap())
            .collect();
        let px = [[0.5f64, 0.5], [7.25, 3.0], [19.5, 23.5], [3.0, 4.0]];
        let views = Tensor::new(&[1u32, 0, 1, 0], &dev()).unwrap();
        let pixels = Tensor::new(&px, &dev()).unwrap().to_dtype(dtype).unwrap();
        let rays = pose_rays(&poses, &cams, &views, &pixels).unwrap();
        assert_eq!(rays.len(), 4);
        for (i, (&v, p)) in [1usize, 0, 1, 0].iter().zip(px).enumerate() {
            let one = Tensor::new(&[p], &dev()).unwrap().to_dtype(dtype).unwrap();
            let want = cams[v].rays_for_pixels(&one).unwrap();
            for (a, b) in [
                (rays.origins(), want.origins()),
                (rays.directions(), want.directions()),
            ] {
                let (a, b) = (&v2(a)[i], &v2(b)[0]);
                assert!(
                    a.iter()
                        .zip(b)
                        .all(|(x, y)| close(*x, *y, 10.0 * tol(dtype))),
                    "{a:?} {b:?}"
                );
            }
        }
        assert_eq!(arg_of(pose_rays(&[], &cams, &views, &pixels)), "poses");
        assert_eq!(
            arg_of(pose_rays(&poses, &cams[..1], &views, &pixels)),
            "cameras"
        );
        let far = Tensor::new(&[1u32, 0, 2, 0], &dev()).unwrap();
        assert_eq!(arg_of(pose_rays(&poses, &cams, &far, &pixels)), "views");
        let floats = views.to_dtype(DType::F32).unwrap();
        assert_eq!(arg_of(pose_rays(&poses, &cams, &floats, &pixels)), "views");
        assert_eq!(
            arg_of(pose_rays(&poses, &cams, &zeros(3), &pixels)),
            "views"
        );
    }
}

/// A batch drawn from a dataset, cast from learnable poses left at the dataset's cameras
/// through its pixels' centres, is the batch's own rays.
#[cfg(feature = "data")]
#[test]
fn pose_rays_of_unmoved_poses_are_the_datasets_rays() {
    use neural_fields::data::{load, LoadConfig, RaySampler};
    let config = LoadConfig {
        downscale: 4,
        ..LoadConfig::default()
    };
    let data = load(std::path::Path::new("examples/data/wuson"), &config).unwrap();
    let cameras: Vec<Camera> = data.views().iter().map(|v| *v.camera()).collect();
    let params: Vec<PoseParam> = cameras
        .iter()
        .map(|c| PoseParam::from_affine(&c.cam_to_world(), &dev(), DType::F32).unwrap())
        .collect();
    let mut sampler = RaySampler::new(&data, 3, &dev(), DType::F32).unwrap();
    let batch = sampler.patches(8, 2).unwrap();
    let pixels = (batch.pixels.to_dtype(DType::F32).unwrap() + 0.5).unwrap();
    let rays = pose_rays(&params, &cameras, &batch.views, &pixels).unwrap();
    for (a, b) in [
        (rays.origins(), batch.rays.origins()),
        (rays.directions(), batch.rays.directions()),
    ] {
        let d = (a - b).unwrap().abs().unwrap().max_all().unwrap();
        assert!(d.to_scalar::<f32>().unwrap() < 1e-5);
    }
}

/// The pose error of a pose against itself is zero, of a pose turned by a known angle
/// about its centre and shifted by a known fraction of its distance is that angle and
/// fraction, averaged over the poses; bad input names itself.
#[test]
fn pose_error_is_the_mean_turn_and_relative_shift() {
    let mut rng = SplitMix64::new(3);
    let truth: Vec<DAffine3> = (0..5)
        .map(|_| {
            let q = DQuat::from_xyzw(rng.normal(), rng.normal(), rng.normal(), rng.normal());
            DAffine3::from_rotation_translation(q.normalize(), vec3(&mut rng) * 4.0)
        })
        .collect();
    let (r0, t0) = pose_error(&truth, &truth).unwrap();
    assert!(r0 < 1e-6 && t0 == 0.0, "{r0} {t0}");
    let moved: Vec<DAffine3> = truth
        .iter()
        .enumerate()
        .map(|(i, p)| {
            let axis = vec3(&mut rng).normalize() * (i as f64 + 1.0).to_radians();
            let shift =
                vec3(&mut rng).normalize() * 0.01 * (i as f64 + 1.0) * p.translation.length();
            retract_pose(p, [axis.x, axis.y, axis.z, shift.x, shift.y, shift.z])
        })
        .collect();
    let (r, t) = pose_error(&moved, &truth).unwrap();
    assert!((r - 3.0).abs() < 1e-9, "{r}");
    assert!((t - 0.03).abs() < 1e-12, "{t}");
    assert_eq!(arg_of(pose_error(&[], &[])), "poses");
    assert_eq!(arg_of(pose_error(&truth, &truth[1..])), "truth");
    let nan = [DAffine3::from_translation(DVec3::NAN)];
    assert_eq!(arg_of(pose_error(&nan, &truth[..1])), "poses");
    assert_eq!(arg_of(pose_error(&truth[..1], &nan)), "truth");
}
