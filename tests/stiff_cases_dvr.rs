//! Stiff cases of `dvr`: marching, secant refinement, sphere tracing, implicit surface
//! points, the DVR/IDR losses and the surface model at extreme inputs.

#![cfg(feature = "dvr")]

mod common;

use candle_core::{DType, Device, Tensor};

use common::stiff::{extreme_points, var, Expect, Suite, DTYPES};

use neural_fields::camera::{ray_sphere, Rays};
use neural_fields::field::{ImplicitSurface, SignedDistance, Sphere};

#[test]
fn dvr_stays_finite() {
    let mut s = Suite::default();
    sweep_dvr(&mut s);
    s.finish("dvr", DVR);
}

#[test]
fn every_public_dvr_function_is_swept_or_exempt() {
    common::stiff::check_coverage("stiff_cases_dvr", &[DVR], EXEMPT, &[], &[]);
}

/// Items swept by `sweep_dvr`.
const DVR: &[&str] = &[
    "dvr::AlphaSchedule::alpha_at",
    "dvr::depth_loss",
    "dvr::eikonal_loss",
    "dvr::idr_mask_loss",
    "dvr::implicit_surface",
    "dvr::march",
    "dvr::occupancy_bce",
    "dvr::most_inside_along_rays",
    "dvr::normal_smoothness_loss",
    "dvr::photometric_loss",
    "dvr::random_points_on_rays",
    "dvr::sphere_trace",
    "dvr::surface_model",
    "dvr::SurfaceModel::loss",
    "dvr::SurfaceModel::shade",
    "dvr::SurfaceModel::value",
    "dvr::SurfaceModel::value_and_grad",
    "dvr::SurfaceModel::rgb",
];

/// Public items without floating-point input (or only reached through a swept item),
/// with the reason. Matching is by prefix.
const EXEMPT: &[(&str, &str)] = &[
    ("dvr::ImplicitConfig::default", "constants"),
    ("dvr::SurfacePoints::", "getters"),
    ("dvr::AlphaSchedule::default", "constants"),
    ("dvr::Hits::", "getters over statuses"),
    ("dvr::MarchConfig::default", "constants"),
    ("dvr::RayStatus::", "enum"),
    ("dvr::SphereTraceConfig::default", "constants"),
    ("dvr::StepSchedule::", "integer schedule"),
    ("dvr::SurfaceModel::inside", "a constant of the kind"),
    ("dvr::SurfaceModelConfig::default", "constants"),
];

fn sweep_dvr(s: &mut Suite) {
    use neural_fields::camera::Intersection;
    use neural_fields::dvr::{
        depth_loss, eikonal_loss, idr_mask_loss, implicit_surface, march, most_inside_along_rays,
        normal_smoothness_loss, occupancy_bce, photometric_loss, random_points_on_rays,
        sphere_trace, AlphaSchedule, ImplicitConfig, MarchConfig, Photometric, SphereTraceConfig,
    };
    use neural_fields::field::Inside;
    let d = Device::Cpu;
    sweep_surface_model(s);
    for dtype in DTYPES {
        let big = if dtype == DType::F32 { 1e18 } else { 1e150 };
        // Rays: a plain hit, a tiny direction, a huge direction, a far-away origin, one
        // starting inside, an exact tangent, a near-tangent one, one along an axis, and
        // four grazing rays from the tangent's origin tilted into the sphere by
        // 1e-3, 1e-6, 1e-9 and 1e-12 rad (the last is a tangent to f32 rounding).
        const GRAZE: [f64; 4] = [1e-3, 1e-6, 1e-9, 1e-12];
        const N_RAYS: usize = 8 + GRAZE.len();
        let o_rows = [
            [0.1, 0.0, -2.0],
            [0.0, 0.1, -2.0],
            [0.0, 0.0, -2.0],
            [0.0, 0.0, -big],
            [0.0, 0.0, 0.1],
            [0.0, 0.5, -2.0],
            [0.0, 0.5 - 1e-7, -2.0],
            [-2.0, 0.0, 0.0],
        ]
        .into_iter()
        .chain(GRAZE.map(|_| [0.0, 0.5, -2.0]))
        .collect::<Vec<_>>()
        .concat();
        let w_rows = [
            [0.0, 0.0, 1.0],
            [0.0, 0.0, 1e-20],
            [0.0, 0.0, 1e20],
            [0.0, 0.0, 1.0],
            [0.0, 0.0, 1.0],
            [0.0, 0.0, 1.0],
            [0.0, 0.0, 1.0],
            [1.0, 0.0, 0.0],
        ]
        .into_iter()
        .chain(GRAZE.map(|a: f64| [0.0, -a.sin(), a.cos()]))
        .collect::<Vec<_>>()
        .concat();
        // Tiny and huge directions: 1e∓20 in f64; 1e∓8 in f32, where ∂t/∂w ∝ t/|w| of a
        // 1e-20 direction (4e40) is beyond the f32 range.
        let s_w = if dtype == DType::F32 { 1e-8 } else { 1e-20 };
        let w_rows = [
            &w_rows[..3],
            &[0.0, 0.0, s_w],
            &[0.0, 0.0, 1.0 / s_w],
            &w_rows[9..],
        ]
        .concat();
        let mut far_v = vec![4.0, 4.0 / s_w, 4.0 * s_w, 2.0 * big, 4.0, 4.0, 4.0, 4.0];
        far_v.extend(GRAZE.map(|_| 4.0));
        let origins = var(&o_rows, &[N_RAYS, 3], dtype);
        let directions = var(&w_rows, &[N_RAYS, 3], dtype);
        let near = Tensor::zeros(N_RAYS, dtype, &d).unwrap();
        let far = Tensor::from_slice(&far_v, N_RAYS, &d)
            .unwrap()
            .to_dtype(dtype)
            .unwrap();
        let range = Intersection::new(near.clone(), far.clone()).unwrap();
        // The rays with graph (gradients reach origins and directions) and detached.
        let rays = Rays::new(origins.as_tensor().clone(), directions.as_tensor().clone()).unwrap();
        let rays_detached = Rays::new(origins.detach(), directions.detach()).unwrap();
        let radius = var(&[0.5], &[], dtype);
        let center = var(&[0.0, 0.0, 0.0], &[3], dtype);
        let sphere = Sphere {
            center: center.as_tensor().clone(),
            radius: radius
                .as_tensor()
                .squeeze(0)
                .unwrap_or(radius.as_tensor().clone()),
        };
        let sdf = sphere.clone().sdf();
        let occ = sphere.occupancy(1e6);
        let fields: [(&str, &dyn ImplicitSurface); 2] = [("sdf", &sdf), ("occupancy k=1e6", &occ)];
        for (name, field) in fields {
            for (steps, secant) in [(2usize, 0usize), (64, 8), (16, 30)] {
                let cfg = MarchConfig {
                    steps,
                    secant_steps: secant,
                    ..MarchConfig::default()
                };
                let label = format!("{dtype:?}, {name}, {steps}+{secant}, extreme rays");
                s.case("dvr::march", label.clone(), Expect::Finite, &[], || {
                    let h = march(field, &rays, &range, &cfg)?;
                    Ok(vec![h.depth, h.points])
                });
                s.case(
                    "dvr::implicit_surface",
                    label,
                    Expect::Finite,
                    &[&origins, &directions, &radius, &center],
                    || {
                        let h = march(field, &rays_detached, &range, &cfg)?;
                        let p = implicit_surface(field, &rays, &h, &ImplicitConfig::default())?;
                        Ok(vec![p.depth, p.points, p.gradient])
                    },
                );
            }
            let bounds = ray_sphere(&rays_detached, [0.0; 3], 1.0).unwrap();
            s.case(
                "dvr::march",
                format!("{dtype:?}, {name}, bounded by ray_sphere"),
                Expect::Finite,
                &[],
                || {
                    let h = march(field, &rays_detached, &bounds, &MarchConfig::default())?;
                    Ok(vec![h.depth, h.points])
                },
            );
            let pts = extreme_points(dtype);
            s.case(
                "dvr::occupancy_bce",
                format!("{dtype:?}, {name}, towards outside"),
                Expect::Finite,
                &[&radius],
                || Ok(vec![occupancy_bce(field, &pts, false)?]),
            );
            s.case(
                "dvr::occupancy_bce",
                format!("{dtype:?}, {name}, towards inside"),
                Expect::Finite,
                &[&radius],
                || Ok(vec![occupancy_bce(field, &pts, true)?]),
            );
            s.case(
                "dvr::normal_smoothness_loss",
                format!("{dtype:?}, {name}"),
                Expect::Finite,
                &[&radius, &center],
                || Ok(vec![normal_smoothness_loss(field, &pts, 5e-4, 1)?]),
            );
            s.case(
                "dvr::most_inside_along_rays",
                format!("{dtype:?}, {name}"),
                Expect::Finite,
                &[&radius, &origins],
                || Ok(vec![most_inside_along_rays(field, &rays, &range, 17)?]),
            );
        }
        s.case(
            "dvr::sphere_trace",
            format!("{dtype:?}, extreme rays"),
            Expect::Finite,
            &[],
            || {
                let h = sphere_trace(&sdf, &rays, &range, &SphereTraceConfig::default())?;
                Ok(vec![h.depth, h.points])
            },
        );
        s.case(
            "dvr::random_points_on_rays",
            format!("{dtype:?}"),
            Expect::Finite,
            &[&origins, &directions],
            || Ok(vec![random_points_on_rays(&rays, &range, 3)?]),
        );
        let top = if dtype == DType::F32 { 1e18 } else { 1e150 };
        let vals = var(&[0.0, 1e-30, -1e-30, top, -top, 1.0], &[6], dtype);
        let mask = Tensor::from_slice(&[1.0, 0.0, 1.0, 0.0, 1.0, 0.5], 6, &d)
            .unwrap()
            .to_dtype(dtype)
            .unwrap();
        let grads = var(
            &[
                0.0, 0.0, 0.0, 1e-30, 0.0, 0.0, top, -top, top, 1.0, 0.0, 0.0,
            ],
            &[4, 3],
            dtype,
        );
        s.case(
            "dvr::eikonal_loss",
            format!("{dtype:?}, |g| 0…{top:e}"),
            Expect::Finite,
            &[&grads],
            || Ok(vec![eikonal_loss(grads.as_tensor())?]),
        );
        for alpha in [1e-6, 50.0, 1e12] {
            s.case(
                "dvr::idr_mask_loss",
                format!("{dtype:?}, α = {alpha:e}"),
                Expect::Finite,
                &[&vals],
                || {
                    Ok(vec![idr_mask_loss(
                        vals.as_tensor(),
                        &mask,
                        Inside::Negative,
                        alpha,
                        6,
                    )?])
                },
            );
        }
        s.case(
            "dvr::depth_loss",
            format!("{dtype:?}, 0…{top:e}"),
            Expect::Finite,
            &[&vals],
            || Ok(vec![depth_loss(vals.as_tensor(), &mask, None)?]),
        );
        let pred = var(&[0.0, 1e-30, top, -top, 1.0, 0.5], &[2, 3], dtype);
        let target = Tensor::zeros((2, 3), dtype, &d).unwrap();
        for norm in [Photometric::L1, Photometric::L2] {
            let expect = if norm == Photometric::L2 && dtype == DType::F32 {
                Expect::FiniteOrErr
            } else {
                Expect::Finite
            };
            let pred = if norm == Photometric::L2 {
                var(&[0.0, 1e-30, 1e15, -1e15, 1.0, 0.5], &[2, 3], dtype)
            } else {
                pred.clone()
            };
            s.case(
                "dvr::photometric_loss",
                format!("{dtype:?}, {norm:?}"),
                expect,
                &[&pred],
                || {
                    Ok(vec![photometric_loss(
                        pred.as_tensor(),
                        &target,
                        None,
                        norm,
                    )?])
                },
            );
        }
        s.case(
            "dvr::AlphaSchedule::alpha_at",
            format!("{dtype:?}"),
            Expect::Finite,
            &[],
            || {
                let a = AlphaSchedule::default();
                Ok(vec![Tensor::new(
                    &[a.alpha_at(0), a.alpha_at(usize::MAX)],
                    &d,
                )?])
            },
        );
    }
}

/// The surface model of each kind: built, evaluated at extreme points, trained a step and
/// shaded on plain rays and on rays from extreme origins with extreme directions.
fn sweep_surface_model(s: &mut Suite) {
    use candle_nn::VarMap;
    use neural_fields::dvr::{surface_model, SurfaceKind, SurfaceModelConfig};
    use neural_fields::nn::build_seeded;
    use neural_fields::texture::{TextureField, TextureInput};
    let d = Device::Cpu;
    for dtype in DTYPES {
        let big = if dtype == DType::F32 { 1e18 } else { 1e150 };
        // Two 2 × 2 patches: rays into the box, and rays from far away, with tiny and huge
        // directions, grazing the box and along an axis.
        let o_rows = [
            [0.1, 0.0, -2.0],
            [0.0, 0.1, -2.0],
            [0.3, 0.3, -2.0],
            [0.0, 0.0, 0.1],
            [0.0, 0.0, -big],
            [1.0, 1.0, -2.0],
            [-2.0, 0.0, 0.0],
            [0.0, 0.0, -2.0],
        ]
        .concat();
        let w_rows = [
            [0.0, 0.0, 1.0],
            [0.0, 0.0, 1.0],
            [0.0, 0.0, 1.0],
            [0.0, 1.0, 0.0],
            [0.0, 0.0, 1.0],
            [0.0, 0.0, 1.0],
            [1.0, 0.0, 0.0],
            [0.0, 1e-3, 1e3],
        ]
        .concat();
        let origins = var(&o_rows, &[8, 3], dtype);
        let directions = var(&w_rows, &[8, 3], dtype);
        let rays = Rays::new(origins.as_tensor().clone(), directions.as_tensor().clone()).unwrap();
        let colors = Tensor::full(0.25, (8, 3), &d)
            .unwrap()
            .to_dtype(dtype)
            .unwrap();
        let mask = Tensor::new(&[1.0, 1.0, 0.0, 1.0, 0.0, 0.0, 1.0, 1.0], &d)
            .unwrap()
            .to_dtype(dtype)
            .unwrap();
        let pts = extreme_points(dtype);
        let dirs = Tensor::ones_like(&pts).unwrap();
        for kind in [SurfaceKind::Dvr, SurfaceKind::DvrJoint, SurfaceKind::Idr] {
            let config = SurfaceModelConfig {
                kind,
                ..SurfaceModelConfig::default()
            };
            let label = format!("{dtype:?}, {kind:?}");
            let build = || {
                build_seeded(&VarMap::new(), dtype, &d, 1, |vb| {
                    surface_model(&config, vb)
                })
            };
            s.case(
                "dvr::surface_model",
                label.clone(),
                Expect::Finite,
                &[],
                || Ok(vec![build()?.value(&pts)?]),
            );
            let model = build().unwrap();
            s.case(
                "dvr::SurfaceModel::value",
                format!("{label}, extreme points"),
                Expect::Finite,
                &[],
                || Ok(vec![model.value(&pts)?]),
            );
            s.case(
                "dvr::SurfaceModel::value_and_grad",
                format!("{label}, extreme points"),
                Expect::Finite,
                &[],
                || {
                    let (v, g) = model.value_and_grad(&pts)?;
                    Ok(vec![v, g])
                },
            );
            s.case(
                "dvr::SurfaceModel::rgb",
                format!("{label}, extreme points"),
                Expect::Finite,
                &[],
                || {
                    let input = TextureInput {
                        view_dirs: Some(&dirs),
                        ..TextureInput::new(&pts)
                    };
                    Ok(vec![model.rgb(&input)?])
                },
            );
            for progress in [0.0, 1.0] {
                s.case(
                    "dvr::SurfaceModel::loss",
                    format!("{label}, extreme rays, progress {progress}"),
                    Expect::Finite,
                    &[&origins, &directions],
                    || {
                        let l = model.loss(&rays, &colors, &mask, progress, 9)?;
                        Ok(vec![l.total, l.photometric])
                    },
                );
            }
            s.case(
                "dvr::SurfaceModel::shade",
                format!("{label}, extreme rays"),
                Expect::Finite,
                &[],
                || {
                    let seen = model.shade(&rays)?;
                    Ok(vec![seen.rgb, seen.depth, seen.coverage, seen.normals])
                },
            );
        }
    }
}
