//! The stiff-case suite: every public function that takes floating-point input is swept
//! over extreme inputs (huge and tiny magnitudes, zeros, points at singularities, f32
//! and f64) and must return finite outputs with finite gradients — or an `Err` where the
//! input is invalid. One line summarises the run; a second test scans `src/` for public
//! functions and names every one that is neither swept here nor exempted with a reason.

mod common;

use candle_core::{DType, Device, Tensor, Var};
use common::v64;
use neural_fields::camera::{
    align_cameras, align_similarity, ray_aabb, ray_sphere, reprojection_error, Camera, Convention,
    Intrinsics, PixelFilter, PoseParam, Rays, Similarity,
};
use neural_fields::encoding::{
    coarse_to_fine_weights, integrated_pe, CoarseToFine, FourierFeatures, FrequencyEncoding,
    PointEncoding,
};
use neural_fields::field::{Cuboid, Field, ImplicitSurface, Plane, SignedDistance, Sphere, Torus};
use neural_fields::glam::{DAffine3, DQuat, DVec3};
use neural_fields::nn::{build_seeded, mlp, Activation, MlpConfig};
use neural_fields::numerics::{
    bce_with_logits, cos_pi, guard_denominator, safe_cos, safe_sin, sigmoid, sin_pi, softplus,
};
use neural_fields::rng::SplitMix64;
use std::collections::BTreeSet;

const DTYPES: [DType; 2] = [DType::F32, DType::F64];

/// Magnitudes every scalar sweep visits, within the dtype's finite range.
fn magnitudes(dtype: DType) -> Vec<f64> {
    let top = if dtype == DType::F32 { 1e30 } else { 1e300 };
    let mut v = vec![
        0.0, 1e-45, 1e-30, 1e-12, 1e-6, 0.5, 1.0, 88.0, 1e4, 1e10, top,
    ];
    if dtype == DType::F64 {
        v.extend([1e-300, 1e30]);
    }
    let neg: Vec<f64> = v.iter().map(|x| -x).collect();
    v.extend(neg);
    v
}

#[derive(Default)]
struct Suite {
    cases: usize,
    failures: Vec<String>,
    covered: BTreeSet<&'static str>,
}

/// What a case may do.
#[derive(Clone, Copy, PartialEq)]
enum Expect {
    /// Must succeed with finite outputs and gradients.
    Finite,
    /// May return `Err` (invalid input); if it succeeds, outputs must be finite.
    FiniteOrErr,
}

impl Suite {
    /// Runs one case: `f` returns output tensors; gradients of their sum w.r.t. `wrt`
    /// must be finite too.
    fn case(
        &mut self,
        item: &'static str,
        label: impl Into<String>,
        expect: Expect,
        wrt: &[&Var],
        f: impl FnOnce() -> neural_fields::Result<Vec<Tensor>>,
    ) {
        self.cases += 1;
        self.covered.insert(item);
        let label = format!("{item} [{}]", label.into());
        let outputs = match f() {
            Ok(o) => o,
            Err(e) => {
                if expect == Expect::Finite {
                    self.failures.push(format!("{label}: unexpected Err: {e}"));
                }
                return;
            }
        };
        let mut loss: Option<Tensor> = None;
        for (i, t) in outputs.iter().enumerate() {
            if !matches!(t.dtype(), DType::F32 | DType::F64) {
                continue;
            }
            if first_bad(t).is_some() {
                self.failures.push(format!(
                    "{label}: output {i} not finite: {:?}",
                    first_bad(t)
                ));
                return;
            }
            let s = t.to_dtype(DType::F64).unwrap().sum_all().unwrap();
            loss = Some(match loss {
                None => s,
                Some(l) => (l + s).unwrap(),
            });
        }
        if wrt.is_empty() {
            return;
        }
        let Some(loss) = loss else { return };
        let grads = match loss.backward() {
            Ok(g) => g,
            Err(e) => {
                self.failures.push(format!("{label}: backward failed: {e}"));
                return;
            }
        };
        for (j, v) in wrt.iter().enumerate() {
            if let Some(g) = grads.get(v) {
                if first_bad(g).is_some() {
                    self.failures.push(format!(
                        "{label}: gradient {j} not finite: {:?}",
                        first_bad(g)
                    ));
                }
            }
        }
    }
}

fn first_bad(t: &Tensor) -> Option<f64> {
    v64(t).into_iter().find(|x| !x.is_finite())
}

fn var(values: &[f64], shape: &[usize], dtype: DType) -> Var {
    Var::from_tensor(
        &Tensor::from_slice(values, shape, &Device::Cpu)
            .unwrap()
            .to_dtype(dtype)
            .unwrap(),
    )
    .unwrap()
}

fn sweep_numerics(s: &mut Suite) {
    for dtype in DTYPES {
        let xs = magnitudes(dtype);
        let n = xs.len();
        let x = var(&xs, &[n], dtype);
        let t = x.as_tensor();
        let half = Tensor::full(0.5f64, n, &Device::Cpu)
            .unwrap()
            .to_dtype(dtype)
            .unwrap();
        let tag = format!("{dtype:?}, |x| up to max");
        s.case("numerics::safe_sin", &tag, Expect::Finite, &[&x], || {
            Ok(vec![safe_sin(t)?])
        });
        s.case("numerics::safe_cos", &tag, Expect::Finite, &[&x], || {
            Ok(vec![safe_cos(t)?])
        });
        s.case("numerics::sin_pi", &tag, Expect::Finite, &[&x], || {
            Ok(vec![sin_pi(t)?])
        });
        s.case("numerics::cos_pi", &tag, Expect::Finite, &[&x], || {
            Ok(vec![cos_pi(t)?])
        });
        s.case("numerics::sigmoid", &tag, Expect::Finite, &[&x], || {
            Ok(vec![sigmoid(t)?])
        });
        for beta in [1e-3, 1.0, 100.0, 1e6] {
            // softplus_β(x) ≈ x for large x: finite as long as x is.
            s.case(
                "numerics::softplus",
                format!("{tag}, β = {beta}"),
                Expect::Finite,
                &[&x],
                || Ok(vec![softplus(t, beta)?]),
            );
        }
        s.case(
            "numerics::bce_with_logits",
            &tag,
            Expect::Finite,
            &[&x],
            || Ok(vec![bce_with_logits(t, &half)?]),
        );
        // guard bounds 1/x by 1/eps and its derivative by 1/eps²; eps must keep 1/eps²
        // representable (≥ 5.4e-20 in f32), which is the caller's choice.
        let tiny_eps = if dtype == DType::F32 { 1e-19 } else { 1e-150 };
        for eps in [tiny_eps, 1e-3, 1.0] {
            s.case(
                "numerics::guard_denominator",
                format!("{tag}, eps = {eps}"),
                Expect::Finite,
                &[&x],
                || Ok(vec![guard_denominator(t, eps)?.recip()?]),
            );
        }
    }
}

/// Points at the origin, on axes, tiny and huge, for shape sweeps.
fn extreme_points(dtype: DType) -> Tensor {
    let big = if dtype == DType::F32 { 1e30 } else { 1e150 };
    let rows: Vec<[f64; 3]> = vec![
        [0.0, 0.0, 0.0],
        [0.0, 0.0, 1e-30],
        [1e-30, 0.0, 0.0],
        [0.3, 0.0, 0.0],
        [0.0, 0.0, 0.3],
        [0.5, 0.5, 0.5],
        [big, 0.0, 0.0],
        [-big, big, -big],
        [1e10, -1e10, 3.0],
    ];
    let flat: Vec<f64> = rows.concat();
    Tensor::from_vec(flat, (rows.len(), 3), &Device::Cpu)
        .unwrap()
        .to_dtype(dtype)
        .unwrap()
}

fn sweep_fields(s: &mut Suite) {
    let d = Device::Cpu;
    for dtype in DTYPES {
        let p = Var::from_tensor(&extreme_points(dtype)).unwrap();
        let pt = p.as_tensor();
        for (scale, tag) in [(1.0, "unit"), (1e-20, "tiny shape"), (1e20, "huge shape")] {
            let label = format!("{dtype:?}, {tag}");
            s.case("field::Sphere::new", &label, Expect::Finite, &[&p], || {
                let (v, g) = Sphere::new([0.0; 3], 0.3 * scale, &d, dtype)?
                    .sdf()
                    .value_and_grad(pt)?;
                Ok(vec![v, g])
            });
            s.case("field::Cuboid::new", &label, Expect::Finite, &[&p], || {
                let (v, g) =
                    Cuboid::new([0.0; 3], [0.3 * scale, 0.2 * scale, 0.1 * scale], &d, dtype)?
                        .sdf()
                        .value_and_grad(pt)?;
                Ok(vec![v, g])
            });
            s.case("field::Torus::new", &label, Expect::Finite, &[&p], || {
                let (v, g) = Torus::new([0.0; 3], 0.3 * scale, 0.1 * scale, &d, dtype)?
                    .sdf()
                    .value_and_grad(pt)?;
                Ok(vec![v, g])
            });
            s.case("field::Plane::new", &label, Expect::Finite, &[&p], || {
                let (v, g) = Plane::new([0.0, 0.0, scale], 0.1, &d, dtype)?
                    .sdf()
                    .value_and_grad(pt)?;
                Ok(vec![v, g])
            });
        }
        // Occupancy logits −k·d: finite while k·|d| is representable.
        s.case(
            "field::Sphere::new",
            format!("{dtype:?}, occupancy k = 100"),
            Expect::Finite,
            &[&p],
            || {
                let (v, g) = Sphere::new([0.0; 3], 0.3, &d, dtype)?
                    .occupancy(100.0)
                    .value_and_grad(pt)?;
                Ok(vec![v, g])
            },
        );
    }
}

fn sweep_encodings(s: &mut Suite) {
    let d = Device::Cpu;
    for dtype in DTYPES {
        let big = if dtype == DType::F32 { 1e20 } else { 1e100 };
        let vals = [0.0, 1e-30, -1e-30, 1.0, -3.0, 1e10, -1e10, big, -big];
        let x = var(&vals, &[3, 3], dtype);
        let t = x.as_tensor();
        let dx = Tensor::ones((3, 2, 3), dtype, &d).unwrap();
        let label = format!("{dtype:?}, |x| up to {big:e}");
        for l in [0usize, 4, 10] {
            s.case(
                "encoding::FrequencyEncoding::forward_jvp",
                format!("{label}, L = {l}"),
                Expect::Finite,
                &[&x],
                || {
                    let mut pe = FrequencyEncoding::new(3, l)?;
                    pe.use_pi = false;
                    let enc = PointEncoding::Frequency(pe);
                    let (v, j) = enc.forward_jvp(t, &dx)?;
                    Ok(vec![v, j, enc.forward(t)?])
                },
            );
        }
        for scale in [1e-10, 1.0, 100.0] {
            s.case(
                "encoding::FourierFeatures::new",
                format!("{label}, s = {scale}"),
                Expect::Finite,
                &[&x],
                || {
                    let enc =
                        PointEncoding::Fourier(FourierFeatures::new(3, 8, scale, 1, &d, dtype)?);
                    let (v, j) = enc.forward_jvp(t, &dx)?;
                    Ok(vec![v, j])
                },
            );
        }
        s.case(
            "encoding::FourierFeatures::from_matrix",
            &label,
            Expect::Finite,
            &[&x],
            || {
                let b = Tensor::from_slice(&[1e-20, 1.0, 0.0, 3.0, -1e3, 0.5], (2, 3), &d)?
                    .to_dtype(dtype)?;
                let enc = PointEncoding::Fourier(FourierFeatures::from_matrix(b)?);
                Ok(vec![enc.forward(t)?])
            },
        );
        s.case(
            "encoding::PointEncoding::forward",
            &label,
            Expect::Finite,
            &[&x],
            || Ok(vec![PointEncoding::Identity.forward(t)?]),
        );
        let var_vals = [0.0, 1e-30, 1e30f64.min(big), 1.0, 0.0, 5.0, 1e-10, 2.0, 0.0];
        let v = var(&var_vals, &[3, 3], dtype);
        s.case(
            "encoding::integrated_pe",
            &label,
            Expect::Finite,
            &[&x, &v],
            || Ok(vec![integrated_pe(t, v.as_tensor(), 0, 16)?]),
        );
        // BARF's window at α below, inside and beyond the bands, over the same inputs.
        for alpha in [f64::NEG_INFINITY, -1e300, 0.0, 2.5, 1e300, f64::INFINITY] {
            for item in [
                "encoding::coarse_to_fine::CoarseToFine::forward",
                "encoding::coarse_to_fine::CoarseToFine::forward_jvp",
                "encoding::coarse_to_fine::CoarseToFine::new",
                "encoding::coarse_to_fine::CoarseToFine::set_alpha",
                "encoding::coarse_to_fine::CoarseToFine::column_weights",
                "encoding::coarse_to_fine::coarse_to_fine_weights",
            ] {
                s.case(
                    item,
                    format!("{label}, α = {alpha:e}"),
                    Expect::Finite,
                    &[&x],
                    || {
                        let mut pe = FrequencyEncoding::new(3, 4)?;
                        pe.use_pi = false;
                        let c = CoarseToFine::new(PointEncoding::Frequency(pe))?;
                        c.set_alpha(alpha)?;
                        let w = Tensor::new(c.column_weights(), &d)?;
                        let weights = Tensor::new(coarse_to_fine_weights(alpha, 4)?, &d)?;
                        let (v, j) = c.forward_jvp(t, &dx)?;
                        Ok(vec![c.forward(t)?, w, weights, v, j])
                    },
                );
            }
        }
        let neg = var(&[-1.0; 9], &[3, 3], dtype);
        // Negative variances are not a Gaussian: growing terms, documented as data; must not be NaN.
        s.case(
            "encoding::integrated_pe",
            format!("{dtype:?}, negative variances"),
            Expect::FiniteOrErr,
            &[&neg],
            || {
                Ok(vec![integrated_pe(
                    &Tensor::zeros((3, 3), dtype, &d)?,
                    neg.as_tensor(),
                    0,
                    4,
                )?])
            },
        );
    }
}

/// The hash grid on extreme positions (clamped into the box), both paths, f32 and f64,
/// with gradients to the positions and the table; a NaN position must be an `Err`.
fn sweep_hash_grid(s: &mut Suite) {
    use neural_fields::encoding::{hash_grid, Encoding, HashGridConfig};
    let d = Device::Cpu;
    for dtype in DTYPES {
        let big = if dtype == DType::F32 { 1e30 } else { 1e300 };
        let vals = [0.0, 1e-30, -1e-30, 1.0, -1.0, 1e10, -big, big, 0.999_999];
        let x = var(&vals, &[3, 3], dtype);
        let t = x.as_tensor();
        let label = format!("{dtype:?}, |x| up to {big:e}");
        let varmap = candle_nn::VarMap::new();
        let vb = candle_nn::VarBuilder::from_varmap(&varmap, dtype, &d);
        let config = HashGridConfig {
            levels: 4,
            log2_table_size: 8,
            finest_resolution: 1e6,
            ..HashGridConfig::default()
        };
        let grid = hash_grid(&config, vb).unwrap();
        let table = varmap.all_vars().remove(0);
        s.case(
            "encoding::hash_grid::hash_grid",
            format!("{dtype:?}, resolutions 16 to 1e6"),
            Expect::Finite,
            &[],
            || Ok(vec![grid.table().clone()]),
        );
        s.case(
            "encoding::hash_grid::HashGrid::forward",
            &label,
            Expect::Finite,
            &[&x, &table],
            || Ok(vec![grid.forward(t)?]),
        );
        s.case(
            "encoding::hash_grid::HashGrid::forward_reference",
            &label,
            Expect::Finite,
            &[&x, &table],
            || Ok(vec![grid.forward_reference(t)?]),
        );
        let dx = Tensor::ones((3, 2, 3), dtype, &d).unwrap();
        s.case(
            "encoding::hash_grid::HashGrid::forward_jvp",
            &label,
            Expect::Finite,
            &[&x, &table],
            || {
                let (v, j) = grid.forward_jvp(t, &dx)?;
                Ok(vec![v, j])
            },
        );
        let nan = Tensor::from_slice(&[f64::NAN, 0.0, 0.0], (1, 3), &d)
            .unwrap()
            .to_dtype(dtype)
            .unwrap();
        if grid.forward(&nan).is_ok() || grid.forward_reference(&nan).is_ok() {
            s.failures.push(format!(
                "HashGrid::forward [{dtype:?}]: a NaN position gave Ok"
            ));
        }
    }
}

/// Point clouds at three scales through their constructors, sampling, tensors and files,
/// and the mesh formats' round trips.
#[cfg(feature = "occupancy")]
fn sweep_point_clouds(s: &mut Suite) {
    use neural_fields::occupancy::{Mesh, MeshFormat, PointCloud};
    let d = Device::Cpu;
    let flat = |v: &[[f64; 3]]| Tensor::from_vec(v.concat(), v.len() * 3, &d);
    for scale in [1e-300, 1e-6, 1.0, 1e6, 1e300] {
        let label = format!("scale {scale:e}");
        let pts = vec![[0.0, 0.0, 0.0], [scale, 0.0, 0.0], [0.0, scale, -scale]];
        let normals = vec![[0.0, 0.0, scale]; 3];
        s.case(
            "occupancy::point_cloud::PointCloud::new",
            &label,
            Expect::Finite,
            &[],
            || Ok(vec![flat(PointCloud::new(pts.clone())?.points())?]),
        );
        s.case(
            "occupancy::point_cloud::PointCloud::with_normals",
            &label,
            Expect::Finite,
            &[],
            || {
                let c = PointCloud::new(pts.clone())?.with_normals(normals.clone())?;
                Ok(vec![flat(c.normals().unwrap_or(&[]))?])
            },
        );
        s.case(
            "occupancy::point_cloud::PointCloud::with_colors",
            &label,
            Expect::Finite,
            &[],
            || {
                let c = PointCloud::new(pts.clone())?.with_colors(vec![[0.0, 0.5, 1.0]; 3])?;
                Ok(vec![flat(c.colors().unwrap_or(&[]))?])
            },
        );
        let cloud = PointCloud::new(pts.clone())
            .unwrap()
            .with_normals(normals.clone())
            .unwrap();
        s.case(
            "occupancy::point_cloud::PointCloud::sample",
            &label,
            Expect::Finite,
            &[],
            || Ok(vec![flat(cloud.sample(7, 1)?.points())?]),
        );
        for dtype in DTYPES {
            // f32 overflows beyond 3.4e38: an infinite tensor would be a silent result.
            let expect = if dtype == DType::F32 && scale > 1e38 {
                Expect::FiniteOrErr
            } else {
                Expect::Finite
            };
            s.case(
                "occupancy::point_cloud::PointCloud::to_tensor",
                format!("{label}, {dtype:?}"),
                expect,
                &[],
                || Ok(vec![cloud.to_tensor(&d, dtype)?]),
            );
            s.case(
                "occupancy::point_cloud::PointCloud::normals_tensor",
                format!("{label}, {dtype:?}"),
                expect,
                &[],
                || Ok(vec![cloud.normals_tensor(&d, dtype)?]),
            );
        }
        for format in [MeshFormat::PlyAscii, MeshFormat::PlyBinary] {
            s.case(
                "occupancy::point_cloud::PointCloud::to_bytes",
                format!("{label}, {format:?}"),
                Expect::FiniteOrErr,
                &[],
                || {
                    let bytes = cloud.to_bytes(format)?;
                    Ok(vec![flat(
                        PointCloud::from_bytes(&bytes, format)?.points(),
                    )?])
                },
            );
            s.case(
                "occupancy::point_cloud::PointCloud::from_bytes",
                format!("{label}, {format:?}"),
                Expect::FiniteOrErr,
                &[],
                || {
                    Ok(vec![flat(
                        PointCloud::from_bytes(&cloud.to_bytes(format)?, format)?.points(),
                    )?])
                },
            );
        }
        let path = std::env::temp_dir().join(format!("nf-stiff-cloud-{}.ply", std::process::id()));
        s.case(
            "occupancy::point_cloud::PointCloud::save",
            &label,
            Expect::FiniteOrErr,
            &[],
            || {
                cloud.save(&path)?;
                Ok(vec![flat(PointCloud::load(&path)?.points())?])
            },
        );
        s.case(
            "occupancy::point_cloud::PointCloud::load",
            &label,
            Expect::FiniteOrErr,
            &[],
            || {
                let c = PointCloud::load(&path)?;
                let _ = std::fs::remove_file(&path);
                Ok(vec![flat(c.points())?])
            },
        );
        // The mesh formats: a tetrahedron at this scale through STL and OFF.
        let tet = Mesh::new(
            vec![
                [0.0; 3],
                [scale, 0.0, 0.0],
                [0.0, scale, 0.0],
                [0.0, 0.0, scale],
            ],
            vec![[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]],
        )
        .unwrap();
        for format in [MeshFormat::StlAscii, MeshFormat::StlBinary, MeshFormat::Off] {
            s.case(
                "occupancy::mesh::Mesh::from_bytes",
                format!("{label}, {format:?}"),
                Expect::FiniteOrErr,
                &[],
                || {
                    Ok(vec![flat(
                        &Mesh::from_bytes(&tet.to_bytes(format)?, format)?.vertices,
                    )?])
                },
            );
        }
    }
}

fn sweep_mlp(s: &mut Suite) {
    let d = Device::Cpu;
    for dtype in DTYPES {
        let big = if dtype == DType::F32 { 1e8 } else { 1e100 };
        let x = var(
            &[
                0.0, 0.0, 0.0, 1e-30, 0.0, 0.0, big, -big, big, 1e4, 1.0, -1e4,
            ],
            &[4, 3],
            dtype,
        );
        for (activation, radius, tag) in [
            (Activation::Relu, None, "ReLU"),
            (
                Activation::Softplus { beta: 100.0 },
                Some(0.5),
                "softplus(100), geometric init",
            ),
            (Activation::Softplus { beta: 1e-3 }, None, "softplus(1e-3)"),
        ] {
            let config = MlpConfig {
                hidden: 16,
                depth: 3,
                skips: vec![2],
                activation,
                geometric_init: radius,
                encoding: PointEncoding::Frequency(FrequencyEncoding::new(3, 4).unwrap()),
                ..MlpConfig::default()
            };
            let varmap = candle_nn::VarMap::new();
            let net = build_seeded(&varmap, dtype, &d, 3, |vb| mlp(&config, vb)).unwrap();
            let label = format!("{dtype:?}, {tag}, |x| up to {big:e}");
            let vars = varmap.all_vars();
            let mut wrt: Vec<&Var> = vars.iter().collect();
            wrt.push(&x);
            s.case("nn::mlp::mlp", &label, Expect::Finite, &[], || Ok(vec![]));
            s.case(
                "nn::mlp::Mlp::forward_with_jacobian",
                &label,
                Expect::Finite,
                &wrt,
                || {
                    let (y, j) = net.forward_with_jacobian(x.as_tensor(), None)?;
                    Ok(vec![y, j])
                },
            );
            s.case(
                "nn::mlp::Mlp::forward",
                &label,
                Expect::Finite,
                &wrt,
                || Ok(vec![Field::forward(&net, x.as_tensor())?]),
            );
            s.case(
                "nn::mlp::MlpConfig::sdf",
                &label,
                Expect::Finite,
                &[],
                || {
                    Ok(vec![Tensor::new(
                        MlpConfig::sdf(1e-30).geometric_init.unwrap_or(0.0),
                        &d,
                    )?])
                },
            );
        }
    }
}

fn sweep_camera(s: &mut Suite) {
    let d = Device::Cpu;
    for dtype in DTYPES {
        let tag = format!("{dtype:?}");
        for (fx, w) in [(1e-6, 1usize), (500.0, 64), (1e8, 8)] {
            s.case(
                "camera::Intrinsics::new",
                format!("{tag}, fx = {fx}"),
                Expect::Finite,
                &[],
                || {
                    let k = Intrinsics::new(fx, fx, w as f64 / 2.0, w as f64 / 2.0, w, w)?;
                    let px =
                        Tensor::from_slice(&[0.0, 0.0, 1e6, -1e6], (2, 2), &d)?.to_dtype(dtype)?;
                    let cam = Camera::new(k, DAffine3::IDENTITY, Convention::OpenCv)?;
                    Ok(vec![cam.rays_for_pixels(&px)?.directions().clone()])
                },
            );
        }
        // The camera-space directions of 0.1's `Intrinsics::camera_directions`: an
        // identity pose, a field of view near π.
        s.case(
            "camera::Camera::rays_for_pixels",
            format!("{tag}, identity pose, fov 3.1"),
            Expect::Finite,
            &[],
            || {
                let k = Intrinsics::from_fov_y(4, 4, 3.1)?;
                let cam = Camera::new(k, DAffine3::IDENTITY, Convention::OpenGl)?;
                Ok(vec![cam
                    .rays_for_pixels(&Tensor::zeros((1, 2), dtype, &d)?)?
                    .directions()
                    .clone()])
            },
        );
        for fov in [1e-12, 1.0, std::f64::consts::PI - 1e-6] {
            s.case(
                "camera::Intrinsics::from_fov_y",
                format!("{tag}, fov = {fov}"),
                Expect::Finite,
                &[],
                || {
                    let k = Intrinsics::from_fov_y(8, 8, fov)?;
                    let cam = Camera::new(k, DAffine3::IDENTITY, Convention::OpenCv)?;
                    Ok(vec![cam
                        .rays_for_pixels(&Tensor::zeros((1, 2), dtype, &d)?)?
                        .directions()
                        .clone()])
                },
            );
        }
        for eye in [
            DVec3::new(0.0, 0.0, 1e-8),
            DVec3::new(1e8, 1e8, 1e8),
            DVec3::new(0.0, 1e-3, 3.0),
        ] {
            let label = format!("{tag}, eye = {eye}");
            let k = Intrinsics::from_fov_y(4, 3, 0.8).unwrap();
            s.case(
                "camera::Camera::look_at",
                &label,
                Expect::Finite,
                &[],
                || {
                    Ok(vec![Camera::look_at(
                        k,
                        eye,
                        DVec3::ZERO,
                        DVec3::Y,
                        Convention::OpenGl,
                    )?
                    .rays(&d, dtype)?
                    .directions()
                    .clone()])
                },
            );
            let cam = Camera::look_at(k, eye, DVec3::ZERO, DVec3::Y, Convention::OpenGl).unwrap();
            s.case("camera::Camera::rays", &label, Expect::Finite, &[], || {
                let r = cam.rays(&d, dtype)?;
                Ok(vec![r.origins().clone(), r.directions().clone()])
            });
            s.case(
                "camera::Camera::pixel_grid",
                &label,
                Expect::Finite,
                &[],
                || Ok(vec![cam.pixel_grid(&d, dtype)?]),
            );
            let filters = [
                PixelFilter::Box,
                PixelFilter::CYCLES,
                PixelFilter::BlackmanHarris { half_width: 64.0 },
                PixelFilter::BlackmanHarris { half_width: 1e-300 },
                PixelFilter::BlackmanHarris {
                    half_width: f64::NAN,
                },
            ];
            for (k, filter) in [1, 3, 64, 65]
                .into_iter()
                .flat_map(|k| filters.map(|f| (k, f)))
            {
                s.case(
                    "camera::Camera::subpixel_grid",
                    format!("{label}, k = {k}, {filter:?}"),
                    if k <= 64 && filter.validate().is_ok() {
                        Expect::Finite
                    } else {
                        Expect::FiniteOrErr
                    },
                    &[],
                    || {
                        let g = cam.subpixel_grid(k, filter, &d, dtype)?;
                        let r = cam.rays_for_pixels(&g)?;
                        Ok(vec![g, r.directions().clone()])
                    },
                );
            }
            for filter in filters {
                for u in [0.0, 1e-300, 0.5, 1.0 - f64::EPSILON, 1.0, -1e-300, f64::NAN] {
                    s.case(
                        "camera::PixelFilter::quantile",
                        format!("{filter:?}, u = {u:e}"),
                        if (0.0..=1.0).contains(&u) && filter.validate().is_ok() {
                            Expect::Finite
                        } else {
                            Expect::FiniteOrErr
                        },
                        &[],
                        || {
                            Ok(vec![
                                Tensor::new(&[filter.quantile(u)?], &d)?.to_dtype(dtype)?
                            ])
                        },
                    );
                }
            }
            s.case(
                "camera::Camera::random_rays",
                &label,
                Expect::Finite,
                &[],
                || {
                    let (r, i) = cam.random_rays(16, 1, &d, dtype)?;
                    Ok(vec![r.origins().clone(), r.directions().clone(), i])
                },
            );
            s.case(
                "camera::Camera::rays_for_pixels",
                &label,
                Expect::Finite,
                &[],
                || {
                    let px = Tensor::from_slice(&[1e-30, 1e6], (1, 2), &d)?.to_dtype(dtype)?;
                    Ok(vec![cam.rays_for_pixels(&px)?.directions().clone()])
                },
            );
            s.case(
                "camera::Camera::pose_param",
                &label,
                Expect::Finite,
                &[],
                || Ok(vec![cam.pose_param(&d, dtype)?.rotation_matrix()?]),
            );
        }
        s.case(
            "camera::Camera::new",
            format!("{tag}, translation 1e12"),
            Expect::Finite,
            &[],
            || {
                let pose = DAffine3::from_rotation_translation(
                    DQuat::from_rotation_y(0.3),
                    DVec3::splat(1e12),
                );
                Ok(vec![Camera::new(
                    Intrinsics::from_fov_y(2, 2, 1.0)?,
                    pose,
                    Convention::OpenCv,
                )?
                .rays(&d, dtype)?
                .origins()
                .clone()])
            },
        );
        // Rays: huge and tiny origins and directions, exact zeros in direction components.
        // In f32 a unit sphere 1e15 away is below resolution (ulp(1e15) ≈ 7e7): r² is lost
        // in |o − c|² − r², and candle's division backward (grad·lhs/rhs²) overflows an
        // intermediate although the true gradient is finite. f32 sweeps stay within 1e6.
        let big = if dtype == DType::F32 { 1e6 } else { 1e100 };
        let o = var(
            &[
                0.0, 0.0, -3.0, 1e-30, 0.5, -big, 2.0, 2.0, 2.0, 0.0, 0.0, 0.0,
            ],
            &[4, 3],
            dtype,
        );
        // ∂t/∂d ≈ t/|d|: a direction of length 1e-20 from inside a unit box has a true
        // gradient of 1e40, beyond f32; f32 sweeps directions down to 1e-9.
        let short = if dtype == DType::F32 { 1e-9 } else { 1e-20 };
        let w = var(
            &[
                0.0, 0.0, 1.0, 0.0, 0.0, 1e-10, 1e10, 0.0, 0.0, short, short, short,
            ],
            &[4, 3],
            dtype,
        );
        let t = var(&[0.0, 1e-30, 1e10, 1.0], &[4], dtype);
        let label = format!("{tag}, origins up to {big:e}, directions {short:e}…1e10");
        s.case(
            "camera::Rays::new",
            &label,
            Expect::Finite,
            &[&o, &w, &t],
            || {
                let r = Rays::new(o.as_tensor().clone(), w.as_tensor().clone())?;
                Ok(vec![r.at(t.as_tensor())?])
            },
        );
        s.case(
            "camera::Rays::at",
            &label,
            Expect::Finite,
            &[&o, &w, &t],
            || {
                Ok(vec![Rays::new(
                    o.as_tensor().clone(),
                    w.as_tensor().clone(),
                )?
                .at(t.as_tensor())?])
            },
        );
        s.case(
            "camera::Rays::normalized",
            &label,
            Expect::Finite,
            &[&w],
            || {
                Ok(vec![Rays::new(
                    o.as_tensor().clone(),
                    w.as_tensor().clone(),
                )?
                .normalized()?
                .directions()
                .clone()])
            },
        );
        s.case(
            "camera::Rays::narrow",
            &label,
            Expect::Finite,
            &[&o],
            || {
                Ok(vec![Rays::new(
                    o.as_tensor().clone(),
                    w.as_tensor().clone(),
                )?
                .narrow(1, 2)?
                .origins()
                .clone()])
            },
        );
        s.case(
            "camera::ray_aabb",
            &label,
            Expect::FiniteOrErr,
            &[&o, &w],
            || {
                let rays = Rays::new(o.as_tensor().clone(), w.as_tensor().clone())?;
                let i = ray_aabb(&rays, [-1.0; 3], [1.0; 3])?;
                Ok(vec![i.near, i.far, i.hit])
            },
        );
        s.case(
            "camera::ray_sphere",
            &label,
            Expect::FiniteOrErr,
            &[&o, &w],
            || {
                let rays = Rays::new(o.as_tensor().clone(), w.as_tensor().clone())?;
                let i = ray_sphere(&rays, [0.0; 3], 1.0)?;
                Ok(vec![i.near, i.far, i.hit])
            },
        );
        // Explicit search ranges: empty, tiny, huge and negative bounds; and far < near,
        // which must be an Err.
        let nf_big = if dtype == DType::F32 { 1e30 } else { 1e300 };
        let near = var(&[0.0, 1e-30, 1e10, -nf_big], &[4], dtype);
        let far = var(&[0.0, 2e-30, 1e10, nf_big], &[4], dtype);
        s.case(
            "camera::Intersection::new",
            format!("{tag}, bounds ±{nf_big:e}"),
            Expect::Finite,
            &[&near, &far],
            || {
                let i = neural_fields::camera::Intersection::new(
                    near.as_tensor().clone(),
                    far.as_tensor().clone(),
                )?;
                Ok(vec![i.near, i.far, i.hit])
            },
        );
        s.case(
            "camera::Intersection::new",
            format!("{tag}, far < near"),
            Expect::FiniteOrErr,
            &[],
            || {
                let i = neural_fields::camera::Intersection::new(
                    far.as_tensor().clone(),
                    near.as_tensor().affine(1.0, -1.0)?,
                )?;
                Ok(vec![i.near, i.far, i.hit])
            },
        );
        // Learnable pose with a tiny and a huge quaternion.
        for qs in [1e-6, 1.0, 1e6] {
            let label = format!("{tag}, |q| = {qs}");
            let pose = DAffine3::from_rotation_translation(
                DQuat::from_rotation_x(0.7),
                DVec3::new(0.0, 1.0, 5.0),
            );
            let k = Intrinsics::from_fov_y(8, 8, 1.0).unwrap();
            let p = PoseParam::from_affine(&pose, &d, dtype).unwrap();
            p.rotation
                .set(&p.rotation.as_tensor().affine(qs, 0.0).unwrap())
                .unwrap();
            let px = Tensor::from_slice(&[0.5, 0.5, 7.5, 7.5], (2, 2), &d)
                .unwrap()
                .to_dtype(dtype)
                .unwrap();
            s.case(
                "camera::PoseParam::rays",
                &label,
                Expect::Finite,
                &[&p.rotation, &p.translation],
                || {
                    let r = p.rays(&k, Convention::OpenCv, &px)?;
                    Ok(vec![r.origins().clone(), r.directions().clone()])
                },
            );
            s.case(
                "camera::PoseParam::rotation_matrix",
                &label,
                Expect::Finite,
                &[&p.rotation],
                || Ok(vec![p.rotation_matrix()?]),
            );
            s.case(
                "camera::PoseParam::from_affine",
                &label,
                Expect::Finite,
                &[],
                || Ok(vec![p.translation.as_tensor().clone()]),
            );
            s.case(
                "camera::PoseParam::to_affine",
                &label,
                Expect::Finite,
                &[],
                || {
                    let a = p.to_affine()?;
                    Ok(vec![Tensor::new(a.matrix3.to_cols_array().as_slice(), &d)?])
                },
            );
            s.case(
                "camera::PoseParam::renormalize",
                &label,
                Expect::Finite,
                &[],
                || {
                    p.renormalize()?;
                    Ok(vec![p.rotation.as_tensor().clone()])
                },
            );
        }
    }
}

fn sweep_rng(s: &mut Suite) {
    let d = Device::Cpu;
    for dtype in DTYPES {
        let tag = format!("{dtype:?}");
        for (a, b) in [(0.0f64, 1e-30f64), (-1e30, 1e30), (1e10, 1e10)] {
            s.case(
                "rng::SplitMix64::normal_tensor",
                format!("{tag}, mean {a}, std {b}"),
                Expect::Finite,
                &[],
                || {
                    Ok(vec![SplitMix64::new(1).normal_tensor(
                        &[64],
                        a,
                        b.abs(),
                        dtype,
                        &d,
                    )?])
                },
            );
            s.case(
                "rng::SplitMix64::uniform_tensor",
                format!("{tag}, [{a}, {b})"),
                Expect::Finite,
                &[],
                || {
                    Ok(vec![SplitMix64::new(1).uniform_tensor(
                        &[64],
                        a,
                        b,
                        dtype,
                        &d,
                    )?])
                },
            );
        }
    }
}

#[cfg(feature = "volume")]
fn sweep_volume(s: &mut Suite) {
    use neural_fields::volume::{
        accumulate, anneal_near_far, composite, depth_smoothness, distortion_loss,
        log_linear_schedule, merge_sorted, render_weights, sample_pdf, step_cdf, stratified,
        trunc_exp, visible_mask, Composite, CompositeConfig, GridConfig, GridMarchConfig,
        Intervals, Jitter, Layout, OccupancyGrid, Packed,
    };
    let d = Device::Cpu;
    let (r, n) = (7usize, 5usize);
    let occupied_fraction = |g: &OccupancyGrid| {
        g.occupied().iter().filter(|&&o| o).count() as f64 / g.occupied().len() as f64
    };
    for dtype in DTYPES {
        let huge = if dtype == DType::F32 { 1e30 } else { 1e300 };
        // Rows: empty, tiny, huge, one opaque slab, f32 transmittance underflow along a long
        // ray (σδ summing to 5e5), mixed extremes, huge steps.
        let sig = [
            [0.0; 5],
            [1e-30; 5],
            [huge; 5],
            [0.0, 0.0, 1e10, 0.0, 0.0],
            [100.0; 5],
            [1e-10, 1e10, 0.0, 1e-30, huge],
            [1.0; 5],
        ]
        .concat();
        let del = [
            [0.1; 5],
            [1e-30; 5],
            [1e-30; 5],
            [0.2; 5],
            [1e3; 5],
            [1e-30, 1e10, 0.0, 1.0, 1e-10],
            [1e10; 5],
        ]
        .concat();
        let sigmas = var(&sig, &[r, n], dtype);
        // The intervals with lengths δ, each ray starting at t = 0 (the depths t are their
        // midpoints, up to 5e10); learnable, so gradients reach starts and ends.
        let (st_h, en_h) = common::intervals::starts_ends(&del, &[n; 7]);
        let starts = var(&st_h, &[r, n], dtype);
        let ends = var(&en_h, &[r, n], dtype);
        let iv = Intervals::new(starts.as_tensor().clone(), ends.as_tensor().clone()).unwrap();
        let mut rng = SplitMix64::new(5);
        let colors =
            Var::from_tensor(&rng.uniform_tensor(&[r, n, 3], 0.0, 1.0, dtype, &d).unwrap())
                .unwrap();
        // Directions of norm 2 (δ doubled) for the cases with rays.
        let dirs = var(&[0.0, 0.0, 2.0].repeat(r), &[r, 3], dtype);
        let rays = Rays::new(
            Tensor::zeros((r, 3), dtype, &d).unwrap(),
            dirs.as_tensor().clone(),
        )
        .unwrap();
        let wrt = [&sigmas, &starts, &ends, &colors];
        let wrt_rays = [&sigmas, &starts, &ends, &colors, &dirs];
        for opaque_last in [false, true] {
            let label = format!("{dtype:?}, σ 0…{huge:e}, δ 0…1e10, opaque_last = {opaque_last}");
            let bg = Tensor::ones(3, dtype, &d).unwrap();
            let cfg = CompositeConfig {
                opaque_last,
                background: Some(bg),
                force_reference: false,
            };
            let reference = CompositeConfig {
                force_reference: true,
                ..cfg.clone()
            };
            let no_bg = CompositeConfig {
                opaque_last,
                ..CompositeConfig::default()
            };
            let (st, ct) = (sigmas.as_tensor(), colors.as_tensor());
            let out = |c: Composite| -> neural_fields::Result<Vec<Tensor>> {
                let nd = c.normalized_depth(1e-10)?;
                Ok(vec![c.color, c.opacity, c.depth, nd])
            };
            // On the CPU `composite` runs the fused kernel (0.1's `composite_fused`).
            s.case(
                "volume::composite::composite",
                &label,
                Expect::Finite,
                &wrt,
                || out(composite(st, ct, &iv, None, &cfg)?),
            );
            s.case(
                "volume::composite::composite",
                format!("{label}, reference path"),
                Expect::Finite,
                &wrt,
                || out(composite(st, ct, &iv, None, &reference)?),
            );
            s.case(
                "volume::composite::composite",
                format!("{label}, rays with |d| = 2"),
                Expect::Finite,
                &wrt_rays,
                || out(composite(st, ct, &iv, Some(&rays), &cfg)?),
            );
            s.case(
                "volume::composite::composite",
                format!("{label}, rays with |d| = 2, reference path"),
                Expect::Finite,
                &wrt_rays,
                || out(composite(st, ct, &iv, Some(&rays), &reference)?),
            );
            s.case(
                "volume::composite::Composite::normalized_depth",
                &label,
                Expect::Finite,
                &wrt,
                || out(composite(st, ct, &iv, None, &reference)?),
            );
            s.case(
                "volume::composite::render_weights",
                &label,
                Expect::Finite,
                &[&sigmas, &starts, &ends],
                || {
                    let w = render_weights(st, &iv, None, &cfg)?;
                    Ok(vec![w.weights, w.transmittance, w.alphas])
                },
            );
            s.case(
                "volume::composite::render_weights",
                format!("{label}, rays with |d| = 2"),
                Expect::Finite,
                &[&sigmas, &starts, &ends, &dirs],
                || {
                    let w = render_weights(st, &iv, Some(&rays), &cfg)?;
                    Ok(vec![w.weights, w.transmittance, w.alphas])
                },
            );
            s.case(
                "volume::composite::accumulate",
                &label,
                Expect::Finite,
                &[&sigmas, &colors],
                || {
                    Ok(vec![accumulate(
                        &render_weights(st, &iv, None, &cfg)?.weights,
                        ct,
                        &Layout::Batched,
                    )?])
                },
            );
            // 0.1's `accumulate_fused`: Σwᵢvᵢ and Σwᵢ by the fused kernel, no background.
            s.case(
                "volume::composite::composite",
                format!("{label}, no background (Σwv, Σw)"),
                Expect::Finite,
                &wrt,
                || {
                    let c = composite(st, ct, &iv, None, &no_bg)?;
                    Ok(vec![c.color, c.opacity])
                },
            );
            // Packed: the same samples as rays of 5, 0, 3, 5, 0, 12, 10 samples, each ray
            // starting at t = 0.
            let counts = [5usize, 0, 3, 5, 0, 12, 10];
            let packed = Packed::from_counts(&counts, &d).unwrap();
            let (pst_h, pen_h) = common::intervals::starts_ends(&del, &counts);
            let pstarts = var(&pst_h, &[r * n], dtype);
            let pends = var(&pen_h, &[r * n], dtype);
            let piv = Intervals::new_packed(
                pstarts.as_tensor().clone(),
                pends.as_tensor().clone(),
                packed.clone(),
            )
            .unwrap();
            let (ps, pc) = (st.flatten_all().unwrap(), ct.reshape((r * n, 3)).unwrap());
            let pwrt = [&sigmas, &pstarts, &pends, &colors];
            let plabel = format!("{label}, packed with empty rays");
            s.case(
                "volume::layout::Packed::from_counts",
                &plabel,
                Expect::Finite,
                &pwrt,
                || {
                    let p = Packed::from_counts(&counts, &d)?;
                    let iv = Intervals::new_packed(
                        pstarts.as_tensor().clone(),
                        pends.as_tensor().clone(),
                        p,
                    )?;
                    out(composite(&ps, &pc, &iv, None, &cfg)?)
                },
            );
            s.case(
                "volume::layout::Intervals::new_packed",
                &plabel,
                Expect::Finite,
                &pwrt,
                || out(composite(&ps, &pc, &piv, None, &cfg)?),
            );
            s.case(
                "volume::composite::composite",
                format!("{plabel}, reference path"),
                Expect::Finite,
                &pwrt,
                || out(composite(&ps, &pc, &piv, None, &reference)?),
            );
            s.case(
                "volume::composite::render_weights",
                &plabel,
                Expect::Finite,
                &[&sigmas, &pstarts, &pends],
                || {
                    let w = render_weights(&ps, &piv, None, &cfg)?;
                    Ok(vec![w.weights, w.transmittance])
                },
            );
            s.case(
                "volume::composite::accumulate",
                &plabel,
                Expect::Finite,
                &[&sigmas, &colors],
                || {
                    Ok(vec![accumulate(
                        &render_weights(&ps, &piv, None, &cfg)?.weights,
                        &pc,
                        &piv.layout,
                    )?])
                },
            );
        }
        let label = format!("{dtype:?}");
        {
            let xs = magnitudes(dtype);
            let x = var(&xs, &[xs.len()], dtype);
            let al = format!("{label}, |x| up to max");
            s.case(
                "volume::activations::trunc_exp",
                &al,
                Expect::Finite,
                &[&x],
                || Ok(vec![trunc_exp(x.as_tensor())?]),
            );
        }
        for eps in [1e-30, 1e-4, 1.0] {
            s.case(
                "volume::composite::visible_mask",
                format!("{label}, eps = {eps}"),
                Expect::Finite,
                &[],
                || Ok(vec![visible_mask(sigmas.as_tensor(), &iv, None, eps)?]),
            );
        }
        s.case(
            "volume::layout::Packed::from_mask",
            &label,
            Expect::Finite,
            &[],
            || {
                let mask = visible_mask(sigmas.as_tensor(), &iv, None, 1e-4)?;
                let (p, idx) = Packed::from_mask(&mask)?;
                Ok(vec![Tensor::new(p.n_samples() as f64, &d)?, idx])
            },
        );
        // Samplers over tiny, huge and far-away ranges.
        let big = if dtype == DType::F32 { 1e6 } else { 1e100 };
        let near = var(&[0.0, 1e-30, big, 0.0], &[4], dtype);
        let far = var(&[1e-20, 2e-30, big * 1.5, 1e10], &[4], dtype);
        let dirs = var(
            &[
                1e-20, 0.0, 0.0, 0.0, 1.0, 0.0, 1e10, 1e10, 1e10, 0.0, 0.0, 1.0,
            ],
            &[4, 3],
            dtype,
        );
        let sampler_rays = Rays::new(
            Tensor::zeros((4, 3), dtype, &d).unwrap(),
            dirs.as_tensor().clone(),
        )
        .unwrap();
        for jitter in [Jitter::None, Jitter::PerSample, Jitter::SingleJitter] {
            let jl = format!("{label}, ranges 1e-30…{big:e}, {jitter:?}");
            s.case(
                "volume::sampling::stratified",
                &jl,
                Expect::Finite,
                &[&near, &far],
                || {
                    let iv = stratified(near.as_tensor(), far.as_tensor(), 16, jitter, 3)?;
                    Ok(vec![iv.starts.clone(), iv.ends.clone()])
                },
            );
        }
        let iv = stratified(near.as_tensor(), far.as_tensor(), 16, Jitter::PerSample, 3).unwrap();
        let il = format!("{label}, ranges 1e-30…{big:e}");
        s.case(
            "volume::layout::Intervals::midpoints",
            &il,
            Expect::Finite,
            &[&near, &far],
            || Ok(vec![iv.midpoints()?]),
        );
        s.case(
            "volume::layout::Intervals::deltas",
            &il,
            Expect::Finite,
            &[&near, &far, &dirs],
            || Ok(vec![iv.deltas(Some(&sampler_rays))?, iv.deltas(None)?]),
        );
        s.case(
            "volume::layout::Intervals::positions",
            format!("{il}, |d| 1e-20…1e10"),
            Expect::Finite,
            &[&near, &far, &dirs],
            || Ok(vec![iv.positions(&sampler_rays)?]),
        );
        s.case(
            "volume::layout::Intervals::directions",
            format!("{il}, |d| 1e-20…1e10"),
            Expect::Finite,
            &[&dirs],
            || Ok(vec![iv.directions(&sampler_rays)?]),
        );
        s.case(
            "volume::layout::Intervals::new",
            &il,
            Expect::Finite,
            &[],
            || {
                Ok(vec![
                    Intervals::new(iv.starts.clone(), iv.ends.clone())?.midpoints()?
                ])
            },
        );
        let w_rows = [[0.0; 16], [1e-30; 16], [huge; 16], {
            let mut one_hot = [0.0; 16];
            one_hot[7] = 1e30f64.min(huge);
            one_hot
        }]
        .concat();
        let weights = var(&w_rows, &[4, 16], dtype);
        for deterministic in [true, false] {
            let sl = format!("{il}, weights 0…{huge:e}, deterministic = {deterministic}");
            s.case(
                "volume::sampling::sample_pdf",
                &sl,
                Expect::Finite,
                &[],
                || {
                    Ok(vec![sample_pdf(
                        &iv,
                        weights.as_tensor(),
                        32,
                        deterministic,
                        9,
                        1e-5,
                    )?])
                },
            );
        }
        s.case(
            "volume::sampling::step_cdf",
            &il,
            Expect::Finite,
            &[&weights],
            || Ok(vec![step_cdf(weights.as_tensor(), 1e-5)?]),
        );
        let fine = sample_pdf(&iv, weights.as_tensor(), 32, false, 9, 1e-5).unwrap();
        s.case(
            "volume::sampling::merge_sorted",
            &il,
            Expect::Finite,
            &[&near, &far],
            || Ok(vec![merge_sorted(&iv.midpoints()?, &fine)?]),
        );
        s.case(
            "volume::sampling::Intervals::from_samples",
            &il,
            Expect::Finite,
            &[&near, &far],
            || {
                let iv2 = Intervals::from_samples(
                    &merge_sorted(&iv.midpoints()?, &fine)?,
                    near.as_tensor(),
                    far.as_tensor(),
                )?;
                Ok(vec![iv2.starts, iv2.ends])
            },
        );
        for step in [0usize, 128, 10_000] {
            s.case(
                "volume::sampling::anneal_near_far",
                format!("{il}, step {step}"),
                Expect::Finite,
                &[&near, &far],
                || {
                    let (a, b) =
                        anneal_near_far(near.as_tensor(), far.as_tensor(), step, 256, 0.5, 0.5)?;
                    Ok(vec![a, b])
                },
            );
        }
        // Regularisers on normalised intervals with extreme weights.
        let dl_w = var(
            &[
                [0.0; 8],
                [1e-30; 8],
                [1.0; 8],
                [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0],
            ]
            .concat(),
            &[4, 8],
            dtype,
        );
        let edges: Vec<f64> = (0..=8).map(|i| f64::from(i) / 8.0).collect();
        let st = Tensor::from_slice(&edges[..8], (1, 8), &d)
            .unwrap()
            .to_dtype(dtype)
            .unwrap()
            .repeat((4, 1))
            .unwrap();
        let en = Tensor::from_slice(&edges[1..], (1, 8), &d)
            .unwrap()
            .to_dtype(dtype)
            .unwrap()
            .repeat((4, 1))
            .unwrap();
        let dl_iv = Intervals::new(st, en).unwrap();
        s.case(
            "volume::regularizers::distortion_loss",
            format!("{label}, weights 0…1"),
            Expect::Finite,
            &[&dl_w],
            || Ok(vec![distortion_loss(dl_w.as_tensor(), &dl_iv)?]),
        );
        let dbig = if dtype == DType::F32 { 1e15 } else { 1e150 };
        let depth = var(
            &[0.0, 1e-30, dbig, -dbig, 1.0, 2.0, 3.0, 4.0, 5.0],
            &[1, 3, 3],
            dtype,
        );
        s.case(
            "volume::regularizers::depth_smoothness",
            format!("{label}, depths ±{dbig:e}"),
            Expect::Finite,
            &[&depth],
            || Ok(vec![depth_smoothness(depth.as_tensor(), None)?]),
        );
        // (400, 0.1, 512) is 0.1's `depth_smoothness_weight`.
        for (a, b) in [(400.0, 0.1), (1e-30, 1e30)] {
            s.case(
                "volume::regularizers::log_linear_schedule",
                format!("{a} → {b}"),
                Expect::Finite,
                &[],
                || {
                    Ok(vec![Tensor::new(
                        &[
                            log_linear_schedule(0, a, b, 512),
                            log_linear_schedule(10_000, a, b, 512),
                            log_linear_schedule(7, 400.0, 0.1, 512),
                        ],
                        &d,
                    )?])
                },
            );
        }
        s.case(
            "volume::regularizers::log_linear_schedule",
            format!("{label}, depth smoothness weight at step 100 000"),
            Expect::Finite,
            &[],
            || {
                Ok(vec![Tensor::new(
                    log_linear_schedule(100_000, 400.0, 0.1, 512),
                    &d,
                )?])
            },
        );
        // Occupancy grid over tiny and huge boxes with extreme densities.
        for (half, sigma) in [(1e-3, 1e30), (1.0, 1e-30), (1e4, 10.0)] {
            let gl = format!("{label}, box ±{half}, σ = {sigma:e}");
            let mut grid = OccupancyGrid::new(GridConfig {
                aabb: [-half, -half, -half, half, half, half],
                resolution: 16,
                levels: 2,
                ..GridConfig::default()
            })
            .unwrap();
            s.case(
                "volume::grid::OccupancyGrid::new",
                &gl,
                Expect::Finite,
                &[],
                || Ok(vec![Tensor::new(occupied_fraction(&grid), &d)?]),
            );
            s.case(
                "volume::grid::OccupancyGrid::update",
                &gl,
                Expect::Finite,
                &[],
                || {
                    grid.update(0, 1, &d, dtype, |p: &Tensor| {
                        let r2 = p.sqr()?.sum(1)?;
                        let inside = r2.lt(half * half * 0.25)?;
                        Ok(inside
                            .where_cond(&r2.ones_like()?.affine(sigma, 0.0)?, &r2.zeros_like()?)?)
                    })?;
                    Ok(vec![Tensor::new(occupied_fraction(&grid), &d)?])
                },
            );
            let o = Tensor::from_slice(&[-3.0 * half, 0.0, 0.0, 0.0, 0.0, 0.0], (2, 3), &d)
                .unwrap()
                .to_dtype(dtype)
                .unwrap();
            let w = Tensor::from_slice(&[1.0, 0.0, 0.0, 0.0, 1e-3, 1.0], (2, 3), &d)
                .unwrap()
                .to_dtype(dtype)
                .unwrap();
            let grid_rays = Rays::new(o, w).unwrap();
            for cone in [0.0, 1e-2] {
                let cl = format!("{gl}, cone {cone}");
                let march = GridMarchConfig {
                    cone_angle: cone,
                    ..GridMarchConfig::new(0.0, 6.0 * half, half / 64.0)
                };
                s.case(
                    "volume::grid::GridMarchConfig::new",
                    &cl,
                    Expect::Finite,
                    &[],
                    || {
                        let gs = grid.sample(&grid_rays, &march)?;
                        Ok(vec![gs.intervals.starts, gs.intervals.ends])
                    },
                );
                s.case(
                    "volume::grid::OccupancyGrid::sample",
                    &cl,
                    Expect::Finite,
                    &[],
                    || {
                        let gs = grid.sample(&grid_rays, &march)?;
                        let iv = &gs.intervals;
                        Ok(vec![
                            iv.midpoints()?,
                            iv.deltas(Some(&grid_rays))?,
                            iv.positions(&grid_rays)?,
                        ])
                    },
                );
                s.case(
                    "volume::grid::GridMarchConfig::with_jitter",
                    &cl,
                    Expect::Finite,
                    &[],
                    || {
                        let gs = grid.sample(&grid_rays, &march.with_jitter(u64::MAX))?;
                        let iv = &gs.intervals;
                        Ok(vec![
                            iv.deltas(Some(&grid_rays))?,
                            iv.positions(&grid_rays)?,
                        ])
                    },
                );
                let gs = grid.sample(&grid_rays, &march).unwrap();
                s.case(
                    "volume::layout::Intervals::midpoints",
                    format!("{cl}, grid samples"),
                    Expect::Finite,
                    &[],
                    || Ok(vec![gs.intervals.midpoints()?]),
                );
                s.case(
                    "volume::layout::Intervals::deltas",
                    format!("{cl}, grid samples"),
                    Expect::Finite,
                    &[],
                    || Ok(vec![gs.intervals.deltas(Some(&grid_rays))?]),
                );
                s.case(
                    "volume::layout::Intervals::positions",
                    format!("{cl}, grid samples"),
                    Expect::Finite,
                    &[],
                    || Ok(vec![gs.intervals.positions(&grid_rays)?]),
                );
            }
        }
        s.case(
            "volume::grid::OccupancyGrid::new",
            format!("{label}, empty box"),
            Expect::FiniteOrErr,
            &[],
            || {
                let g = OccupancyGrid::new(GridConfig {
                    aabb: [0.0; 6],
                    resolution: 8,
                    levels: 1,
                    ..GridConfig::default()
                })?;
                Ok(vec![Tensor::new(occupied_fraction(&g), &d)?])
            },
        );
    }
}

#[cfg(feature = "dvr")]
fn sweep_dvr(s: &mut Suite) {
    use neural_fields::camera::Intersection;
    use neural_fields::dvr::{
        depth_loss, eikonal_loss, freespace_loss, idr_mask_loss, implicit_surface, march,
        missed_foreground_loss, most_inside_along_rays, normal_smoothness_loss, photometric_loss,
        random_points_on_rays, secant_point, sphere_trace, AlphaSchedule, ImplicitConfig,
        MarchConfig, Photometric, SphereTraceConfig,
    };
    use neural_fields::field::Inside;
    let d = Device::Cpu;
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
                s.case(
                    "dvr::march::march",
                    label.clone(),
                    Expect::Finite,
                    &[],
                    || {
                        let h = march(field, &rays, &range, &cfg)?;
                        Ok(vec![h.depth, h.points])
                    },
                );
                s.case(
                    "dvr::implicit::implicit_surface",
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
                "dvr::march::march",
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
                "dvr::losses::freespace_loss",
                format!("{dtype:?}, {name}"),
                Expect::Finite,
                &[&radius],
                || Ok(vec![freespace_loss(field, &pts)?]),
            );
            s.case(
                "dvr::losses::missed_foreground_loss",
                format!("{dtype:?}, {name}"),
                Expect::Finite,
                &[&radius],
                || Ok(vec![missed_foreground_loss(field, &pts)?]),
            );
            s.case(
                "dvr::losses::normal_smoothness_loss",
                format!("{dtype:?}, {name}"),
                Expect::Finite,
                &[&radius, &center],
                || Ok(vec![normal_smoothness_loss(field, &pts, 5e-4, 1)?]),
            );
            s.case(
                "dvr::losses::most_inside_along_rays",
                format!("{dtype:?}, {name}"),
                Expect::Finite,
                &[&radius, &origins],
                || Ok(vec![most_inside_along_rays(field, &rays, &range, 17)?]),
            );
        }
        s.case(
            "dvr::march::sphere_trace",
            format!("{dtype:?}, extreme rays"),
            Expect::Finite,
            &[],
            || {
                let h = sphere_trace(&sdf, &rays, &range, &SphereTraceConfig::default())?;
                Ok(vec![h.depth, h.points])
            },
        );
        s.case(
            "dvr::losses::random_points_on_rays",
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
            "dvr::losses::eikonal_loss",
            format!("{dtype:?}, |g| 0…{top:e}"),
            Expect::Finite,
            &[&grads],
            || Ok(vec![eikonal_loss(grads.as_tensor())?]),
        );
        for alpha in [1e-6, 50.0, 1e12] {
            s.case(
                "dvr::losses::idr_mask_loss",
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
            "dvr::losses::depth_loss",
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
                "dvr::losses::photometric_loss",
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
            "dvr::losses::AlphaSchedule::alpha_at",
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
    let m = f64::MAX;
    for (lo, slo, hi, shi) in [
        (0.0, -m, 1.0, m),
        (0.0, 0.0, 1.0, 0.0),
        (0.0, f64::NAN, 1.0, 1.0),
        (-1e300, -1e-300, 1e300, 1e-300),
        (0.0, -f64::INFINITY, 1.0, f64::INFINITY),
    ] {
        s.case(
            "dvr::march::secant_point",
            format!("[{lo:e}, {hi:e}], s {slo:e}…{shi:e}"),
            Expect::Finite,
            &[],
            || {
                Ok(vec![Tensor::new(
                    &[secant_point(lo, slo, hi, shi).0],
                    &Device::Cpu,
                )?])
            },
        );
    }
}

#[cfg(feature = "occupancy")]
fn sweep_occupancy(s: &mut Suite) {
    use neural_fields::field::Inside;
    use neural_fields::nn::{onet_decoder, NormMode, OnetConfig};
    use neural_fields::occupancy::{
        from_tensor, inside_mesh, iou, kl_standard_normal, logit_threshold, marching_cubes,
        mesh_metrics, mise, near_surface, points_tensor, reconstruction_loss, refine_vertices,
        reparameterize, surface_metrics, uniform_in_padded_cube, winding_numbers,
        winding_numbers_exact, Grid, KdTree, Mesh, MeshFormat, MiseConfig, RefineConfig,
    };
    let d = Device::Cpu;
    let flat = |v: Vec<[f64; 3]>| Tensor::from_vec(v.concat(), v.len() * 3, &d);
    let vt = |v: Vec<f64>| Tensor::from_vec(v.clone(), v.len(), &d);
    // A tetrahedron at three scales: tiny, unit, huge.
    let tet = |scale: f64| {
        Mesh::new(
            vec![
                [0.0, 0.0, 0.0],
                [scale, 0.0, 0.0],
                [0.0, scale, 0.0],
                [0.0, 0.0, scale],
            ],
            vec![[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]],
        )
    };
    for scale in [1e-6, 1.0, 1e6] {
        let label = format!("tetrahedron of size {scale:e}");
        let mesh = tet(scale).unwrap();
        let q = vec![
            [0.1 * scale, 0.1 * scale, 0.1 * scale],
            [10.0 * scale, 0.0, 0.0],
            [0.0, 0.0, 0.0],
            [1e-30, 0.0, 0.0],
        ];
        s.case(
            "occupancy::mesh::Mesh::new",
            &label,
            Expect::Finite,
            &[],
            || {
                let m = tet(scale)?;
                m.validate()?;
                Ok(vec![
                    flat(m.vertex_normals()?)?,
                    flat(m.face_normals()?)?,
                    vt(m.face_areas()?)?,
                    Tensor::new(
                        &[m.face_areas()?.iter().sum::<f64>(), m.signed_volume()?],
                        &d,
                    )?,
                ])
            },
        );
        s.case(
            "occupancy::mesh::Mesh::validate",
            &label,
            Expect::Finite,
            &[],
            || {
                mesh.validate()?;
                Ok(vec![])
            },
        );
        for c in [0.0, 1e-300, 1.0, -1e-300, 1.0 + 1e-12, 1e300, f64::NAN] {
            s.case(
                "occupancy::mesh::Mesh::with_colors",
                format!("{label}, colour {c:e}"),
                if (0.0..=1.0).contains(&c) {
                    Expect::Finite
                } else {
                    Expect::FiniteOrErr
                },
                &[],
                || {
                    let coloured = mesh
                        .clone()
                        .with_colors(vec![[c; 3]; mesh.vertices.len()])?;
                    let flat: Vec<f64> = coloured.colors.unwrap_or_default().concat();
                    Ok(vec![Tensor::from_vec(flat.clone(), flat.len(), &d)?])
                },
            );
        }
        s.case(
            "occupancy::mesh::Mesh::normalize_unit_cube",
            &label,
            Expect::Finite,
            &[],
            || {
                let mut m = mesh.clone();
                let (c, k) = m.normalize_unit_cube()?;
                Ok(vec![
                    flat(m.vertices.clone())?,
                    Tensor::new(&[c[0], c[1], c[2], k], &d)?,
                ])
            },
        );
        s.case(
            "occupancy::mesh::Mesh::sample_surface",
            &label,
            Expect::Finite,
            &[],
            || {
                let smp = mesh.sample_surface(64, 1)?;
                Ok(vec![flat(smp.0)?, flat(smp.1)?])
            },
        );
        s.case(
            "occupancy::mesh::points_tensor",
            format!("{label}, vertices"),
            Expect::Finite,
            &[],
            || Ok(vec![points_tensor(&mesh.vertices, &d, DType::F32)?]),
        );
        s.case(
            "occupancy::mesh::points_tensor",
            &label,
            Expect::Finite,
            &[],
            || Ok(vec![points_tensor(&q, &d, DType::F32)?]),
        );
        s.case(
            "occupancy::mesh::Mesh::to_bytes",
            format!("{label}, PLY"),
            Expect::Finite,
            &[],
            || {
                let a = mesh.to_bytes(MeshFormat::PlyAscii)?;
                let b = mesh.to_bytes(MeshFormat::PlyBinary)?;
                let a = Mesh::from_bytes(&a, MeshFormat::PlyBinary)?;
                let b = Mesh::from_bytes(&b, MeshFormat::PlyBinary)?;
                Ok(vec![flat(a.vertices)?, flat(b.vertices)?])
            },
        );
        s.case(
            "occupancy::mesh::Mesh::from_bytes",
            format!("{label}, ASCII PLY"),
            Expect::Finite,
            &[],
            || {
                let bytes = mesh.to_bytes(MeshFormat::PlyAscii)?;
                Ok(vec![flat(
                    Mesh::from_bytes(&bytes, MeshFormat::PlyBinary)?.vertices,
                )?])
            },
        );
        s.case(
            "occupancy::mesh::Mesh::to_bytes",
            format!("{label}, OBJ"),
            Expect::Finite,
            &[],
            || {
                let obj = String::from_utf8(mesh.to_bytes(MeshFormat::Obj)?).unwrap();
                Ok(vec![flat(
                    Mesh::from_bytes(obj.as_bytes(), MeshFormat::Obj)?.vertices,
                )?])
            },
        );
        s.case(
            "occupancy::mesh::Mesh::from_bytes",
            format!("{label}, OBJ"),
            Expect::Finite,
            &[],
            || {
                let obj = String::from_utf8(mesh.to_bytes(MeshFormat::Obj)?).unwrap();
                Ok(vec![flat(
                    Mesh::from_bytes(obj.as_bytes(), MeshFormat::Obj)?.vertices,
                )?])
            },
        );
        s.case(
            "occupancy::mesh::Mesh::save",
            &label,
            Expect::Finite,
            &[],
            || {
                let path = std::env::temp_dir()
                    .join(format!("nf_stiff_{}_{scale:e}.ply", std::process::id()));
                mesh.save(&path)?;
                let m = Mesh::load(&path)?;
                let _ = std::fs::remove_file(&path);
                Ok(vec![flat(m.vertices)?])
            },
        );
        s.case(
            "occupancy::mesh::Mesh::load",
            &label,
            Expect::FiniteOrErr,
            &[],
            || Ok(vec![flat(Mesh::load("/nonexistent/mesh.ply")?.vertices)?]),
        );
        s.case(
            "occupancy::sampling::winding_numbers",
            &label,
            Expect::Finite,
            &[],
            || Ok(vec![vt(winding_numbers(&mesh, &q)?)?]),
        );
        s.case(
            "occupancy::sampling::winding_numbers_exact",
            &label,
            Expect::Finite,
            &[],
            || Ok(vec![vt(winding_numbers_exact(&mesh, &q)?)?]),
        );
        s.case(
            "occupancy::sampling::inside_mesh",
            &label,
            Expect::Finite,
            &[],
            || {
                Ok(vec![vt(inside_mesh(&mesh, &q)?
                    .into_iter()
                    .map(f64::from)
                    .collect())?])
            },
        );
        for sigma in [0.0, 1e-30, 1e3] {
            s.case(
                "occupancy::sampling::near_surface",
                format!("{label}, σ = {sigma:e}"),
                Expect::FiniteOrErr,
                &[],
                || Ok(vec![flat(near_surface(&mesh, 32, sigma, 2)?)?]),
            );
        }
        s.case(
            "occupancy::metrics::KdTree::new",
            &label,
            Expect::Finite,
            &[],
            || {
                let tree = KdTree::new(&mesh.vertices)?;
                Ok(vec![vt(q.iter().map(|p| tree.nearest(*p).1).collect())?])
            },
        );
        // 0.1's `nearest_distances(queries, reference)`.
        s.case(
            "occupancy::metrics::KdTree::new",
            format!("{label}, nearest distances"),
            Expect::Finite,
            &[],
            || {
                let tree = KdTree::new(&mesh.vertices)?;
                Ok(vec![vt(q
                    .iter()
                    .map(|&p| tree.nearest(p))
                    .map(|(_, dist)| dist)
                    .collect())?])
            },
        );
        s.case(
            "occupancy::metrics::surface_metrics",
            &label,
            Expect::Finite,
            &[],
            || {
                let m = surface_metrics(&q, None, &mesh.vertices, None, 0.01 * scale)?;
                Ok(vec![vt(vec![
                    m.accuracy,
                    m.completeness,
                    m.chamfer_l1,
                    m.normal_consistency.unwrap_or(0.0),
                    m.f_score,
                ])?])
            },
        );
        s.case(
            "occupancy::metrics::mesh_metrics",
            &label,
            Expect::Finite,
            &[],
            || {
                let m = mesh_metrics(&mesh, &tet(scale * 1.01)?, 256, 0.01 * scale, 3)?;
                Ok(vec![vt(vec![
                    m.accuracy,
                    m.completeness,
                    m.chamfer_l1,
                    m.normal_consistency.unwrap_or(0.0),
                    m.f_score,
                ])?])
            },
        );
    }
    s.case(
        "occupancy::metrics::iou",
        "empty union and disjoint sets",
        Expect::FiniteOrErr,
        &[],
        || {
            Ok(vec![vt(vec![
                iou(&[false, false], &[false, false])?,
                iou(&[true, false], &[false, true])?,
            ])?])
        },
    );
    for dtype in DTYPES {
        let tag = format!("{dtype:?}");
        // Losses at extreme logits, means and log-variances.
        let xs = magnitudes(dtype);
        let n = xs.len();
        let logits = var(&xs, &[1, n], dtype);
        let targets = Tensor::full(1.0f64, (1, n), &d)
            .unwrap()
            .to_dtype(dtype)
            .unwrap();
        s.case(
            "occupancy::losses::reconstruction_loss",
            format!("{tag}, logits up to max"),
            Expect::Finite,
            &[&logits],
            || Ok(vec![reconstruction_loss(logits.as_tensor(), &targets)?]),
        );
        let mean = var(&[0.0, 1e-30, 1e3, -1e3], &[1, 4], dtype);
        let logvar = var(&[0.0, -50.0, 50.0, -1e-30], &[1, 4], dtype);
        s.case(
            "occupancy::losses::kl_standard_normal",
            format!("{tag}, log-variances ±50"),
            Expect::Finite,
            &[&mean, &logvar],
            || {
                Ok(vec![kl_standard_normal(
                    mean.as_tensor(),
                    logvar.as_tensor(),
                )?])
            },
        );
        s.case(
            "occupancy::losses::reparameterize",
            format!("{tag}, log-variances ±50"),
            Expect::Finite,
            &[&mean, &logvar],
            || {
                Ok(vec![reparameterize(
                    mean.as_tensor(),
                    logvar.as_tensor(),
                    4,
                )?])
            },
        );
        for pad in [0.0, 0.1, 1e6] {
            s.case(
                "occupancy::sampling::uniform_in_padded_cube",
                format!("{tag}, padding {pad}"),
                Expect::Finite,
                &[],
                || {
                    let p = uniform_in_padded_cube(64, pad, 1, &d, dtype)?;
                    Ok(vec![points_tensor(&from_tensor(&p)?, &d, dtype)?, p])
                },
            );
        }
        s.case(
            "occupancy::mesh::points_tensor",
            format!("{tag}, 1e-30…1e30"),
            Expect::Finite,
            &[],
            || Ok(vec![points_tensor(&[[1e-30, 1e30, 0.0]], &d, dtype)?]),
        );
        s.case(
            "occupancy::sampling::from_tensor",
            &tag,
            Expect::Finite,
            &[],
            || {
                Ok(vec![flat(from_tensor(
                    &Tensor::new(&[[1e-30f64, 1e30, 0.0]], &d)?.to_dtype(dtype)?,
                )?)?])
            },
        );
        // Grids of extreme values and extents, and MISE on analytic fields.
        for (ext, amp) in [(1e-6, 1e-30), (1.0, 1.0), (1e6, 1e30)] {
            let gl = format!("{tag}, box ±{ext}, values ±{amp:e}");
            let f = move |p: [f64; 3]| {
                amp * ((p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt() - 0.5 * ext)
            };
            s.case(
                "occupancy::marching_cubes::Grid::from_fn",
                &gl,
                Expect::Finite,
                &[],
                || {
                    let g = Grid::from_fn([9, 9, 9], [-ext; 3], [ext; 3], f)?;
                    let sp = g.spacing();
                    Ok(vec![
                        flat(marching_cubes(&g, 0.0, Inside::Negative)?.vertices)?,
                        // x of grid point (1, 2, 3).
                        Tensor::new(&[sp[0], g.min[0] + sp[0]], &d)?,
                    ])
                },
            );
            s.case(
                "occupancy::marching_cubes::marching_cubes",
                &gl,
                Expect::Finite,
                &[],
                || {
                    Ok(vec![flat(
                        marching_cubes(
                            &Grid::from_fn([9, 9, 9], [-ext; 3], [ext; 3], f)?,
                            0.0,
                            Inside::Negative,
                        )?
                        .vertices,
                    )?])
                },
            );
            s.case(
                "occupancy::marching_cubes::Grid::new",
                &gl,
                Expect::FiniteOrErr,
                &[],
                || {
                    let vals: Vec<f32> = (0..27)
                        .map(|i| if i == 13 { -(amp as f32) } else { amp as f32 })
                        .collect();
                    Ok(vec![flat(
                        marching_cubes(
                            &Grid::new(vals, [3, 3, 3], [-ext; 3], [ext; 3])?,
                            0.0,
                            Inside::Negative,
                        )?
                        .vertices,
                    )?])
                },
            );
            s.case(
                "occupancy::marching_cubes::Grid::sample",
                &gl,
                Expect::Finite,
                &[],
                || {
                    let sphere = Sphere::new([0.0; 3], 0.5 * ext, &d, dtype)?.sdf();
                    Ok(vec![flat(
                        marching_cubes(
                            &Grid::sample(&sphere, [9, 9, 9], [-ext; 3], [ext; 3], 64, &d, dtype)?,
                            0.0,
                            Inside::Negative,
                        )?
                        .vertices,
                    )?])
                },
            );
            s.case("occupancy::mise::mise", &gl, Expect::Finite, &[], || {
                let sphere = Sphere::new([0.0; 3], 0.5 * ext, &d, dtype)?.occupancy(100.0 / ext);
                let mut cfg = MiseConfig::new(8, 2, &d, dtype);
                cfg.min = [-ext; 3];
                cfg.max = [ext; 3];
                let out = mise(&sphere, &cfg)?;
                Ok(vec![
                    flat(out.mesh.vertices)?,
                    Tensor::new(out.evaluations as f64, &d)?,
                ])
            });
            s.case(
                "occupancy::mise::refine_vertices",
                &gl,
                Expect::Finite,
                &[],
                || {
                    let sphere =
                        Sphere::new([0.0; 3], 0.5 * ext, &d, dtype)?.occupancy(100.0 / ext);
                    let mut cfg = MiseConfig::new(8, 1, &d, dtype);
                    cfg.min = [-ext; 3];
                    cfg.max = [ext; 3];
                    let mut mesh = mise(&sphere, &cfg)?.mesh;
                    let (before, after) = refine_vertices(
                        &sphere,
                        &mut mesh,
                        &RefineConfig::new(0.1 * ext, &d, dtype),
                    )?;
                    Ok(vec![
                        flat(mesh.vertices)?,
                        Tensor::new(&[before, after], &d)?,
                    ])
                },
            );
            s.case(
                "occupancy::mise::RefineConfig::new",
                &gl,
                Expect::Finite,
                &[],
                || {
                    Ok(vec![Tensor::new(
                        RefineConfig::new(ext, &d, dtype).max_shift,
                        &d,
                    )?])
                },
            );
            s.case(
                "occupancy::mise::MiseConfig::new",
                &gl,
                Expect::Finite,
                &[],
                || {
                    let cfg = MiseConfig::new(4, 1, &d, dtype);
                    Ok(vec![Tensor::new(
                        ((cfg.resolution0 << cfg.upsampling_steps) + 1) as f64,
                        &d,
                    )?])
                },
            );
        }
        for p in [0.0, 1e-30, 0.5, 1.0 - 1e-12, 1.0] {
            s.case(
                "occupancy::mise::logit_threshold",
                format!("p = {p}"),
                Expect::FiniteOrErr,
                &[],
                || Ok(vec![Tensor::new(logit_threshold(p)?, &d)?]),
            );
        }
        // PointNet encoder on extreme points and labels.
        {
            use neural_fields::nn::{pointnet_encoder, PointNetConfig};
            let cfg = PointNetConfig {
                hidden: 8,
                layers: 2,
                latent_dim: 3,
                point_features: 1,
            };
            let vm = candle_nn::VarMap::new();
            let enc = build_seeded(&vm, dtype, &d, 2, |vb| pointnet_encoder(&cfg, vb)).unwrap();
            let big = if dtype == DType::F32 { 1e15 } else { 1e100 };
            let p = var(
                &[
                    0.0, 0.0, 0.0, 1e-30, -1.0, 1.0, big, -big, big, 0.5, 0.5, 0.5,
                ],
                &[1, 4, 3],
                dtype,
            );
            let o = var(&[0.0, 1.0, 1e-30, 0.5], &[1, 4], dtype);
            let el = format!("{tag}, |p| up to {big:e}");
            s.case(
                "nn::pointnet::pointnet_encoder",
                &el,
                Expect::Finite,
                &[&p, &o],
                || {
                    let (m, l) = enc.forward(p.as_tensor(), o.as_tensor())?;
                    Ok(vec![m, l])
                },
            );
            s.case(
                "nn::pointnet::PointNetEncoder::forward",
                &el,
                Expect::Finite,
                &[&p, &o],
                || {
                    let (m, l) = enc.forward(p.as_tensor(), o.as_tensor())?;
                    Ok(vec![m, l])
                },
            );
            // Points with extreme per-point features (Texture Fields' normals).
            let cfg3 = PointNetConfig {
                point_features: 3,
                ..cfg.clone()
            };
            let vm3 = candle_nn::VarMap::new();
            let enc3 = build_seeded(&vm3, dtype, &d, 3, |vb| pointnet_encoder(&cfg3, vb)).unwrap();
            let nrm = var(
                &[
                    0.0, 0.0, 0.0, 1.0, 0.0, 0.0, -big, big, 1e-30, 0.5, -0.5, 0.5,
                ],
                &[1, 4, 3],
                dtype,
            );
            s.case(
                "nn::pointnet::PointNetEncoder::forward_features",
                &el,
                Expect::Finite,
                &[&p, &nrm],
                || {
                    let (m, l) = enc3.forward_features(p.as_tensor(), nrm.as_tensor())?;
                    Ok(vec![m, l])
                },
            );
        }
        // ONet's simple decoder on extreme points and codes.
        {
            use neural_fields::nn::{simple_decoder, SimpleDecoderConfig};
            let cfg = SimpleDecoderConfig {
                hidden: 8,
                blocks: 2,
                code_dim: 4,
            };
            let vm = candle_nn::VarMap::new();
            let dec = build_seeded(&vm, dtype, &d, 6, |vb| simple_decoder(&cfg, vb)).unwrap();
            let big = if dtype == DType::F32 { 1e15 } else { 1e100 };
            let p = var(
                &[0.0, 0.0, 0.0, 1e-30, 1.0, -1.0, big, -big, big],
                &[3, 3],
                dtype,
            );
            let c = var(
                &[
                    0.0, 1e-30, 1.0, -1.0, 1e3, -1e3, 0.5, 0.0, big, 0.0, 0.0, 0.0,
                ],
                &[3, 4],
                dtype,
            );
            let sl = format!("{tag}, |p|, |z| up to {big:e}");
            s.case(
                "nn::onet::simple_decoder",
                &sl,
                Expect::Finite,
                &[&p, &c],
                || Ok(vec![dec.logits(p.as_tensor(), c.as_tensor())?]),
            );
            s.case(
                "nn::onet::SimpleDecoder::logits",
                &sl,
                Expect::Finite,
                &[&p, &c],
                || Ok(vec![dec.logits(p.as_tensor(), c.as_tensor())?]),
            );
            s.case(
                "nn::onet::SimpleDecoder::value_and_grad_with_code",
                &sl,
                Expect::Finite,
                &[&p, &c],
                || {
                    let (v, g) = neural_fields::field::ConditionalField::value_and_grad_with_code(
                        &dec,
                        p.as_tensor(),
                        c.as_tensor(),
                    )?;
                    Ok(vec![v, g])
                },
            );
            s.case(
                "nn::onet::SimpleDecoder::forward_with_code",
                &sl,
                Expect::Finite,
                &[&p, &c],
                || {
                    Ok(vec![
                        neural_fields::field::ConditionalField::forward_with_code(
                            &dec,
                            p.as_tensor(),
                            c.as_tensor(),
                        )?,
                    ])
                },
            );
        }
        // ONet decoder on extreme points and codes, both norm modes.
        let config = OnetConfig {
            hidden: 16,
            blocks: 2,
            code_dim: 4,
            ..OnetConfig::default()
        };
        let varmap = candle_nn::VarMap::new();
        let net = build_seeded(&varmap, dtype, &d, 1, |vb| onet_decoder(&config, vb)).unwrap();
        let big = if dtype == DType::F32 { 1e6 } else { 1e100 };
        let pts = var(
            &[0.0, 0.0, 0.0, 1e-30, 1.0, -1.0, big, -big, big],
            &[3, 3],
            dtype,
        );
        let codes = var(
            &[
                0.0, 1e-30, 1.0, -1.0, 1e3, -1e3, 0.5, 0.0, big, 0.0, 0.0, 0.0,
            ],
            &[3, 4],
            dtype,
        );
        for mode in [NormMode::Train, NormMode::Eval] {
            let ol = format!("{tag}, |p|, |z| up to {big:e}, {mode:?}");
            net.set_mode(mode);
            s.case(
                "nn::onet::onet_decoder",
                &ol,
                Expect::Finite,
                &[&pts, &codes],
                || Ok(vec![net.logits(pts.as_tensor(), codes.as_tensor())?]),
            );
            s.case(
                "nn::onet::OnetDecoder::logits",
                &ol,
                Expect::Finite,
                &[&pts, &codes],
                || Ok(vec![net.logits(pts.as_tensor(), codes.as_tensor())?]),
            );
            s.case(
                "nn::onet::OnetDecoder::set_mode",
                &ol,
                Expect::Finite,
                &[],
                || Ok(vec![]),
            );
            s.case(
                "nn::onet::OnetDecoder::forward_with_code",
                &ol,
                Expect::Finite,
                &[&pts, &codes],
                || {
                    Ok(vec![
                        neural_fields::field::ConditionalField::forward_with_code(
                            &net,
                            pts.as_tensor(),
                            codes.as_tensor(),
                        )?,
                    ])
                },
            );
            s.case(
                "nn::onet::OnetDecoder::value_and_grad_with_code",
                &ol,
                Expect::Finite,
                &[&pts, &codes],
                || {
                    let (v, g) = neural_fields::field::ConditionalField::value_and_grad_with_code(
                        &net,
                        pts.as_tensor(),
                        codes.as_tensor(),
                    )?;
                    Ok(vec![v, g])
                },
            );
        }
    }
}

#[test]
fn stiff_cases_give_finite_outputs_and_gradients_or_err() {
    let mut s = Suite::default();
    sweep_numerics(&mut s);
    sweep_fields(&mut s);
    sweep_encodings(&mut s);
    sweep_hash_grid(&mut s);
    #[cfg(feature = "occupancy")]
    sweep_point_clouds(&mut s);
    sweep_mlp(&mut s);
    sweep_camera(&mut s);
    sweep_camera_host(&mut s);
    sweep_nerf(&mut s);
    #[cfg(feature = "data")]
    sweep_data(&mut s);
    sweep_rng(&mut s);
    #[cfg(feature = "volume")]
    sweep_volume(&mut s);
    #[cfg(feature = "occupancy")]
    sweep_occupancy(&mut s);
    #[cfg(feature = "dvr")]
    sweep_dvr(&mut s);
    #[cfg(feature = "texture")]
    sweep_texture(&mut s);
    sweep_grid_sample(&mut s);
    #[cfg(feature = "flow")]
    sweep_flow(&mut s);
    #[cfg(feature = "occupancy")]
    sweep_conv_onet(&mut s);
    println!(
        "stiff cases: {} cases run over {} items, {} failures",
        s.cases,
        s.covered.len(),
        s.failures.len()
    );
    assert!(
        s.failures.is_empty(),
        "stiff-case failures:\n{}",
        s.failures.join("\n")
    );
    covered_matches_list(&s.covered);
}

/// Items swept above; kept in sync with the sweeps by `covered_matches_list`.
const COVERED: &[&str] = &[
    "camera::cameras_around",
    "camera::PixelFilter::quantile",
    "nn::nerf::Nerf::density",
    "nn::nerf::Nerf::radiance",
    "nn::nerf::nerf",
    "camera::Camera::project",
    "camera::Camera::ray",
    "camera::Camera::look_at",
    "camera::Camera::new",
    "camera::Camera::pixel_grid",
    "camera::Camera::subpixel_grid",
    "camera::Camera::pose_param",
    "camera::Camera::random_rays",
    "camera::Camera::rays",
    "camera::Camera::rays_for_pixels",
    "camera::Intersection::new",
    "camera::Intrinsics::from_fov_y",
    "camera::Intrinsics::new",
    "camera::PoseParam::from_affine",
    "camera::PoseParam::rays",
    "camera::PoseParam::renormalize",
    "camera::PoseParam::rotation_matrix",
    "camera::PoseParam::to_affine",
    "camera::Rays::at",
    "camera::Rays::narrow",
    "camera::Rays::new",
    "camera::Rays::normalized",
    "camera::ray_aabb",
    "camera::ray_sphere",
    "camera::align_cameras",
    "camera::reprojection_error",
    "camera::align_similarity",
    "camera::retract_pose",
    "numerics::damped_solve",
    "camera::Similarity::inverse",
    "camera::Similarity::transform_pose",
    "camera::Similarity::transform_point",
    "encoding::coarse_to_fine::coarse_to_fine_weights",
    "encoding::coarse_to_fine::CoarseToFine::column_weights",
    "encoding::coarse_to_fine::CoarseToFine::forward",
    "encoding::coarse_to_fine::CoarseToFine::forward_jvp",
    "encoding::coarse_to_fine::CoarseToFine::new",
    "encoding::coarse_to_fine::CoarseToFine::set_alpha",
    "encoding::FourierFeatures::from_matrix",
    "encoding::FourierFeatures::new",
    "encoding::FrequencyEncoding::forward_jvp",
    "encoding::PointEncoding::forward",
    "encoding::integrated_pe",
    "encoding::hash_grid::hash_grid",
    "encoding::hash_grid::HashGrid::forward",
    "encoding::hash_grid::HashGrid::forward_jvp",
    "encoding::hash_grid::HashGrid::forward_reference",
    "field::Cuboid::new",
    "field::Plane::new",
    "field::Sphere::new",
    "field::Torus::new",
    "nn::mlp::Mlp::forward",
    "nn::mlp::Mlp::forward_with_jacobian",
    "nn::mlp::MlpConfig::sdf",
    "nn::mlp::mlp",
    "numerics::bce_with_logits",
    "numerics::cos_pi",
    "numerics::guard_denominator",
    "numerics::safe_cos",
    "numerics::safe_sin",
    "numerics::sigmoid",
    "numerics::sin_pi",
    "numerics::softplus",
    "rng::SplitMix64::normal_tensor",
    "rng::SplitMix64::uniform_tensor",
];

/// Data items swept by `sweep_data`.
const DATA_COVERED: &[&str] = &[
    "data::batch::Dataset::view_rays",
    "data::batch::RaySampler::new",
    "data::batch::RaySampler::patches",
    "data::batch::RaySampler::pixel_footprints",
    "data::batch::RaySampler::with_pixel_filter",
    "data::batch::RaySampler::pixels",
    "data::dataset::Dataset::new",
    "data::dataset::View::mask",
    "data::dataset::View::new",
    "data::dataset::View::rgb",
    "data::dataset::load",
    "data::image::Image::from_tensor",
    "data::image::Image::to_tensor",
    "data::metrics::psnr",
    "data::metrics::ssim",
    "data::output::colorize_depth",
    "data::output::colorize_normals",
    "data::output::comparison_strip",
    "data::output::write_png",
    "data::transforms::write_blender",
];

/// DVR items swept by `sweep_dvr`.
const DVR_COVERED: &[&str] = &[
    "dvr::implicit::implicit_surface",
    "dvr::losses::AlphaSchedule::alpha_at",
    "dvr::losses::depth_loss",
    "dvr::losses::eikonal_loss",
    "dvr::losses::freespace_loss",
    "dvr::losses::idr_mask_loss",
    "dvr::losses::missed_foreground_loss",
    "dvr::losses::most_inside_along_rays",
    "dvr::losses::normal_smoothness_loss",
    "dvr::losses::photometric_loss",
    "dvr::losses::random_points_on_rays",
    "dvr::march::march",
    "dvr::march::secant_point",
    "dvr::march::sphere_trace",
];

/// Volume items swept by `sweep_volume`.
const VOLUME_COVERED: &[&str] = &[
    "nn::nerf::Nerf::color_loss",
    "volume::proposal::interlevel_loss",
    "volume::proposal::proposal_sample",
    "volume::layout::Intervals::retain",
    "volume::activations::trunc_exp",
    "volume::composite::Composite::normalized_depth",
    "volume::composite::accumulate",
    "volume::composite::composite",
    "volume::composite::render_weights",
    "volume::composite::visible_mask",
    "volume::grid::GridMarchConfig::new",
    "volume::grid::GridMarchConfig::with_jitter",
    "volume::grid::OccupancyGrid::new",
    "volume::grid::OccupancyGrid::sample",
    "volume::grid::OccupancyGrid::update",
    "volume::layout::Intervals::deltas",
    "volume::layout::Intervals::directions",
    "volume::layout::Intervals::midpoints",
    "volume::layout::Intervals::new",
    "volume::layout::Intervals::new_packed",
    "volume::layout::Intervals::positions",
    "volume::layout::Packed::from_counts",
    "volume::layout::Packed::from_mask",
    "volume::regularizers::depth_smoothness",
    "volume::regularizers::distortion_loss",
    "volume::regularizers::log_linear_schedule",
    "volume::sampling::Intervals::from_samples",
    "volume::sampling::anneal_near_far",
    "volume::sampling::merge_sorted",
    "volume::sampling::sample_pdf",
    "volume::sampling::step_cdf",
    "volume::sampling::stratified",
];

/// Occupancy and ONet items swept by `sweep_occupancy`.
const OCCUPANCY_COVERED: &[&str] = &[
    "occupancy::point_cloud::PointCloud::new",
    "occupancy::point_cloud::PointCloud::with_normals",
    "occupancy::point_cloud::PointCloud::with_colors",
    "occupancy::point_cloud::PointCloud::sample",
    "occupancy::point_cloud::PointCloud::to_tensor",
    "occupancy::point_cloud::PointCloud::normals_tensor",
    "occupancy::point_cloud::PointCloud::to_bytes",
    "occupancy::point_cloud::PointCloud::from_bytes",
    "occupancy::point_cloud::PointCloud::save",
    "occupancy::point_cloud::PointCloud::load",
    "nn::pointnet::PointNetEncoder::forward_features",
    "occupancy::mesh::Mesh::with_colors",
    "nn::onet::OnetDecoder::forward_with_code",
    "nn::onet::OnetDecoder::logits",
    "nn::onet::OnetDecoder::set_mode",
    "nn::onet::OnetDecoder::value_and_grad_with_code",
    "nn::onet::SimpleDecoder::forward_with_code",
    "nn::onet::SimpleDecoder::logits",
    "nn::onet::SimpleDecoder::value_and_grad_with_code",
    "nn::onet::onet_decoder",
    "nn::onet::simple_decoder",
    "nn::pointnet::PointNetEncoder::forward",
    "nn::pointnet::pointnet_encoder",
    "occupancy::losses::kl_standard_normal",
    "occupancy::losses::reconstruction_loss",
    "occupancy::losses::reparameterize",
    "occupancy::marching_cubes::Grid::from_fn",
    "occupancy::marching_cubes::Grid::new",
    "occupancy::marching_cubes::Grid::sample",
    "occupancy::marching_cubes::marching_cubes",
    "occupancy::mesh::Mesh::from_bytes",
    "occupancy::mesh::Mesh::load",
    "occupancy::mesh::Mesh::new",
    "occupancy::mesh::Mesh::normalize_unit_cube",
    "occupancy::mesh::Mesh::sample_surface",
    "occupancy::mesh::Mesh::save",
    "occupancy::mesh::Mesh::to_bytes",
    "occupancy::mesh::Mesh::validate",
    "occupancy::mesh::points_tensor",
    "occupancy::metrics::KdTree::new",
    "occupancy::metrics::iou",
    "occupancy::metrics::mesh_metrics",
    "occupancy::metrics::surface_metrics",
    "occupancy::mise::MiseConfig::new",
    "occupancy::mise::RefineConfig::new",
    "occupancy::mise::logit_threshold",
    "occupancy::mise::mise",
    "occupancy::mise::refine_vertices",
    "occupancy::sampling::from_tensor",
    "occupancy::sampling::inside_mesh",
    "occupancy::sampling::near_surface",
    "occupancy::sampling::uniform_in_padded_cube",
    "occupancy::sampling::winding_numbers",
    "occupancy::sampling::winding_numbers_exact",
];

/// Public items without floating-point input (or only reached through a swept item),
/// with the reason. Matching is by prefix, so `"error::check_"` covers the checks.
const EXEMPT: &[(&str, &str)] = &[
    (
        "encoding::grid_sample::FusedGridSample::",
        "CustomOp internals, swept via grid_sample",
    ),
    (
        "encoding::grid_sample::FusedScatterMax::",
        "CustomOp internals, swept via scatter_max",
    ),
    ("flow::ode::Solver::occupancy_flow", "constant"),
    ("flow::velocity::VelocityField::config", "getter"),
    ("flow::velocity::VelocityFieldConfig::default", "constant"),
    ("nn::conv_onet::ConvOnetConfig::default", "constant"),
    ("nn::conv_onet::UnetConfig::default", "constant"),
    ("nn::conv_onet::LocalDecoderConfig::default", "constant"),
    ("nn::conv_onet::ConvOnetEncoder::config", "getter"),
    ("nn::conv_onet::LocalDecoder::config", "getter"),
    ("nn::conv_onet::LocalFeatures::batch_and_channels", "getter"),
    ("nn::conv_onet::SceneField::features", "getter"),
    ("nn::conv_onet::SceneField::out_dim", "constant"),
    ("encoding::hash_grid::HashGrid::config", "getter"),
    ("encoding::coarse_to_fine::CoarseToFine::inner", "getter"),
    ("encoding::coarse_to_fine::CoarseToFine::bands", "getter"),
    ("encoding::coarse_to_fine::CoarseToFine::alpha", "getter"),
    ("encoding::coarse_to_fine::CoarseToFine::in_dim", "getter"),
    ("encoding::coarse_to_fine::CoarseToFine::out_dim", "getter"),
    ("encoding::hash_grid::HashGrid::table", "getter"),
    ("encoding::hash_grid::HashGrid::levels", "getter"),
    ("encoding::hash_grid::HashGrid::in_dim", "getter"),
    ("encoding::hash_grid::HashGrid::out_dim", "getter"),
    ("encoding::hash_grid::HashGridConfig::default", "constant"),
    (
        "encoding::hash_grid::FusedHashGrid::",
        "CustomOp internals, swept via HashGrid::forward",
    ),
    ("encoding::PointEncoding::in_dim", "getter"),
    ("occupancy::point_cloud::PointCloud::points", "getter"),
    ("occupancy::point_cloud::PointCloud::normals", "getter"),
    ("occupancy::point_cloud::PointCloud::colors", "getter"),
    ("occupancy::point_cloud::PointCloud::len", "getter"),
    ("occupancy::point_cloud::PointCloud::is_empty", "getter"),
    (
        "occupancy::mesh::MeshFormat::from_path",
        "an extension; no float input",
    ),
    (
        "occupancy::ply::",
        "crate-private reader, swept via Mesh::from_bytes and PointCloud::from_bytes",
    ),
    (
        "occupancy::stl::",
        "crate-private reader, swept via Mesh::from_bytes",
    ),
    (
        "occupancy::off::",
        "crate-private reader, swept via Mesh::from_bytes",
    ),
    (
        "occupancy::mesh::ObjContent::",
        "crate-private reader, swept via Mesh::from_bytes",
    ),
    (
        "texture::TextureInput::",
        "builder: stores references to its tensors, computes nothing",
    ),
    ("nn::texture::TextureDecoderConfig::default", "constant"),
    ("nn::texture::RenderingNetConfig::default", "constant"),
    ("nn::texture::TextureDecoder::config", "getter"),
    ("nn::texture::RenderingNet::config", "getter"),
    ("nn::texture::JointDecoder::mlp", "getter"),
    ("nn::texture::JointDecoder::out_dim", "constant"),
    ("nn::texture::JointDecoder::inside", "constant"),
    ("nn::nerf::Nerf::config", "getter"),
    ("volume::proposal::ProposalConfig::default", "constant"),
    (
        "volume::grid::OccupancyGrid::occupied_fraction",
        "counts booleans; no float input",
    ),
    ("nn::nerf::Nerf::forward", "swept through Nerf::density"),
    ("nn::nerf::Nerf::out_dim", "constant"),
    ("nn::nerf::NerfConfig::default", "constant"),
    ("data::batch::RayBatch::is_empty", "getter"),
    ("data::batch::RayBatch::len", "getter"),
    (
        "camera::PixelFilter::validate",
        "a parameter check; swept through PixelFilter::quantile and Camera::subpixel_grid",
    ),
    (
        "data::batch::RaySampler::with_jitter",
        "a flag; its jittered rays are checked in tests/data_batches.rs",
    ),
    ("data::dataset::Background::", "constants"),
    ("data::dataset::Dataset::background", "getter"),
    ("data::dataset::Dataset::bounds", "getter"),
    ("data::dataset::Dataset::image_bytes", "integer count"),
    ("data::dataset::Dataset::is_empty", "getter"),
    ("data::dataset::Dataset::len", "getter"),
    ("data::dataset::Dataset::views", "getter"),
    (
        "data::dataset::DatasetLayout::detect",
        "file-system probe, no floats",
    ),
    ("data::dataset::LoadConfig::default", "constant"),
    ("data::dataset::Split::name", "constant"),
    ("data::dataset::View::camera", "getter"),
    ("data::dataset::View::has_mask", "getter"),
    ("data::dataset::View::image", "getter"),
    ("data::dataset::View::mask_image", "getter"),
    ("data::dataset::View::name", "getter"),
    ("data::image::Image::channels", "getter"),
    ("data::image::Image::data", "getter"),
    ("data::image::Image::height", "getter"),
    ("data::image::Image::new", "bytes, no floats"),
    ("data::image::Image::pixel", "bytes, no floats"),
    ("data::image::Image::width", "getter"),
    ("nn::onet::SimpleDecoderConfig::default", "constant"),
    ("nn::onet::SimpleDecoder::code_dim", "getter"),
    ("nn::onet::SimpleDecoder::config", "getter"),
    ("nn::onet::SimpleDecoder::inside", "getter"),
    ("nn::onet::SimpleDecoder::out_dim", "getter"),
    ("nn::pointnet::PointNetConfig::default", "constant"),
    ("nn::pointnet::PointNetEncoder::config", "getter"),
    ("nn::onet::OnetConfig::default", "constant"),
    ("nn::onet::OnetDecoder::code_dim", "getter"),
    ("nn::onet::OnetDecoder::config", "getter"),
    ("nn::onet::OnetDecoder::inside", "getter"),
    ("nn::onet::OnetDecoder::out_dim", "getter"),
    (
        "occupancy::marching_cubes::Grid::spacing",
        "swept through Grid::from_fn",
    ),
    (
        "occupancy::mesh::Mesh::bounds",
        "swept through normalize_unit_cube",
    ),
    ("occupancy::mesh::Mesh::edge_report", "integer topology"),
    (
        "occupancy::mesh::Mesh::face_areas",
        "swept through Mesh::new",
    ),
    (
        "occupancy::mesh::Mesh::face_normals",
        "swept through Mesh::new",
    ),
    (
        "occupancy::mesh::Mesh::is_watertight_and_oriented",
        "integer topology",
    ),
    (
        "occupancy::mesh::Mesh::signed_volume",
        "swept through Mesh::new",
    ),
    (
        "occupancy::mesh::Mesh::vertex_normals",
        "swept through Mesh::new",
    ),
    (
        "occupancy::metrics::KdTree::nearest",
        "swept through KdTree::new",
    ),
    ("dvr::implicit::ImplicitConfig::default", "constants"),
    ("dvr::implicit::SurfacePoints::", "getters"),
    ("dvr::losses::AlphaSchedule::default", "constants"),
    ("dvr::march::Hits::", "getters over statuses"),
    ("dvr::march::MarchConfig::default", "constants"),
    ("dvr::march::RayStatus::", "enum"),
    ("dvr::march::SphereTraceConfig::default", "constants"),
    ("dvr::march::StepSchedule::", "integer schedule"),
    ("camera::Camera::cam_to_world", "getter"),
    ("camera::Camera::center", "getter"),
    ("camera::Camera::convention", "getter"),
    ("camera::Camera::intrinsics", "getter"),
    ("camera::Convention::", "enum"),
    ("camera::Rays::directions", "getter"),
    ("camera::Rays::is_empty", "getter"),
    ("camera::Rays::len", "getter"),
    ("camera::Rays::origins", "getter"),
    (
        "encoding::FourierFeatures::forward",
        "swept through PointEncoding::forward_jvp / forward",
    ),
    (
        "encoding::FourierFeatures::forward_jvp",
        "swept through PointEncoding::forward_jvp",
    ),
    ("encoding::FourierFeatures::in_dim", "getter"),
    ("encoding::FourierFeatures::matrix", "getter"),
    ("encoding::FourierFeatures::out_dim", "getter"),
    (
        "encoding::FrequencyEncoding::forward",
        "swept through PointEncoding::forward",
    ),
    ("encoding::FrequencyEncoding::in_dim", "getter"),
    ("encoding::FrequencyEncoding::n_freqs", "getter"),
    ("encoding::FrequencyEncoding::new", "integer arguments"),
    ("encoding::FrequencyEncoding::out_dim", "getter"),
    (
        "encoding::PointEncoding::forward_jvp",
        "swept in the FrequencyEncoding / FourierFeatures cases",
    ),
    ("encoding::PointEncoding::out_dim_for", "integer arithmetic"),
    (
        "error::",
        "validation helpers: their job is to return Err for bad input (unit-tested)",
    ),
    (
        "field::Conditioned::",
        "forwards to the wrapped field (swept via the Mlp)",
    ),
    ("field::Inside::sign", "constant"),
    (
        "field::Occupancy::",
        "trait methods, swept via the shapes' cases",
    ),
    ("field::Sdf::", "trait methods, swept via the shapes' cases"),
    (
        "field::Cuboid::distance_and_grad",
        "swept via the Cuboid cases",
    ),
    (
        "field::Plane::distance_and_grad",
        "swept via the Plane cases",
    ),
    (
        "field::Sphere::distance_and_grad",
        "swept via the Sphere cases",
    ),
    (
        "field::Torus::distance_and_grad",
        "swept via the Torus cases",
    ),
    ("nn::SeededBackend::", "private"),
    (
        "nn::build_seeded",
        "integer seed; its draws are swept via the Mlp cases",
    ),
    ("nn::mlp::Mlp::config", "getter"),
    (
        "nn::mlp::Mlp::forward_with_code",
        "the ConditionalField forward: the Field forward with codes (swept as Mlp::forward)",
    ),
    ("nn::mlp::Mlp::inside", "getter"),
    ("nn::mlp::Mlp::out_dim", "getter"),
    ("nn::mlp::Mlp::value", "forwards to Field::forward"),
    ("nn::mlp::Mlp::code_dim", "getter"),
    (
        "nn::mlp::Mlp::value_and_grad",
        "forwards to forward_with_jacobian",
    ),
    ("nn::mlp::MlpConfig::default", "constant"),
    ("rng::SplitMix64::", "integer state; tensor makers swept"),
    (
        "numerics::SoftplusOp::",
        "CustomOp internals, swept via numerics::softplus",
    ),
    (
        "numerics::SigmoidOfScaled::",
        "CustomOp internals (softplus backward), swept via numerics::softplus",
    ),
    (
        "volume::activations::TruncExp::",
        "CustomOp internals, swept via activations::trunc_exp",
    ),
    ("volume::layout::Intervals::n_rays", "getter"),
    ("volume::layout::Packed::n_samples", "getter"),
    ("volume::layout::Packed::offsets_host", "getter"),
    (
        "volume::fused::FusedComposite::",
        "CustomOp internals, swept via composite",
    ),
    (
        "nn::fused_mlp::FusedMlp::",
        "CustomOp internals, swept via Mlp::forward",
    ),
    (
        "nn::fused_mlp::FusedNerf::",
        "CustomOp internals, swept via Nerf::radiance",
    ),
    (
        "nn::fused_mlp::nerf_loss::FusedNerfLoss::",
        "CustomOp internals, swept via Nerf::color_loss",
    ),
    (
        "nn::fused_mlp::FusedMlpJvp::",
        "CustomOp internals, swept via Mlp::forward_with_jacobian",
    ),
    (
        "nn::fused_mlp::activation::",
        "crate-internal activation slices of the fused ops, swept via the softplus Mlp \
         (Mlp::value_and_grad) and tested against the standard library in their module",
    ),
    (
        "encoding::FusedFrequency::",
        "CustomOp internals, swept via FrequencyEncoding::forward",
    ),
    ("volume::grid::GridConfig::default", "constant"),
    ("volume::grid::OccupancyGrid::config", "getter"),
    ("volume::grid::OccupancyGrid::density", "getter"),
    (
        "volume::grid::OccupancyGrid::is_occupied",
        "lookup, swept through sample",
    ),
    ("volume::grid::OccupancyGrid::occupied", "getter"),
];

/// Public functions and trait-impl methods in `src/`, as `module::Type::method` or
/// `module::function` (everything after a file's first `#[cfg(test)]` is skipped).
fn public_items() -> BTreeSet<String> {
    let mut items = BTreeSet::new();
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut stack = vec![root.clone()];
    while let Some(dir) = stack.pop() {
        for entry in std::fs::read_dir(&dir).unwrap() {
            let path = entry.unwrap().path();
            if path.is_dir() {
                stack.push(path);
                continue;
            }
            if path.extension().and_then(|e| e.to_str()) != Some("rs") {
                continue;
            }
            let rel = path.strip_prefix(&root).unwrap().with_extension("");
            let mut module: Vec<String> = rel
                .iter()
                .map(|c| c.to_string_lossy().into_owned())
                .collect();
            if module.last().map(|m| m == "mod" || m == "lib") == Some(true) {
                module.pop();
            }
            let module = module.join("::");
            let text = std::fs::read_to_string(&path).unwrap();
            let mut current: Option<(String, bool)> = None; // (type, is trait impl)
            for line in text.lines() {
                if line.starts_with("#[cfg(test)]") {
                    break;
                }
                if line.starts_with("impl") {
                    let head = line.trim_end_matches('{').trim();
                    let is_trait = head.contains(" for ");
                    let ty = head
                        .rsplit(" for ")
                        .next()
                        .unwrap()
                        .trim_start_matches("impl")
                        .trim();
                    let ty = ty.rsplit("> ").next().unwrap_or(ty);
                    let ty = ty
                        .split('<')
                        .next()
                        .unwrap()
                        .trim()
                        .rsplit("::")
                        .next()
                        .unwrap()
                        .to_string();
                    current = Some((ty, is_trait));
                    continue;
                }
                if line.starts_with('}') {
                    current = None;
                    continue;
                }
                let trimmed = line.trim_start();
                let indent = line.len() - trimmed.len();
                let name_after = |prefix: &str| {
                    trimmed
                        .strip_prefix(prefix)
                        .map(|r| r.split(['(', '<']).next().unwrap().to_string())
                };
                let prefix = if module.is_empty() {
                    String::new()
                } else {
                    format!("{module}::")
                };
                match (&current, indent) {
                    (None, 0) => {
                        if let Some(n) = name_after("pub fn ") {
                            items.insert(format!("{prefix}{n}"));
                        }
                    }
                    (Some((ty, is_trait)), 4) => {
                        let n = if *is_trait {
                            name_after("fn ")
                        } else {
                            name_after("pub fn ")
                        };
                        if let Some(n) = n {
                            items.insert(format!("{prefix}{ty}::{n}"));
                        }
                    }
                    _ => {}
                }
            }
        }
    }
    items
}

/// `COVERED` plus the lists of the enabled feature modules.
fn covered() -> Vec<&'static str> {
    let mut v = COVERED.to_vec();
    if cfg!(feature = "volume") {
        v.extend(VOLUME_COVERED);
    }
    if cfg!(feature = "occupancy") {
        v.extend(OCCUPANCY_COVERED);
    }
    if cfg!(feature = "dvr") {
        v.extend(DVR_COVERED);
    }
    if cfg!(feature = "data") {
        v.extend(DATA_COVERED);
    }
    v.extend(GRID_SAMPLE_COVERED);
    if cfg!(feature = "flow") {
        v.extend(FLOW_COVERED);
    }
    if cfg!(feature = "occupancy") {
        v.extend(CONV_ONET_COVERED);
    }
    if cfg!(feature = "texture") {
        v.extend(TEXTURE_COVERED);
        if cfg!(feature = "occupancy") {
            v.push("texture::vertex_colors");
        }
    }
    v
}

/// Whether a module's feature is enabled (items of disabled modules are not compiled).
fn module_enabled(item: &str) -> bool {
    let feature_of = [
        ("volume::", cfg!(feature = "volume")),
        ("dvr::", cfg!(feature = "dvr")),
        ("occupancy::", cfg!(feature = "occupancy")),
        ("data::", cfg!(feature = "data")),
        ("texture::", cfg!(feature = "texture")),
        ("nn::texture::", cfg!(feature = "texture")),
        // ONet's networks: `mod onet` / `mod pointnet` are behind `occupancy` in src/nn.
        ("nn::onet::", cfg!(feature = "occupancy")),
        ("nn::pointnet::", cfg!(feature = "occupancy")),
        ("nn::conv_onet::", cfg!(feature = "occupancy")),
        ("flow::", cfg!(feature = "flow")),
        ("nn::nerf::Nerf::color_loss", cfg!(feature = "volume")),
    ];
    feature_of
        .iter()
        .all(|(prefix, on)| !item.starts_with(prefix) || *on)
}

fn covered_matches_list(swept: &BTreeSet<&'static str>) {
    let listed: BTreeSet<&str> = covered().into_iter().collect();
    let stale: Vec<_> = listed.symmetric_difference(swept).collect();
    assert!(
        stale.is_empty(),
        "COVERED differs from what the sweeps ran: {stale:?}"
    );
}

#[test]
fn every_public_float_function_is_swept_or_exempt() {
    let items: BTreeSet<String> = public_items()
        .into_iter()
        .filter(|i| module_enabled(i))
        .collect();
    assert!(items.len() > 50, "scanner found only {} items", items.len());
    let covered = covered();
    let missing: Vec<&String> = items
        .iter()
        .filter(|i| !covered.contains(&i.as_str()) && !EXEMPT.iter().any(|(p, _)| i.starts_with(p)))
        .collect();
    assert!(
        missing.is_empty(),
        "public items neither swept in tests/stiff_cases.rs nor exempted with a reason:\n{}",
        missing
            .iter()
            .map(|s| s.as_str())
            .collect::<Vec<_>>()
            .join("\n")
    );
    let unknown: Vec<&str> = COVERED
        .iter()
        .copied()
        .filter(|c| !items.contains(*c))
        .collect();
    assert!(
        unknown.is_empty(),
        "COVERED names items that no longer exist: {unknown:?}"
    );
}

/// A host-side vector result as a `[3]` f64 tensor, so the suite checks it is finite.
fn host3(v: DVec3) -> neural_fields::Result<Tensor> {
    Ok(Tensor::new(&v.to_array(), &Device::Cpu)?)
}

fn sweep_camera_host(s: &mut Suite) {
    let k = Intrinsics::new(500.0, 400.0, 32.0, 24.0, 64, 48).unwrap();
    // Pose steps and damped Gauss–Newton systems at every magnitude: finite poses, and
    // steps that are finite or refused (`None`).
    for &x in &magnitudes(DType::F64) {
        let x = x.clamp(-1e150, 1e150);
        s.case(
            "camera::retract_pose",
            format!("step of {x:e}"),
            Expect::Finite,
            &[],
            || {
                let pose = DAffine3::from_translation(DVec3::splat(x));
                let moved = neural_fields::camera::retract_pose(&pose, [x, -x, 0.5, x, 1.0, -x]);
                Ok(vec![
                    host3(moved.translation)?,
                    host3(moved.matrix3.x_axis)?,
                    host3(moved.matrix3.z_axis)?,
                ])
            },
        );
        for lambda in [0.0, 1e-3, 1e300] {
            s.case(
                "numerics::damped_solve",
                format!("system scaled by {x:e}, λ = {lambda:e}"),
                Expect::FiniteOrErr,
                &[],
                || {
                    let h = [[4.0 * x, x], [x, 2.0 * x]];
                    let step = neural_fields::numerics::damped_solve(&h, &[x, -1.0], lambda)
                        .ok_or_else(|| neural_fields::Error::InvalidArgument {
                            arg: "h",
                            expected: "a solvable system".into(),
                            got: "none".into(),
                        })?;
                    Ok(vec![Tensor::new(&step, &Device::Cpu)?])
                },
            );
        }
    }
    for r in [1e-6, 1.0, 1e6, 1e150] {
        s.case(
            "camera::cameras_around",
            format!("cameras at distance {r:e}"),
            Expect::FiniteOrErr,
            &[],
            || {
                let cams: Vec<Camera> = [DVec3::X, DVec3::Y, -DVec3::X]
                    .iter()
                    .map(|&e| {
                        Camera::look_at(
                            k,
                            (e + DVec3::Z * 0.3) * r,
                            DVec3::ZERO,
                            DVec3::Z,
                            Convention::OpenGl,
                        )
                    })
                    .collect::<neural_fields::Result<_>>()?;
                let around = neural_fields::camera::cameras_around(&cams, 8, 1)?;
                around.iter().map(|c| host3(c.center())).collect()
            },
        );
    }
    // Alignment by the views of scenes at every magnitude (cameras 3·x from the scene,
    // points within 0.3·x), onto a copy scaled by up to 1e±150: finite maps, or `Err`
    // for scenes whose cameras or points over- or underflow.
    let cams = |x: f64, scale: f64| -> neural_fields::Result<Vec<Camera>> {
        let k = Intrinsics::from_fov_y(32, 32, 0.6)?;
        [DVec3::X, -DVec3::X, DVec3::Y, DVec3::Z]
            .iter()
            .map(|&e| {
                Camera::look_at(
                    k,
                    e * 3.0 * x * scale,
                    DVec3::ZERO,
                    DVec3::new(0.1, 0.2, 1.0),
                    Convention::OpenCv,
                )
            })
            .collect()
    };
    for &x in &magnitudes(DType::F64) {
        for ratio in [1e-150, 1.0, 1e150] {
            s.case(
                "camera::align_cameras",
                format!("scene at scale {x:e}, copy scaled by {ratio:e}"),
                Expect::FiniteOrErr,
                &[],
                || {
                    let points = [DVec3::ZERO, DVec3::X * 0.3 * x, DVec3::Y * 0.3 * x];
                    let sim = align_cameras(&cams(x, 1.0)?, &cams(x, ratio)?, &points)?;
                    Ok(vec![
                        host3(sim.transform_point(points[1]))?,
                        Tensor::new(&[sim.scale, sim.rotation.w], &Device::Cpu)?,
                    ])
                },
            );
            // The residual of that alignment: finite pixels, or `Err`.
            s.case(
                "camera::reprojection_error",
                format!("scene at scale {x:e}, copy scaled by {ratio:e}"),
                Expect::FiniteOrErr,
                &[],
                || {
                    let points = [DVec3::ZERO, DVec3::X * 0.3 * x, DVec3::Y * 0.3 * x];
                    let frame = Similarity {
                        scale: ratio,
                        ..Similarity::IDENTITY
                    };
                    let px = reprojection_error(&cams(x, 1.0)?, &cams(x, ratio)?, &points, &frame)?;
                    Ok(vec![Tensor::new(&[px], &Device::Cpu)?])
                },
            );
        }
    }
    // Similarity alignment of clouds at every magnitude (and onto a cloud scaled by up to
    // 1e±150): finite maps, or `Err` for clouds whose spread over- or underflows.
    for &x in &magnitudes(DType::F64) {
        for ratio in [1e-150, 1.0, 1e150] {
            s.case(
                "camera::align_similarity",
                format!("cloud at {x:e}, scaled by {ratio:e}"),
                Expect::FiniteOrErr,
                &[],
                || {
                    let from: Vec<DVec3> = [DVec3::X, DVec3::Y, DVec3::Z, DVec3::ONE]
                        .iter()
                        .map(|&p| p * x + DVec3::splat(x))
                        .collect();
                    let to: Vec<DVec3> = from
                        .iter()
                        .map(|&p| DVec3::new(p.y, -p.x, p.z) * ratio)
                        .collect();
                    let sim = align_similarity(&from, &to)?;
                    let pose = DAffine3::from_translation(DVec3::splat(x));
                    let moved = sim.inverse().transform_pose(&sim.transform_pose(&pose));
                    Ok(vec![
                        host3(sim.transform_point(from[0]))?,
                        host3(moved.translation)?,
                        Tensor::new(&[sim.scale, sim.rotation.w], &Device::Cpu)?,
                    ])
                },
            );
            for name in [
                "camera::Similarity::inverse",
                "camera::Similarity::transform_pose",
                "camera::Similarity::transform_point",
            ] {
                s.case(
                    name,
                    format!("scale {ratio:e}, point {x:e}"),
                    Expect::Finite,
                    &[],
                    || {
                        let sim = Similarity {
                            scale: ratio,
                            rotation: DQuat::from_rotation_z(0.5),
                            translation: DVec3::splat(1.0),
                        };
                        let p = DVec3::splat(x.clamp(-1e100, 1e100));
                        let pose = sim.transform_pose(&DAffine3::from_translation(p));
                        Ok(vec![
                            host3(sim.inverse().transform_point(p))?,
                            host3(pose.translation)?,
                        ])
                    },
                );
            }
        }
    }
    for convention in [Convention::OpenCv, Convention::OpenGl] {
        let cam = Camera::look_at(
            k,
            DVec3::new(1.0, -2.0, 0.5),
            DVec3::ZERO,
            DVec3::Z,
            convention,
        )
        .unwrap();
        for &x in &magnitudes(DType::F64) {
            s.case(
                "camera::Camera::ray",
                format!("{convention:?}, pixel ({x}, {x})"),
                Expect::Finite,
                &[],
                || {
                    let (o, d) = cam.ray(neural_fields::glam::DVec2::new(x, -x));
                    Ok(vec![host3(o)?, host3(d)?])
                },
            );
            // Points on and near the camera plane, behind it and far in front: `None` or a
            // finite pixel, never an infinite one.
            let c = cam.center();
            let axis = cam.cam_to_world().matrix3.z_axis;
            for p in [
                c + DVec3::splat(x),
                c + axis * x + DVec3::new(1.0, 0.0, 0.0),
                DVec3::splat(x),
            ] {
                s.case(
                    "camera::Camera::project",
                    format!("{convention:?}, point {p}"),
                    Expect::Finite,
                    &[],
                    || Ok(cam.project(p).map(host3).transpose()?.into_iter().collect()),
                );
            }
        }
    }
}

#[cfg(feature = "data")]
fn sweep_data(s: &mut Suite) {
    use neural_fields::data::{
        colorize_depth, colorize_normals, comparison_strip, load, psnr, ssim, write_blender,
        write_png, Background, Dataset, Image, LoadConfig, RaySampler, Split, View,
    };
    let d = Device::Cpu;
    let scalar = |x: f64| Ok::<_, neural_fields::Error>(Tensor::new(x, &d)?);
    let dir = std::env::temp_dir().join(format!("neural-fields-stiff-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    for dtype in DTYPES {
        for &x in &magnitudes(dtype) {
            let tag = format!("{dtype:?}, {x}");
            let full = |shape: &[usize]| Tensor::full(x, shape, &d).and_then(|t| t.to_dtype(dtype));
            let half =
                |shape: &[usize]| Tensor::full(0.5, shape, &d).and_then(|t| t.to_dtype(dtype));
            s.case(
                "data::metrics::psnr",
                &tag,
                Expect::FiniteOrErr,
                &[],
                || {
                    let p = psnr(&full(&[12, 12, 3])?, &half(&[12, 12, 3])?, None)?;
                    // Identical images (x = 0.5) give +∞ by contract; never NaN or −∞.
                    assert!(!p.is_nan() && p != f64::NEG_INFINITY);
                    Ok(if p == f64::INFINITY {
                        vec![]
                    } else {
                        vec![scalar(p)?]
                    })
                },
            );
            s.case(
                "data::metrics::ssim",
                &tag,
                Expect::FiniteOrErr,
                &[],
                || {
                    let p = ssim(&full(&[12, 12, 3])?, &half(&[12, 12, 3])?, None)?;
                    Ok(vec![scalar(p)?])
                },
            );
            s.case(
                "data::output::colorize_depth",
                &tag,
                Expect::Finite,
                &[],
                || {
                    let depth = Tensor::cat(&[&full(&[2, 2])?, &half(&[2, 2])?], 1)?;
                    let (rgb, (lo, hi)) = colorize_depth(&depth, None)?;
                    Ok(vec![rgb, scalar(lo)?, scalar(hi)?])
                },
            );
            s.case(
                "data::output::colorize_normals",
                &tag,
                Expect::FiniteOrErr,
                &[],
                || Ok(vec![colorize_normals(&full(&[2, 2, 3])?)?]),
            );
            s.case(
                "data::output::comparison_strip",
                &tag,
                Expect::FiniteOrErr,
                &[],
                || {
                    Ok(vec![comparison_strip(
                        &half(&[2, 2, 3])?,
                        &full(&[2, 2, 3])?,
                    )?])
                },
            );
            s.case(
                "data::image::Image::from_tensor",
                &tag,
                Expect::Finite,
                &[],
                || {
                    let img = Image::from_tensor(&full(&[2, 3, 4])?)?;
                    Ok(vec![img.to_tensor(&d, dtype)?])
                },
            );
            s.case("data::output::write_png", &tag, Expect::Finite, &[], || {
                write_png(&dir.join("stiff.png"), &full(&[2, 3, 3])?)?;
                Ok(vec![])
            });
            s.case(
                "data::dataset::Dataset::new",
                &tag,
                Expect::FiniteOrErr,
                &[],
                || {
                    let k = Intrinsics::new(3.0, 3.0, 1.0, 1.0, 2, 2)?;
                    let cam = Camera::new(k, DAffine3::IDENTITY, Convention::OpenCv)?;
                    let view = View::new(cam, Image::new(2, 2, 3, vec![9; 12])?, None, "v".into())?;
                    let data = Dataset::new(vec![view], Background::Color([x; 3]), None)?;
                    Ok(vec![data.views()[0].rgb(
                        [x.clamp(0.0, 1.0); 3],
                        &d,
                        dtype,
                    )?])
                },
            );
        }
        s.case(
            "data::image::Image::to_tensor",
            format!("{dtype:?}, bytes 0 and 255"),
            Expect::Finite,
            &[],
            || {
                Ok(vec![
                    Image::new(2, 1, 3, vec![0, 0, 0, 255, 255, 255])?.to_tensor(&d, dtype)?
                ])
            },
        );
        // Cameras at extreme focal lengths and distances: rays finite or an error.
        for (f, eye) in [(1e-6, 1.0), (1e8, 1.0), (500.0, 1e10), (500.0, 1e-10)] {
            let tag = format!("{dtype:?}, fx {f}, eye at {eye}");
            let view = || -> neural_fields::Result<View> {
                let k = Intrinsics::new(f, f, 2.0, 2.0, 4, 4)?;
                let cam = Camera::look_at(
                    k,
                    DVec3::new(eye, 0.0, 0.0),
                    DVec3::ZERO,
                    DVec3::Z,
                    Convention::OpenGl,
                )?;
                View::new(
                    cam,
                    Image::new(4, 4, 4, (0..64).map(|i| (i * 4) as u8).collect())?,
                    None,
                    "v".into(),
                )
            };
            s.case(
                "data::dataset::View::new",
                &tag,
                Expect::Finite,
                &[],
                || {
                    let v = view()?;
                    Ok(vec![
                        v.rgb([0.0; 3], &d, dtype)?,
                        v.mask(&d, dtype)?.expect("alpha"),
                    ])
                },
            );
            s.case(
                "data::dataset::View::rgb",
                &tag,
                Expect::Finite,
                &[],
                || Ok(vec![view()?.rgb([1.0; 3], &d, dtype)?]),
            );
            s.case(
                "data::dataset::View::mask",
                &tag,
                Expect::Finite,
                &[],
                || Ok(view()?.mask(&d, dtype)?.into_iter().collect()),
            );
            let data = Dataset::new(vec![view().unwrap()], Background::Random, None).unwrap();
            s.case(
                "data::batch::RaySampler::new",
                &tag,
                Expect::FiniteOrErr,
                &[],
                || {
                    RaySampler::new(&data, 0, &d, dtype)?;
                    Ok(vec![])
                },
            );
            s.case(
                "data::batch::RaySampler::pixels",
                &tag,
                Expect::FiniteOrErr,
                &[],
                || {
                    let b = RaySampler::new(&data, 0, &d, dtype)?.pixels(64)?;
                    Ok(vec![
                        b.rays.directions().clone(),
                        b.rays.origins().clone(),
                        b.colors,
                        b.backgrounds,
                    ])
                },
            );
            s.case(
                "data::batch::RaySampler::pixel_footprints",
                &tag,
                Expect::FiniteOrErr,
                &[],
                || {
                    let b = RaySampler::new(&data, 0, &d, dtype)?
                        .with_jitter(true)
                        .pixel_footprints(16, 2)?;
                    Ok(vec![b.rays.directions().clone(), b.colors, b.backgrounds])
                },
            );
            for half_width in [1.5, 64.0, 0.0, f64::INFINITY] {
                s.case(
                    "data::batch::RaySampler::with_pixel_filter",
                    format!("{tag}, Blackman-Harris ±{half_width}"),
                    Expect::FiniteOrErr,
                    &[],
                    || {
                        let filter = PixelFilter::BlackmanHarris { half_width };
                        let mut sampler = RaySampler::new(&data, 0, &d, dtype)?
                            .with_jitter(true)
                            .with_pixel_filter(filter)?;
                        let (a, b) = (sampler.pixels(64)?, sampler.pixel_footprints(16, 3)?);
                        Ok(vec![
                            a.rays.directions().clone(),
                            b.rays.directions().clone(),
                        ])
                    },
                );
            }
            s.case(
                "data::batch::RaySampler::patches",
                &tag,
                Expect::FiniteOrErr,
                &[],
                || {
                    let b = RaySampler::new(&data, 0, &d, dtype)?.patches(4, 3)?;
                    Ok(vec![b.rays.directions().clone(), b.colors])
                },
            );
            s.case(
                "data::batch::Dataset::view_rays",
                &tag,
                Expect::FiniteOrErr,
                &[],
                || {
                    let b = data.view_rays(0, 0, 16, &d, dtype)?;
                    Ok(vec![b.rays.directions().clone(), b.colors])
                },
            );
            s.case(
                "data::transforms::write_blender",
                &tag,
                Expect::FiniteOrErr,
                &[],
                || {
                    let out = dir.join(format!("blender-{f}-{eye}"));
                    write_blender(&out, Split::Test, &data)?;
                    let back = load(
                        &out,
                        &LoadConfig {
                            split: Split::Test,
                            ..LoadConfig::default()
                        },
                    )?;
                    Ok(vec![back.views()[0].rgb([0.0; 3], &d, dtype)?])
                },
            );
        }
    }
    for downscale in [1, 7, 100, 101, usize::MAX] {
        s.case(
            "data::dataset::load",
            format!("downscale {downscale}"),
            Expect::FiniteOrErr,
            &[],
            || {
                let data = load(
                    std::path::Path::new("examples/data/wuson"),
                    &LoadConfig {
                        split: Split::Val,
                        downscale,
                        ..LoadConfig::default()
                    },
                )?;
                Ok(vec![data.views()[0].rgb([1.0; 3], &d, DType::F32)?])
            },
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
}

fn sweep_nerf(s: &mut Suite) {
    use neural_fields::nn::{nerf, DensityActivation, NerfConfig};
    let d = Device::Cpu;
    for dtype in DTYPES {
        let big = if dtype == DType::F32 { 1e8 } else { 1e100 };
        let pts = [
            0.0, 0.0, 0.0, 1e-30, 0.0, 0.0, big, -big, big, 1e4, 1.0, -1e4,
        ];
        // Directions: zero, tiny, huge, ordinary.
        let dirs = [
            0.0, 0.0, 0.0, 1e-30, 0.0, 0.0, big, big, -big, 0.3, -0.4, 0.5,
        ];
        for (density, tag) in [
            (DensityActivation::TruncExp { shift: -1.0 }, "trunc_exp"),
            (DensityActivation::Softplus { shift: -1.0 }, "softplus"),
        ] {
            let config = NerfConfig {
                density,
                width: 16,
                color_width: 8,
                ..NerfConfig::default()
            };
            let varmap = candle_nn::VarMap::new();
            let label = format!("{dtype:?}, {tag}, |x| up to {big:e}");
            s.case("nn::nerf::nerf", &label, Expect::Finite, &[], || {
                build_seeded(&varmap, dtype, &d, 5, |vb| nerf(&config, vb))?;
                Ok(vec![])
            });
            let net = build_seeded(&varmap, dtype, &d, 5, |vb| nerf(&config, vb)).unwrap();
            let vars = varmap.all_vars();
            let (x, v) = (var(&pts, &[4, 3], dtype), var(&dirs, &[4, 3], dtype));
            let mut wrt: Vec<&Var> = vars.iter().collect();
            wrt.push(&x);
            s.case(
                "nn::nerf::Nerf::density",
                &label,
                Expect::Finite,
                &wrt,
                || Ok(vec![net.density(x.as_tensor())?]),
            );
            wrt.push(&v);
            s.case(
                "nn::nerf::Nerf::radiance",
                &label,
                Expect::Finite,
                &wrt,
                || {
                    let (sigma, rgb) = net.radiance(x.as_tensor(), v.as_tensor())?;
                    Ok(vec![sigma, rgb])
                },
            );
            // The fused training loss: rays from the origin, from ±big and from 1e-30,
            // along tiny, huge and ordinary directions (rays have none of length 0), over [0, 1], [0, big] and
            // [1e-30, 2e-30]; targets in [0, 1].
            #[cfg(feature = "volume")]
            {
                use neural_fields::camera::Rays;
                use neural_fields::volume::{stratified, CompositeConfig, Jitter};
                let t = |v: &[f64], shape: &[usize]| {
                    Tensor::from_slice(v, shape, &d)
                        .unwrap()
                        .to_dtype(dtype)
                        .unwrap()
                };
                let mut ray_dirs = dirs;
                ray_dirs[2] = 1.0;
                let rays = Rays::new(t(&pts, &[4, 3]), t(&ray_dirs, &[4, 3])).unwrap();
                let near = t(&[0.0, 0.0, 1e-30, 0.0], &[4]);
                let far = t(&[1.0, big, 2e-30, 1.0], &[4]);
                let target = t(
                    &[0.0, 0.5, 1.0, 1.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.2, 0.3, 0.4],
                    &[4, 3],
                );
                let wrt: Vec<&Var> = vars.iter().collect();
                s.case(
                    "nn::nerf::Nerf::color_loss",
                    &label,
                    Expect::FiniteOrErr,
                    &wrt,
                    || {
                        let iv = stratified(&near, &far, 150, Jitter::PerSample, 0)?;
                        Ok(vec![net.color_loss(
                            &rays,
                            &iv,
                            &target,
                            &CompositeConfig::default(),
                        )?])
                    },
                );
            }
        }
    }
    #[cfg(feature = "volume")]
    for dtype in DTYPES {
        use neural_fields::volume::{stratified, Jitter};
        let top = if dtype == DType::F32 { 1e30 } else { 1e300 };
        let near = Tensor::new(&[0.0, -top, 1e-30], &d)
            .unwrap()
            .to_dtype(dtype)
            .unwrap();
        let far = Tensor::new(&[1.0, top, 2e-30], &d)
            .unwrap()
            .to_dtype(dtype)
            .unwrap();
        s.case(
            "volume::layout::Intervals::retain",
            format!("{dtype:?}, ±{top:e}"),
            Expect::FiniteOrErr,
            &[],
            || {
                let iv = stratified(&near, &far, 4, Jitter::None, 0)?;
                let mask = Tensor::new(&[[1u8, 0, 1, 0], [1, 1, 1, 1], [0, 0, 0, 1]], &d)?;
                let (kept, idx) = iv.retain(&mask)?;
                let (again, _) = kept.retain(&Tensor::ones(kept.starts.dims(), DType::U8, &d)?)?;
                Ok(vec![
                    kept.starts,
                    kept.ends,
                    again.midpoints()?,
                    idx.to_dtype(DType::F64)?,
                ])
            },
        );
        sweep_proposal(s, dtype, top);
    }
}

#[cfg(feature = "volume")]
fn sweep_proposal(s: &mut Suite, dtype: DType, top: f64) {
    use neural_fields::volume::{interlevel_loss, proposal_sample, ProposalConfig};
    let d = Device::Cpu;
    // Proposal sampling over extreme ranges and densities, and its loss's gradient.
    for (range, density) in [(1e-6, 1e6), (1.0, 0.0), (1e4, 1e-6), (top / 1e10, 1.0)] {
        let label = format!("{dtype:?}, range {range:e}, density {density:e}");
        let rays = Rays::new(
            Tensor::new(&[[0.0, 0.0, -1.0], [1.0, 2.0, 3.0]], &d)
                .unwrap()
                .to_dtype(dtype)
                .unwrap(),
            Tensor::new(&[[0.0, 0.0, 1.0], [1e-3, 0.0, -2.0]], &d)
                .unwrap()
                .to_dtype(dtype)
                .unwrap(),
        )
        .unwrap();
        let near = Tensor::zeros(2, dtype, &d).unwrap();
        let far = Tensor::full(range, 2, &d).unwrap().to_dtype(dtype).unwrap();
        let mut field = |p: &Tensor| -> neural_fields::Result<Tensor> {
            Ok((p.narrow(1, 0, 1)?.squeeze(1)?.abs()?.affine(0.0, 1.0)? * density)?)
        };
        let config = ProposalConfig {
            samples: vec![16],
            final_samples: 8,
            padding: 0.01,
        };
        let out = proposal_sample(&rays, &near, &far, &mut [&mut field], &config, Some(3));
        let first = out.as_ref().map(|o| o.clone()).map_err(|e| e.to_string());
        s.case(
            "volume::proposal::proposal_sample",
            &label,
            Expect::FiniteOrErr,
            &[],
            || {
                let out = first.map_err(|e| neural_fields::Error::InvalidArgument {
                    arg: "proposal",
                    expected: String::new(),
                    got: e,
                })?;
                Ok(vec![
                    out.intervals.starts,
                    out.intervals.ends,
                    out.levels[0].1.clone(),
                ])
            },
        );
        if let Ok(out) = out {
            let w_hat = Var::from_tensor(&out.levels[0].1).unwrap();
            let (r, n) = out.intervals.starts.dims2().unwrap();
            let w = Tensor::full(0.5, (r, n), &d)
                .unwrap()
                .to_dtype(dtype)
                .unwrap();
            s.case(
                "volume::proposal::interlevel_loss",
                &label,
                Expect::Finite,
                &[&w_hat],
                || {
                    let level = (out.levels[0].0.clone(), w_hat.as_tensor().clone());
                    Ok(vec![interlevel_loss(&level, &out.intervals, &w)?])
                },
            );
        }
    }
}

/// Items swept by `sweep_texture`.
const TEXTURE_COVERED: &[&str] = &[
    "nn::texture::texture_decoder",
    "nn::texture::TextureDecoder::rgb",
    "nn::texture::rendering_net",
    "nn::texture::RenderingNet::rgb",
    "nn::texture::joint_decoder",
    "nn::texture::JointDecoder::rgb",
    "nn::texture::JointDecoder::value",
    "nn::texture::JointDecoder::value_and_grad",
    "nn::texture::JointDecoder::forward",
    "texture::losses::image_gradient_loss",
];

/// The texture networks at extreme points, normals, directions, features and codes (zero
/// directions and normals included); the image-gradient loss on extreme colours; vertex
/// colours from a closure that returns extreme or non-finite values.
#[cfg(feature = "texture")]
fn sweep_texture(s: &mut Suite) {
    use neural_fields::nn::{
        joint_decoder, rendering_net, texture_decoder, RenderingNetConfig, TextureDecoderConfig,
    };
    use neural_fields::texture::{image_gradient_loss, TextureField, TextureInput};
    let d = Device::Cpu;
    for dtype in [DType::F32, DType::F64] {
        let big = if dtype == DType::F32 { 1e30 } else { 1e150 };
        let tag = format!("{dtype:?}, |x| up to {big:e}");
        let pts = extreme_points(dtype);
        let n = pts.dim(0).unwrap();
        let p = Var::from_tensor(&pts).unwrap();
        let mut rng = SplitMix64::new(11);
        let extreme = |cols: usize, rng: &mut SplitMix64| -> Var {
            let values: Vec<f64> = (0..n * cols)
                .map(|i| match i % 5 {
                    0 => 0.0,
                    1 => big,
                    2 => -1e-30,
                    _ => rng.normal(),
                })
                .collect();
            var(&values, &[n, cols], dtype)
        };
        let (nrm, dirs, feat) = (
            extreme(3, &mut rng),
            extreme(3, &mut rng),
            extreme(2, &mut rng),
        );
        let (c, z) = (extreme(2, &mut rng), extreme(1, &mut rng));
        let tcfg = TextureDecoderConfig {
            hidden: 8,
            blocks: 2,
            shape_code_dim: 2,
            image_code_dim: 1,
            encoding: PointEncoding::Frequency(FrequencyEncoding::new(3, 4).unwrap()),
        };
        let vm = candle_nn::VarMap::new();
        let tex = build_seeded(&vm, dtype, &d, 1, |vb| texture_decoder(&tcfg, vb)).unwrap();
        for item in [
            "nn::texture::texture_decoder",
            "nn::texture::TextureDecoder::rgb",
        ] {
            s.case(item, &tag, Expect::Finite, &[&p, &c, &z], || {
                let input = TextureInput::new(p.as_tensor())
                    .shape_code(c.as_tensor())
                    .image_code(z.as_tensor());
                Ok(vec![tex.rgb(&input)?])
            });
        }
        let rcfg = RenderingNetConfig {
            feature_dim: 2,
            hidden: 8,
            depth: 2,
            ..RenderingNetConfig::default()
        };
        let vm = candle_nn::VarMap::new();
        let render = build_seeded(&vm, dtype, &d, 2, |vb| rendering_net(&rcfg, vb)).unwrap();
        for item in [
            "nn::texture::rendering_net",
            "nn::texture::RenderingNet::rgb",
        ] {
            s.case(
                item,
                &tag,
                Expect::Finite,
                &[&p, &nrm, &dirs, &feat],
                || {
                    let input = TextureInput::new(p.as_tensor())
                        .normals(nrm.as_tensor())
                        .view_dirs(dirs.as_tensor())
                        .features(feat.as_tensor());
                    Ok(vec![render.rgb(&input)?])
                },
            );
        }
        let jcfg = MlpConfig {
            hidden: 8,
            depth: 2,
            ..MlpConfig::default()
        };
        let vm = candle_nn::VarMap::new();
        let joint = build_seeded(&vm, dtype, &d, 3, |vb| joint_decoder(&jcfg, vb)).unwrap();
        for item in [
            "nn::texture::joint_decoder",
            "nn::texture::JointDecoder::rgb",
        ] {
            s.case(item, &tag, Expect::Finite, &[&p], || {
                Ok(vec![joint.rgb(&TextureInput::new(p.as_tensor()))?])
            });
        }
        s.case(
            "nn::texture::JointDecoder::value",
            &tag,
            Expect::Finite,
            &[&p],
            || Ok(vec![joint.value(p.as_tensor())?]),
        );
        s.case(
            "nn::texture::JointDecoder::forward",
            &tag,
            Expect::Finite,
            &[&p],
            || Ok(vec![Field::forward(&joint, p.as_tensor())?]),
        );
        s.case(
            "nn::texture::JointDecoder::value_and_grad",
            &tag,
            Expect::Finite,
            &[&p],
            || {
                let (v, g) = joint.value_and_grad(p.as_tensor())?;
                Ok(vec![v, g])
            },
        );
        // The image-gradient loss on 2 × 2 patches of extreme colours.
        let mags = magnitudes(dtype);
        let colours = |shift: usize| -> Var {
            let values: Vec<f64> = (0..8 * 3).map(|i| mags[(i + shift) % mags.len()]).collect();
            var(&values, &[8, 3], dtype)
        };
        let (pred, target) = (colours(0), colours(5));
        let valid = Tensor::new(&[1u8, 1, 1, 1, 1, 0, 1, 1], &d).unwrap();
        s.case(
            "texture::losses::image_gradient_loss",
            format!(
                "{dtype:?}, colours in ±{:e}",
                mags.iter().fold(0.0f64, |m, x| m.max(x.abs()))
            ),
            Expect::Finite,
            &[&pred, &target],
            || {
                Ok(vec![
                    image_gradient_loss(pred.as_tensor(), target.as_tensor(), Some(&valid), 2)?,
                    image_gradient_loss(pred.as_tensor(), target.as_tensor(), None, 2)?,
                ])
            },
        );
        #[cfg(feature = "occupancy")]
        {
            use neural_fields::occupancy::Mesh;
            use neural_fields::texture::vertex_colors;
            let mesh = Mesh::new(
                vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
                vec![[0, 1, 2]],
            )
            .unwrap();
            for value in [0.0, 1e-300, 1.0, 1e300, -1e300, f64::INFINITY, f64::NAN] {
                s.case(
                    "texture::vertex_colors",
                    format!("{dtype:?}, closure returns {value:e}"),
                    // ±1e300 is infinite in f32, and an infinite colour is an error.
                    if value.is_finite() && (dtype == DType::F64 || value.abs() < 1e38) {
                        Expect::Finite
                    } else {
                        Expect::FiniteOrErr
                    },
                    &[],
                    || {
                        let colors = vertex_colors(&mesh, 2, &d, dtype, |p| {
                            Ok(Tensor::full(value, p.dims(), &d)?.to_dtype(dtype)?)
                        })?;
                        let flat: Vec<f64> = colors.concat();
                        Ok(vec![Tensor::from_vec(flat.clone(), flat.len(), &d)?])
                    },
                );
            }
        }
    }
}

/// Items swept by `sweep_grid_sample`.
const GRID_SAMPLE_COVERED: &[&str] = &[
    "encoding::grid_sample::grid_sample",
    "encoding::grid_sample::grid_sample_reference",
    "encoding::grid_sample::cell_index",
    "encoding::grid_sample::scatter_mean",
    "encoding::grid_sample::scatter_max",
    "encoding::grid_sample::scatter_max_reference",
];

/// Bilinear/trilinear sampling at coordinates far outside, on and just inside the border,
/// of features of every magnitude; scatter pooling of extreme values with ties.
fn sweep_grid_sample(s: &mut Suite) {
    use neural_fields::encoding::grid_sample::{
        cell_index, grid_sample, grid_sample_reference, scatter_max, scatter_max_reference,
        scatter_mean,
    };
    let d = Device::Cpu;
    for dtype in DTYPES {
        let mags = magnitudes(dtype);
        let big = if dtype == DType::F32 { 1e30 } else { 1e300 };
        let coords_1d = [
            0.0, 1e-30, -1e-30, 0.5, 1.0, -1.0, 0.999_999, 1.000_001, big, -big, 1e10, -0.25,
        ];
        for k in [2usize, 3] {
            let n = coords_1d.len();
            let coord_values: Vec<f64> =
                (0..n * k).map(|i| coords_1d[(i * 5 + i / k) % n]).collect();
            let coords = var(&coord_values, &[1, n, k], dtype);
            let spatial = vec![3usize; k];
            let cells: usize = spatial.iter().product();
            let feat_values: Vec<f64> =
                (0..2 * cells).map(|i| mags[(i * 7) % mags.len()]).collect();
            let mut shape = vec![1usize, 2];
            shape.extend(&spatial);
            let features = var(&feat_values, &shape, dtype);
            let label = format!("{dtype:?}, k = {k}, features and coordinates up to {big:e}");
            s.case(
                "encoding::grid_sample::grid_sample",
                &label,
                Expect::Finite,
                &[&features, &coords],
                || Ok(vec![grid_sample(features.as_tensor(), coords.as_tensor())?]),
            );
            s.case(
                "encoding::grid_sample::grid_sample_reference",
                &label,
                Expect::Finite,
                &[&features, &coords],
                || {
                    Ok(vec![grid_sample_reference(
                        features.as_tensor(),
                        coords.as_tensor(),
                    )?])
                },
            );
            s.case(
                "encoding::grid_sample::cell_index",
                &label,
                Expect::Finite,
                &[],
                || Ok(vec![cell_index(coords.as_tensor(), 4)?]),
            );
            let nan = coords
                .as_tensor()
                .slice_assign(
                    &[0..1, 0..1, 0..1],
                    &Tensor::full(f64::NAN, (1, 1, 1), &d)
                        .unwrap()
                        .to_dtype(dtype)
                        .unwrap(),
                )
                .unwrap();
            if grid_sample(features.as_tensor(), &nan).is_ok()
                || grid_sample_reference(features.as_tensor(), &nan).is_ok()
                || cell_index(&nan, 4).is_ok()
            {
                s.failures.push(format!(
                    "grid_sample / cell_index [{dtype:?}, k = {k}]: a NaN coordinate gave Ok"
                ));
            }
            // Scatter pooling of extreme values into the cells of those coordinates; the
            // repeated magnitudes make ties for the maximum.
            let Ok(index) = cell_index(coords.as_tensor(), 2) else {
                continue;
            };
            let values: Vec<f64> = (0..n * 3).map(|i| mags[(i * 3) % mags.len()]).collect();
            let values = var(&values, &[1, n, 3], dtype);
            let cells = 1usize << k;
            for (item, f) in [
                (
                    "encoding::grid_sample::scatter_mean",
                    scatter_mean as fn(&Tensor, &Tensor, usize) -> neural_fields::Result<Tensor>,
                ),
                ("encoding::grid_sample::scatter_max", scatter_max),
                (
                    "encoding::grid_sample::scatter_max_reference",
                    scatter_max_reference,
                ),
            ] {
                s.case(item, &label, Expect::Finite, &[&values], || {
                    Ok(vec![f(values.as_tensor(), &index, cells)?])
                });
            }
        }
    }
}

/// Items swept by `sweep_flow`.
const FLOW_COVERED: &[&str] = &[
    "flow::ode::odeint",
    "flow::velocity::velocity_field",
    "flow::velocity::VelocityField::velocity",
    "flow::velocity::VelocityField::carry",
    "flow::velocity::OccupancyFlow::logits",
    "flow::velocity::OccupancyFlow::correspondences",
    "flow::velocity::correspondence_loss",
];

/// The ODE solvers on stiff linear systems (decay rates up to 1e8, where RK4 blows up and
/// Dormand–Prince runs out of steps: both must end in `Err`, not in a non-finite state),
/// and with a right-hand side that returns NaN; the velocity field, carried points and
/// Occupancy Flow at extreme points, times and codes; the correspondence loss at zero
/// and extreme distances.
#[cfg(feature = "flow")]
fn sweep_flow(s: &mut Suite) {
    use neural_fields::flow::{
        correspondence_loss, odeint, velocity_field, Graph, OccupancyFlow, Solver,
        VelocityFieldConfig,
    };
    let d = Device::Cpu;
    let solvers = [
        Solver::Rk4 { steps: 8 },
        Solver::Dopri5 {
            rtol: 1e-3,
            atol: 1e-5,
            max_steps: 200,
        },
    ];
    for dtype in DTYPES {
        let mags = magnitudes(dtype);
        let y0 = var(&mags, &[mags.len()], dtype);
        for solver in &solvers {
            for rate in [0.0, 1e-30, 1.0, 1e3, 1e8] {
                // Stiff rates may end in Err (step limit, non-finite state); mild ones may not.
                let expect = if rate <= 1.0 {
                    Expect::Finite
                } else {
                    Expect::FiniteOrErr
                };
                s.case(
                    "flow::ode::odeint",
                    format!("{dtype:?}, {solver:?}, y' = -{rate:e} y, |y0| up to 1e30+"),
                    expect,
                    &[&y0],
                    || {
                        let out = odeint(
                            |_, y| Ok(y.affine(-rate, 0.0)?),
                            y0.as_tensor(),
                            &[0.0, 0.5, 1.0],
                            solver,
                            Graph::Keep,
                        )?;
                        Ok(out.states)
                    },
                );
            }
            let nan = odeint(
                |_, y| Ok((y * f64::NAN)?),
                y0.as_tensor(),
                &[0.0, 1.0],
                solver,
                Graph::Keep,
            );
            if nan.is_ok() {
                s.failures.push(format!(
                    "odeint [{dtype:?}, {solver:?}]: a right-hand side returning NaN gave Ok"
                ));
            }
        }

        let big = if dtype == DType::F32 { 1e8 } else { 1e100 };
        let p = var(
            &[
                0.0, 0.0, 0.0, 1e-30, 0.0, 0.0, big, -big, big, 1e4, 1.0, -1e4, 0.5, 0.5, 0.5,
            ],
            &[5, 3],
            dtype,
        );
        let code = var(
            &[0.0, big, -1e-30, 1.0, 0.5, -big, 1e4, 0.0, 2.0, -3.0],
            &[5, 2],
            dtype,
        );
        let config = VelocityFieldConfig {
            hidden: 8,
            blocks: 2,
            code_dim: 2,
        };
        let vm = candle_nn::VarMap::new();
        let v = build_seeded(&vm, dtype, &d, 4, |vb| velocity_field(&config, vb)).unwrap();
        let mut wrt: Vec<Var> = vm.all_vars();
        wrt.push(p.clone());
        wrt.push(code.clone());
        let wrt: Vec<&Var> = wrt.iter().collect();
        let label = format!("{dtype:?}, |p| and |code| up to {big:e}");
        s.case(
            "flow::velocity::velocity_field",
            &label,
            Expect::Finite,
            &[],
            || Ok(vec![]),
        );
        for t in [0.0, 1e-30, 0.5, 1.0] {
            s.case(
                "flow::velocity::VelocityField::velocity",
                format!("{label}, t = {t:e}"),
                Expect::Finite,
                &wrt,
                || {
                    Ok(vec![v.velocity(
                        p.as_tensor(),
                        t,
                        Some(code.as_tensor()),
                    )?])
                },
            );
        }
        for solver in &solvers {
            // |v| grows with |p|: Dormand–Prince may run out of steps on the huge points.
            s.case(
                "flow::velocity::VelocityField::carry",
                format!("{label}, {solver:?}"),
                Expect::FiniteOrErr,
                &wrt,
                || {
                    Ok(v.carry(
                        p.as_tensor(),
                        &[1.0, 0.25, 0.0],
                        Some(code.as_tensor()),
                        solver,
                        Graph::Keep,
                    )?
                    .states)
                },
            );
        }
        let dm = candle_nn::VarMap::new();
        let decoder_config = MlpConfig {
            hidden: 8,
            depth: 2,
            ..MlpConfig::default()
        };
        let decoder = build_seeded(&dm, dtype, &d, 5, |vb| mlp(&decoder_config, vb)).unwrap();
        let small = var(
            &[
                0.0, 0.0, 0.0, 1e-30, 0.0, 0.0, 0.5, -0.5, 0.5, 1.0, 1.0, -1.0, 0.2, 0.1, 0.0,
            ],
            &[5, 3],
            dtype,
        );
        let shared = code.as_tensor().get(1).unwrap();
        let flow = OccupancyFlow {
            decoder: &decoder,
            velocity: &v,
            code: Some(&shared),
            solver: Solver::occupancy_flow(),
            graph: Graph::Keep,
        };
        let mut fwrt: Vec<Var> = vm.all_vars();
        fwrt.extend(dm.all_vars());
        fwrt.push(small.clone());
        let fwrt: Vec<&Var> = fwrt.iter().collect();
        let flabel = format!("{dtype:?}, code up to {big:e}");
        for t in [0.0, 1e-30, 0.5, 1.0] {
            s.case(
                "flow::velocity::OccupancyFlow::logits",
                format!("{flabel}, t = {t:e}"),
                Expect::FiniteOrErr,
                &fwrt,
                || Ok(vec![flow.logits(small.as_tensor(), t)?]),
            );
        }
        s.case(
            "flow::velocity::OccupancyFlow::correspondences",
            &flabel,
            Expect::FiniteOrErr,
            &fwrt,
            || flow.correspondences(small.as_tensor(), &[0.0, 1e-30, 0.5, 1.0]),
        );
        // A moderate code: Occupancy Flow must succeed.
        let unit = Tensor::new(&[0.3, -0.2], &d)
            .unwrap()
            .to_dtype(dtype)
            .unwrap();
        let moderate = OccupancyFlow {
            code: Some(&unit),
            ..flow
        };
        s.case(
            "flow::velocity::OccupancyFlow::logits",
            format!("{dtype:?}, moderate code, t = 0.75"),
            Expect::Finite,
            &fwrt,
            || Ok(vec![moderate.logits(small.as_tensor(), 0.75)?]),
        );
        s.case(
            "flow::velocity::OccupancyFlow::correspondences",
            format!("{dtype:?}, moderate code"),
            Expect::Finite,
            &fwrt,
            || moderate.correspondences(small.as_tensor(), &[0.25, 1.0]),
        );
        // Zero distances (the norm's kink) and extreme ones.
        let top = if dtype == DType::F32 { 1e18 } else { 1e150 };
        let pred = var(
            &[
                0.0, 0.0, 0.0, 1.0, 2.0, 3.0, top, -top, top, 1e-30, 0.0, 0.0,
            ],
            &[4, 3],
            dtype,
        );
        let target = var(
            &[0.0, 0.0, 0.0, 1.0, 2.0, 3.0, -top, top, 0.0, 0.0, 0.0, 0.0],
            &[4, 3],
            dtype,
        );
        s.case(
            "flow::velocity::correspondence_loss",
            format!("{dtype:?}, distances 0 to {top:e}"),
            Expect::Finite,
            &[&pred, &target],
            || {
                Ok(vec![correspondence_loss(
                    pred.as_tensor(),
                    target.as_tensor(),
                )?])
            },
        );
    }
}

/// Items swept by `sweep_conv_onet`.
const CONV_ONET_COVERED: &[&str] = &[
    "nn::conv_onet::conv_onet_encoder",
    "nn::conv_onet::ConvOnetEncoder::forward",
    "nn::conv_onet::ConvOnetEncoder::encode_cloud",
    "nn::conv_onet::local_decoder",
    "nn::conv_onet::LocalDecoder::logits",
    "nn::conv_onet::LocalDecoder::bind",
    "nn::conv_onet::SceneField::forward",
    "nn::conv_onet::conv3d",
];

/// Conv. ONet on point clouds with coordinates from 0 to far outside the padded box (in
/// both layouts), the decoder at such points, and `conv3d` on extreme inputs.
#[cfg(feature = "occupancy")]
fn sweep_conv_onet(s: &mut Suite) {
    use neural_fields::nn::{
        conv3d, conv_onet_encoder, local_decoder, ConvOnetConfig, FeatureLayout,
        LocalDecoderConfig, UnetConfig,
    };
    use neural_fields::occupancy::PointCloud;
    let d = Device::Cpu;
    for dtype in DTYPES {
        let big = if dtype == DType::F32 { 1e8 } else { 1e100 };
        let rows: Vec<[f64; 3]> = vec![
            [0.0, 0.0, 0.0],
            [1e-30, 0.0, 0.0],
            [0.5, 0.5, 0.5],
            [-0.55, 0.55, 0.0],
            [big, -big, big],
            [1e4, 1.0, -1e4],
        ];
        let n = rows.len();
        let p = var(&rows.concat(), &[1, n, 3], dtype);
        for layout in [
            FeatureLayout::Planes { resolution: 4 },
            FeatureLayout::Grid { resolution: 4 },
        ] {
            let config = ConvOnetConfig {
                layout,
                hidden: 8,
                blocks: 2,
                feature_dim: 4,
                unet: UnetConfig {
                    depth: 2,
                    start_filters: 4,
                },
                ..ConvOnetConfig::default()
            };
            let dconfig = LocalDecoderConfig {
                hidden: 8,
                blocks: 2,
                feature_dim: 4,
                padding: config.padding,
            };
            let vm = candle_nn::VarMap::new();
            let (enc, dec) = build_seeded(&vm, dtype, &d, 6, |vb| {
                Ok((
                    conv_onet_encoder(&config, vb.pp("enc"))?,
                    local_decoder(&dconfig, vb.pp("dec"))?,
                ))
            })
            .unwrap();
            let mut wrt: Vec<Var> = vm.all_vars();
            wrt.push(p.clone());
            let wrt: Vec<&Var> = wrt.iter().collect();
            let label = format!("{dtype:?}, {layout:?}, |p| up to {big:e}");
            for item in [
                "nn::conv_onet::conv_onet_encoder",
                "nn::conv_onet::local_decoder",
            ] {
                s.case(item, &label, Expect::Finite, &[], || Ok(vec![]));
            }
            s.case(
                "nn::conv_onet::ConvOnetEncoder::forward",
                &label,
                Expect::Finite,
                &wrt,
                || {
                    let f = enc.forward(p.as_tensor())?;
                    Ok(match f {
                        neural_fields::nn::LocalFeatures::Planes { xz, xy, yz } => {
                            vec![xz, xy, yz]
                        }
                        neural_fields::nn::LocalFeatures::Grid(g) => vec![g],
                    })
                },
            );
            s.case(
                "nn::conv_onet::LocalDecoder::logits",
                &label,
                Expect::Finite,
                &wrt,
                || {
                    let f = enc.forward(p.as_tensor())?;
                    Ok(vec![dec.logits(p.as_tensor(), &f)?])
                },
            );
            let cloud = PointCloud::new(rows.clone()).unwrap();
            for item in [
                "nn::conv_onet::ConvOnetEncoder::encode_cloud",
                "nn::conv_onet::LocalDecoder::bind",
                "nn::conv_onet::SceneField::forward",
            ] {
                s.case(item, &label, Expect::Finite, &wrt, || {
                    let field = dec.bind(enc.encode_cloud(&cloud)?)?;
                    Ok(vec![field.forward(&p.as_tensor().squeeze(0)?)?])
                });
            }
        }
        // conv3d: extreme inputs under unit weights, extreme weights under unit inputs.
        let mags = magnitudes(dtype);
        let extreme: Vec<f64> = (0..2 * 27).map(|i| mags[(i * 5) % mags.len()]).collect();
        let unit: Vec<f64> = (0..2 * 27).map(|i| ((i % 7) as f64 - 3.0) / 3.0).collect();
        for (x, w, tag) in [(&extreme, &unit, "inputs"), (&unit, &extreme, "weights")] {
            let x = var(x, &[1, 2, 3, 3, 3], dtype);
            let w = var(w, &[1, 2, 3, 3, 3], dtype);
            s.case(
                "nn::conv_onet::conv3d",
                format!("{dtype:?}, extreme {tag}"),
                Expect::Finite,
                &[&x, &w],
                || {
                    Ok(vec![
                        conv3d(x.as_tensor(), w.as_tensor(), 1)?,
                        conv3d(x.as_tensor(), w.as_tensor(), 0)?,
                    ])
                },
            );
        }
    }
}
