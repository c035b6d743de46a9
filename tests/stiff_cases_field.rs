//! Stiff cases of `field`: the analytic shapes at their singular points and far away.

mod common;

use candle_core::{Device, Var};

use common::stiff::{extreme_points, Expect, Suite, DTYPES};

use neural_fields::field::{Cuboid, ImplicitSurface, Plane, SignedDistance, Sphere, Torus};

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
    "field::Cuboid::new",
    "field::Plane::new",
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
