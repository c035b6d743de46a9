//! Stiff cases of `field`: the analytic shapes at their singular points and far away.

mod common;

use std::sync::Arc;

use candle_core::{DType, Device, Tensor, Var};

use common::stiff::{extreme_points, var, Expect, Suite, DTYPES};

use neural_fields::field::{
    Capsule, Csg, CsgOp, Cuboid, Cylinder, ImplicitSurface, Plane, RoundedBox, SignedDistance,
    Sphere, Torus,
};

#[test]
fn analytic_fields_stay_finite() {
    let mut s = Suite::default();
    sweep_fields(&mut s);
    s.finish("field", FIELDS);
}

#[test]
fn every_public_field_function_is_swept_or_exempt() {
    common::stiff::check_coverage("stiff_cases_field", &[FIELDS], EXEMPT, &[], &[]);
}

/// Items swept by `sweep_fields`.
const FIELDS: &[&str] = &[
    "field::Capsule::new",
    "field::Csg::distance_and_grad",
    "field::Cuboid::new",
    "field::Cylinder::new",
    "field::Plane::new",
    "field::RoundedBox::new",
    "field::Sphere::new",
    "field::Torus::new",
];

/// Public items without floating-point input (or only reached through a swept item),
/// with the reason. Matching is by prefix.
const EXEMPT: &[(&str, &str)] = &[
    (
        "field::Conditioned::",
        "forwards to the wrapped field (swept via the Mlp)",
    ),
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
    (
        "field::RoundedBox::distance_and_grad",
        "swept via the RoundedBox cases",
    ),
    (
        "field::Capsule::distance_and_grad",
        "swept via the Capsule cases",
    ),
    (
        "field::Cylinder::distance_and_grad",
        "swept via the Cylinder cases",
    ),
    ("field::Csg::fmt", "Debug: prints the operation, no numbers"),
];

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
        // The new shapes on the extreme points plus the far end of the dtype's range, in
        // the unit, tiny and huge sizes; their axes run along z through the origin, so
        // the points on the z axis lie on a capsule's segment and a cylinder's axis, and
        // the origin is every shape's centre.
        let top = if dtype == DType::F32 { 1e38 } else { 1e300 };
        let extra = Tensor::new(
            &[
                [top, 0.0, 0.0],
                [0.0, 0.0, -top],
                [top, -top, top],
                [1e-300, 1e-300, 0.0],
                [0.0, 0.0, 1e-300],
            ],
            &d,
        )
        .unwrap()
        .to_dtype(dtype)
        .unwrap();
        let q = Var::from_tensor(&Tensor::cat(&[pt, &extra], 0).unwrap()).unwrap();
        let qt = q.as_tensor();
        for (scale, tag) in [(1.0, "unit"), (1e-20, "tiny shape"), (1e20, "huge shape")] {
            let label = format!("{dtype:?}, {tag}");
            s.case(
                "field::RoundedBox::new",
                &label,
                Expect::Finite,
                &[&q],
                || {
                    let h = [0.3 * scale, 0.2 * scale, 0.1 * scale];
                    let mut out = Vec::new();
                    // Rounded a little, and fully along z (a flat inner box).
                    for r in [0.02 * scale, 0.1 * scale] {
                        let (v, g) = RoundedBox::new([0.0; 3], h, r, &d, dtype)?
                            .sdf()
                            .value_and_grad(qt)?;
                        out.extend([v, g]);
                    }
                    Ok(out)
                },
            );
            s.case("field::Capsule::new", &label, Expect::Finite, &[&q], || {
                let mut out = Vec::new();
                // A segment along z, and coinciding ends (a sphere).
                for b in [[0.0, 0.0, 0.3 * scale], [0.0, 0.0, -0.3 * scale]] {
                    let (v, g) = Capsule::new([0.0, 0.0, -0.3 * scale], b, 0.1 * scale, &d, dtype)?
                        .sdf()
                        .value_and_grad(qt)?;
                    out.extend([v, g]);
                }
                Ok(out)
            });
            s.case(
                "field::Cylinder::new",
                &label,
                Expect::Finite,
                &[&q],
                || {
                    let mut out = Vec::new();
                    // Long and thin (the side nearest on the axis), and flat (a cap nearest).
                    for (half, r) in [(0.3, 0.1), (0.1, 0.3)] {
                        let (v, g) = Cylinder::new(
                            [0.0, 0.0, -half * scale],
                            [0.0, 0.0, half * scale],
                            r * scale,
                            &d,
                            dtype,
                        )?
                        .sdf()
                        .value_and_grad(qt)?;
                        out.extend([v, g]);
                    }
                    Ok(out)
                },
            );
            s.case(
                "field::Csg::distance_and_grad",
                &label,
                Expect::Finite,
                &[&q],
                || {
                    let ball = Arc::new(Sphere::new([0.0; 3], 0.3 * scale, &d, dtype)?);
                    let rod = Arc::new(Cylinder::new(
                        [0.0, 0.0, -0.5 * scale],
                        [0.0, 0.0, 0.5 * scale],
                        0.1 * scale,
                        &d,
                        dtype,
                    )?);
                    let mut out = Vec::new();
                    let smooth = [1e-30, 0.05 * scale, 1e30];
                    let ops = [CsgOp::Union, CsgOp::Intersection, CsgOp::Difference]
                        .into_iter()
                        .chain(smooth.map(|k| CsgOp::SmoothUnion { k }));
                    for op in ops {
                        let csg = Csg {
                            op,
                            a: ball.clone(),
                            b: rod.clone(),
                        };
                        let (v, g) = csg.sdf().value_and_grad(qt)?;
                        out.extend([v, g]);
                    }
                    Ok(out)
                },
            );
        }
        // Parameters as variables at their degenerate values: a capsule whose ends
        // coincide, a cylinder whose ends coincide (refused by `new`, reachable through
        // the fields), a rounded box with r = h (a sphere); gradients w.r.t. the points
        // and the parameters stay finite.
        let a = var(&[0.0, 0.0, 0.0], &[3], dtype);
        let b = var(&[0.0, 0.0, 0.0], &[3], dtype);
        let r = var(&[0.3], &[], dtype);
        let h = var(&[0.3, 0.3, 0.3], &[3], dtype);
        let label = format!("{dtype:?}, parameters as Vars, degenerate");
        s.case(
            "field::Capsule::new",
            &label,
            Expect::Finite,
            &[&q, &a, &b, &r],
            || {
                let c = Capsule {
                    a: a.as_tensor().clone(),
                    b: b.as_tensor().clone(),
                    radius: r.as_tensor().clone(),
                };
                let (v, g) = c.distance_and_grad(qt)?;
                Ok(vec![v, g])
            },
        );
        s.case(
            "field::Cylinder::new",
            &label,
            Expect::Finite,
            &[&q, &a, &b, &r],
            || {
                let c = Cylinder {
                    a: a.as_tensor().clone(),
                    b: b.as_tensor().clone(),
                    radius: r.as_tensor().clone(),
                };
                let (v, g) = c.distance_and_grad(qt)?;
                Ok(vec![v, g])
            },
        );
        s.case(
            "field::RoundedBox::new",
            &label,
            Expect::Finite,
            &[&q, &a, &h, &r],
            || {
                let c = RoundedBox {
                    center: a.as_tensor().clone(),
                    half_extents: h.as_tensor().clone(),
                    radius: r.as_tensor().clone(),
                };
                let (v, g) = c.distance_and_grad(qt)?;
                Ok(vec![v, g])
            },
        );
        s.case(
            "field::Csg::distance_and_grad",
            &label,
            Expect::Finite,
            &[&q, &a, &b, &r],
            || {
                let c = Arc::new(Capsule {
                    a: a.as_tensor().clone(),
                    b: b.as_tensor().clone(),
                    radius: r.as_tensor().clone(),
                });
                let csg = Csg {
                    op: CsgOp::SmoothUnion { k: 0.1 },
                    a: c.clone(),
                    b: c,
                };
                let (v, g) = csg.distance_and_grad(qt)?;
                Ok(vec![v, g])
            },
        );
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
