//! Table-driven input validation: every public tensor-taking function of `field`,
//! `encoding` and `nn::Mlp` is fed a wrong-rank tensor (`[N, 2]` or rank 1 where
//! `[N, 3]` is expected, or the analogue for its argument) and a U32 tensor, and must
//! return an `Err` whose message starts with the argument's name (`"points: …"`).
//! Each row also runs once with a good tensor and must succeed, so a row cannot pass
//! because its set-up is broken.
//! `Rays::new`, which validates rays once for every ray function, is fed the same and
//! non-finite values and zero directions.

use candle_core::{DType, Device, Tensor};
use candle_nn::{VarBuilder, VarMap};
use neural_fields::encoding::{
    integrated_pe, Encoding, FourierFeatures, FrequencyEncoding, PointEncoding,
};
use neural_fields::field::{
    ConditionalField, Conditioned, Cuboid, Field, ImplicitSurface, Plane, SignedDistance, Sphere,
    Torus,
};
use neural_fields::nn::{mlp, Mlp, MlpConfig};

const N: usize = 4;
const CODE: usize = 4;

type Call<'a> = Box<dyn Fn(&Tensor) -> Result<(), String> + 'a>;

/// One function and the argument that receives the tensor under test.
struct Case<'a> {
    what: String,
    arg: &'static str,
    good: Tensor,
    bad: Vec<Tensor>,
    call: Call<'a>,
}

fn t(shape: &[usize], dtype: DType) -> Tensor {
    Tensor::zeros(shape, dtype, &Device::Cpu).unwrap()
}

/// Points in general position (none at a centre, on an axis or a crease).
fn good_points() -> Tensor {
    Tensor::new(
        &[
            [0.3f64, 0.1, 0.2],
            [-0.4, 0.25, 0.05],
            [0.15, -0.35, 0.45],
            [0.6, 0.2, -0.1],
        ],
        &Device::Cpu,
    )
    .unwrap()
}

/// Wrong for an `[N, 3]` float argument: `[N, 2]`, rank 1, U32.
fn bad_points() -> Vec<Tensor> {
    vec![
        t(&[N, 2], DType::F64),
        t(&[3], DType::F64),
        t(&[N, 3], DType::U32),
    ]
}

fn ok<T>(r: neural_fields::Result<T>) -> Result<(), String> {
    r.map(|_| ()).map_err(|e| e.to_string())
}

fn shape_cases<'a, S: SignedDistance + Clone + 'a>(name: &str, shape: S) -> Vec<Case<'a>> {
    let case = |what: &str, call: Call<'a>| Case {
        what: format!("{name}: {what}"),
        arg: "points",
        good: good_points(),
        bad: bad_points(),
        call,
    };
    let (s, sdf, occ) = (
        shape.clone(),
        shape.clone().sdf(),
        shape.clone().occupancy(10.0),
    );
    let (sdf2, occ2, sdf3, occ3) = (sdf.clone(), occ.clone(), sdf.clone(), occ.clone());
    vec![
        case(
            "distance_and_grad",
            Box::new(move |p| ok(s.distance_and_grad(p))),
        ),
        case("Sdf::value", Box::new(move |p| ok(sdf.value(p)))),
        case(
            "Sdf::value_and_grad",
            Box::new(move |p| ok(sdf2.value_and_grad(p))),
        ),
        case(
            "Sdf as Field::forward",
            Box::new(move |p| ok(Field::forward(&sdf3, p))),
        ),
        case("Occupancy::value", Box::new(move |p| ok(occ.value(p)))),
        case(
            "Occupancy::value_and_grad",
            Box::new(move |p| ok(occ2.value_and_grad(p))),
        ),
        case(
            "Occupancy as Field::forward",
            Box::new(move |p| ok(Field::forward(&occ3, p))),
        ),
    ]
}

/// A row for an `[N, 3]` argument named `points`.
fn points_case<'a>(what: &str, call: Call<'a>) -> Case<'a> {
    Case {
        what: what.to_string(),
        arg: "points",
        good: good_points(),
        bad: bad_points(),
        call,
    }
}

/// A row for `[N, CODE]` latent codes: wrong width, rank 1, U32.
fn codes_case<'a>(what: &str, call: Call<'a>) -> Case<'a> {
    Case {
        what: what.to_string(),
        arg: "codes",
        good: Tensor::ones((N, CODE), DType::F64, &Device::Cpu).unwrap(),
        bad: vec![
            t(&[N, 2], DType::F64),
            t(&[CODE], DType::F64),
            t(&[N, CODE], DType::U32),
        ],
        call,
    }
}

fn net(code_dim: usize) -> (VarMap, Mlp) {
    let varmap = VarMap::new();
    let vb = VarBuilder::from_varmap(&varmap, DType::F64, &Device::Cpu);
    let config = MlpConfig {
        code_dim,
        hidden: 8,
        depth: 2,
        ..MlpConfig::default()
    };
    let net = mlp(&config, vb).unwrap();
    (varmap, net)
}

fn run(cases: Vec<Case<'_>>) {
    let mut checked = 0;
    for case in cases {
        let Case {
            what,
            arg,
            good,
            bad,
            call,
        } = case;
        if let Err(e) = call(&good) {
            panic!("{what}: the good input must be accepted, got {e}");
        }
        for b in bad {
            match call(&b) {
                Ok(()) => panic!(
                    "{what}: {arg} of shape {:?} and dtype {:?} was accepted",
                    b.dims(),
                    b.dtype()
                ),
                Err(e) => assert!(
                    e.starts_with(&format!("{arg}: ")),
                    "{what}: {arg} of shape {:?}, {:?}: the error must name {arg}, got {e}",
                    b.dims(),
                    b.dtype()
                ),
            }
            checked += 1;
        }
    }
    assert!(checked > 0);
}

#[test]
fn analytic_shapes_reject_bad_points_naming_them() {
    let (d, f) = (Device::Cpu, DType::F64);
    let mut cases = shape_cases("Sphere", Sphere::new([0.0; 3], 0.5, &d, f).unwrap());
    cases.extend(shape_cases(
        "Cuboid",
        Cuboid::new([0.0; 3], [0.5, 0.4, 0.3], &d, f).unwrap(),
    ));
    cases.extend(shape_cases(
        "Torus",
        Torus::new([0.0; 3], 0.5, 0.1, &d, f).unwrap(),
    ));
    cases.extend(shape_cases(
        "Plane",
        Plane::new([0.0, 0.0, 1.0], 0.1, &d, f).unwrap(),
    ));
    assert_eq!(cases.len(), 28);
    run(cases);
}

#[test]
fn encodings_reject_bad_inputs_naming_them() {
    let pe = FrequencyEncoding::new(3, 4).unwrap();
    let ff = FourierFeatures::new(3, 8, 1.0, 7, &Device::Cpu, DType::F64).unwrap();
    let x = good_points();
    let dx = Tensor::ones((N, 2, 3), DType::F64, &Device::Cpu).unwrap();
    let bad_dx = || {
        vec![
            t(&[N, 1, 2], DType::F64),
            t(&[3], DType::F64),
            t(&[N, 1, 3], DType::U32),
        ]
    };
    let points_case = |what: &str, call: Call<'static>| Case {
        what: what.to_string(),
        arg: "x",
        good: good_points(),
        bad: bad_points(),
        call,
    };
    let dx_case = |what: &str, call: Call<'static>| Case {
        what: what.to_string(),
        arg: "dx",
        good: dx.clone(),
        bad: bad_dx(),
        call,
    };
    let identity = PointEncoding::Identity;
    let point_fourier = PointEncoding::Fourier(ff.clone());
    let cases = vec![
        points_case("FrequencyEncoding::forward", {
            let pe = pe.clone();
            Box::new(move |x| ok(pe.forward(x)))
        }),
        points_case("FrequencyEncoding::forward_jvp (x)", {
            let (pe, dx) = (pe.clone(), dx.clone());
            Box::new(move |x| ok(pe.forward_jvp(x, &dx)))
        }),
        dx_case("FrequencyEncoding::forward_jvp (dx)", {
            let (pe, x) = (pe.clone(), x.clone());
            Box::new(move |dx| ok(pe.forward_jvp(&x, dx)))
        }),
        points_case("FourierFeatures::forward", {
            let ff = ff.clone();
            Box::new(move |x| ok(ff.forward(x)))
        }),
        points_case("FourierFeatures::forward_jvp (x)", {
            let (ff, dx) = (ff.clone(), dx.clone());
            Box::new(move |x| ok(ff.forward_jvp(x, &dx)))
        }),
        dx_case("FourierFeatures::forward_jvp (dx)", {
            let (ff, x) = (ff.clone(), x.clone());
            Box::new(move |dx| ok(ff.forward_jvp(&x, dx)))
        }),
        // The identity accepts any D; wrong ranks and dtypes still fail.
        Case {
            what: "PointEncoding::Identity::forward".into(),
            arg: "x",
            good: good_points(),
            bad: vec![
                t(&[3], DType::F64),
                t(&[N, 3, 1], DType::F64),
                t(&[N, 3], DType::U32),
            ],
            call: {
                let e = identity.clone();
                Box::new(move |x| ok(e.forward(x)))
            },
        },
        Case {
            what: "PointEncoding::Identity::forward_jvp (x)".into(),
            arg: "x",
            good: good_points(),
            bad: vec![t(&[3], DType::F64), t(&[N, 3], DType::U32)],
            call: {
                let (e, dx) = (identity.clone(), dx.clone());
                Box::new(move |x| ok(e.forward_jvp(x, &dx)))
            },
        },
        dx_case("PointEncoding::Identity::forward_jvp (dx)", {
            let (e, x) = (identity.clone(), x.clone());
            Box::new(move |dx| ok(e.forward_jvp(&x, dx)))
        }),
        points_case("PointEncoding::Fourier::forward", {
            let e = point_fourier.clone();
            Box::new(move |x| ok(e.forward(x)))
        }),
        Case {
            what: "FourierFeatures::from_matrix".into(),
            arg: "b",
            good: t(&[8, 3], DType::F64),
            bad: vec![
                t(&[3], DType::F64),
                t(&[8, 3, 1], DType::F64),
                t(&[8, 3], DType::U32),
            ],
            call: Box::new(|b| ok(FourierFeatures::from_matrix(b.clone()))),
        },
        Case {
            what: "integrated_pe (means)".into(),
            arg: "means",
            good: good_points(),
            bad: vec![
                t(&[3], DType::F64),
                t(&[N, 3, 1], DType::F64),
                t(&[N, 3], DType::U32),
            ],
            call: Box::new(|m| {
                let var = Tensor::ones((N, 3), DType::F64, &Device::Cpu).unwrap();
                ok(integrated_pe(m, &var, 0, 4))
            }),
        },
        Case {
            what: "integrated_pe (variances)".into(),
            arg: "variances",
            good: Tensor::ones((N, 3), DType::F64, &Device::Cpu).unwrap(),
            bad: bad_points(),
            call: {
                let x = x.clone();
                Box::new(move |v| ok(integrated_pe(&x, v, 0, 4)))
            },
        },
    ];
    run(cases);
}

#[test]
fn mlp_and_conditioned_reject_bad_points_codes_and_rays_naming_them() {
    let (_vm, plain) = net(0);
    let (_vm2, cond) = net(CODE);
    let p = good_points();
    let codes = Tensor::ones((N, CODE), DType::F64, &Device::Cpu).unwrap();
    let (plain, cond) = (&plain, &cond);
    // One code per ray: point i takes row rays[i] of the [R, D] code.
    let per_ray = Conditioned::new(cond, codes.clone()).unwrap();
    let per_ray = &per_ray;
    let rays = Tensor::new(&[0u32, 1, 1, 3], &Device::Cpu).unwrap();
    let bad_rays = || {
        vec![
            t(&[N, 3], DType::U32),
            t(&[N - 1], DType::U32),
            t(&[N], DType::F32),
        ]
    };
    let (p_, c_, r_) = (&p, &codes, &rays);
    let cases = vec![
        points_case(
            "Mlp::forward_with_jacobian",
            Box::new(move |x| ok(plain.forward_with_jacobian(x, None))),
        ),
        points_case(
            "Mlp as Field::forward",
            Box::new(move |x| ok(Field::forward(plain, x))),
        ),
        points_case(
            "Mlp::value",
            Box::new(move |x| ok(ImplicitSurface::value(plain, x))),
        ),
        points_case(
            "Mlp::value_and_grad",
            Box::new(move |x| ok(ImplicitSurface::value_and_grad(plain, x))),
        ),
        points_case(
            "Mlp::value_and_grad_with_code (points)",
            Box::new(move |x| ok(cond.value_and_grad_with_code(x, c_))),
        ),
        codes_case(
            "Mlp::forward_with_jacobian (codes)",
            Box::new(move |c| ok(cond.forward_with_jacobian(p_, Some(c)))),
        ),
        codes_case(
            "Mlp::forward_with_code (codes)",
            Box::new(move |c| ok(cond.forward_with_code(p_, c))),
        ),
        codes_case(
            "Mlp::value_and_grad_with_code (codes)",
            Box::new(move |c| ok(cond.value_and_grad_with_code(p_, c))),
        ),
        Case {
            what: "Conditioned::value_on_rays (rays)".into(),
            arg: "rays",
            good: rays.clone(),
            bad: bad_rays(),
            call: Box::new(move |r| ok(per_ray.value_on_rays(p_, r))),
        },
        Case {
            what: "Conditioned::value_and_grad_on_rays (rays)".into(),
            arg: "rays",
            good: rays.clone(),
            bad: bad_rays(),
            call: Box::new(move |r| ok(per_ray.value_and_grad_on_rays(p_, r))),
        },
        points_case(
            "Conditioned::value_on_rays (points)",
            Box::new(move |x| ok(per_ray.value_on_rays(x, r_))),
        ),
    ];
    run(cases);
}

#[test]
fn rays_new_rejects_bad_origins_and_directions_naming_them() {
    use neural_fields::camera::Rays;
    let dirs = || Tensor::new(&[[0.0f64, 0.0, 1.0]; N], &Device::Cpu).unwrap();
    let with = |row: [f64; 3]| {
        let mut v = [[0.3f64, 0.1, 1.0]; N];
        v[N - 1] = row;
        Tensor::from_vec(v.concat(), (N, 3), &Device::Cpu).unwrap()
    };
    let cases = vec![
        Case {
            what: "Rays::new (origins)".into(),
            arg: "origins",
            good: good_points(),
            bad: [
                bad_points(),
                vec![with([f64::NAN, 0.0, 0.0]), with([0.0, f64::INFINITY, 0.0])],
            ]
            .concat(),
            call: Box::new(move |o| ok(Rays::new(o.clone(), dirs()))),
        },
        Case {
            what: "Rays::new (directions)".into(),
            arg: "directions",
            good: with([0.0, 0.0, -1.0]),
            bad: [
                bad_points(),
                vec![
                    with([f64::NAN, 0.0, 1.0]),
                    with([0.0, 0.0, f64::NEG_INFINITY]),
                    with([0.0, 0.0, 0.0]),
                    t(&[N - 1, 3], DType::F64),
                    t(&[N, 3], DType::F32),
                ],
            ]
            .concat(),
            call: Box::new(move |d| ok(Rays::new(good_points(), d.clone()))),
        },
    ];
    run(cases);
}
