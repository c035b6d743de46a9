//! Constructive solid geometry of analytic shapes (`field::Csg`): values of union,
//! intersection, difference and smooth union, their gradients against finite differences,
//! parameter gradients through the combination, and the checks of the blend width `k`.

mod common;

use candle_core::{DType, Device, Tensor, Var};
use common::{central_diff, v64};
use neural_fields::field::{
    Capsule, Csg, CsgOp, Cuboid, Cylinder, ImplicitSurface, Inside, RoundedBox, SignedDistance,
    Sphere, Torus,
};
use neural_fields::rng::SplitMix64;
use proptest::prelude::*;
use std::sync::Arc;

type Operand = Arc<dyn SignedDistance + Send + Sync>;

/// A random analytic shape (one of six kinds) near the origin, in f64.
fn random_shape(rng: &mut SplitMix64) -> Operand {
    let mut u = |lo: f64, hi: f64| lo + (hi - lo) * rng.uniform();
    let (dev, f) = (Device::Cpu, DType::F64);
    let c = [u(-0.4, 0.4), u(-0.4, 0.4), u(-0.4, 0.4)];
    let e = [u(-0.4, 0.4), u(-0.4, 0.4), u(-0.4, 0.4)];
    let h = [u(0.1, 0.6), u(0.1, 0.6), u(0.1, 0.6)];
    let r = u(0.1, 0.5);
    match (u(0.0, 6.0)) as usize {
        0 => Arc::new(Sphere::new(c, r, &dev, f).unwrap()),
        1 => Arc::new(Cuboid::new(c, h, &dev, f).unwrap()),
        2 => Arc::new(RoundedBox::new(c, h, 0.09, &dev, f).unwrap()),
        3 => Arc::new(Torus::new(c, r + 0.1, r / 2.0, &dev, f).unwrap()),
        4 => Arc::new(Capsule::new(c, e, r / 2.0, &dev, f).unwrap()),
        _ => Arc::new(Cylinder::new(c, e, r, &dev, f).unwrap()),
    }
}

fn eval(shape: &dyn SignedDistance, points: &[[f64; 3]]) -> (Vec<f64>, Vec<f64>) {
    let p = Tensor::from_vec(points.concat(), (points.len(), 3), &Device::Cpu).unwrap();
    let (d, g) = shape.distance_and_grad(&p).unwrap();
    (v64(&d), v64(&g))
}

fn ops(k: f64) -> [CsgOp; 4] {
    [
        CsgOp::Union,
        CsgOp::Intersection,
        CsgOp::Difference,
        CsgOp::SmoothUnion { k },
    ]
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(48))]

    /// Every operation's gradient equals central finite differences of its distance
    /// wherever the distance is smooth (the creases `a = b` of min and max, and the
    /// operands' own, are skipped by the kink check); `‖∇d‖ ≤ 1` everywhere, `= 1` where
    /// min and max are smooth. The values are min / max / max(a, −b) / the polynomial
    /// smooth minimum of the operands' distances.
    #[test]
    fn csg_gradients_match_finite_differences(seed in any::<u64>(), k in 0.01f64..0.5, far in any::<bool>()) {
        let mut rng = SplitMix64::new(seed);
        let a = random_shape(&mut rng);
        let b = random_shape(&mut rng);
        let scale = if far { 1e6 } else { 1.0 };
        let points: Vec<[f64; 3]> = (0..16)
            .map(|_| [0; 3].map(|_| scale * (2.0 * rng.uniform() - 1.0)))
            .collect();
        let (da, _) = eval(&*a, &points);
        let (db, _) = eval(&*b, &points);
        let mut checked = 0;
        for op in ops(k) {
            let csg = Csg { op, a: a.clone(), b: b.clone() };
            let (d, g) = eval(&csg, &points);
            for (n, p) in points.iter().enumerate() {
                let expected = match op {
                    CsgOp::Union => da[n].min(db[n]),
                    CsgOp::Intersection => da[n].max(db[n]),
                    CsgOp::Difference => da[n].max(-db[n]),
                    CsgOp::SmoothUnion { k } => {
                        let h = (0.5 + 0.5 * (db[n] - da[n]) / k).clamp(0.0, 1.0);
                        db[n] + h * (da[n] - db[n]) - k * h * (1.0 - h)
                    }
                };
                prop_assert!((d[n] - expected).abs() <= 1e-12 * scale, "{:?}: {} vs {}", op, d[n], expected);
                let norm = g[3 * n..3 * n + 3].iter().map(|x| x * x).sum::<f64>().sqrt();
                prop_assert!(norm <= 1.0 + 1e-12, "{:?}: ‖∇d‖ = {}", op, norm);
                let h = 1e-7 * scale;
                let mut smooth = true;
                for j in 0..3 {
                    let mut f = |x: f64| {
                        let mut q = *p;
                        q[j] = x;
                        eval(&csg, &[q]).0[0]
                    };
                    match central_diff(&mut f, p[j], h, 1.0) {
                        Some(fd) => {
                            prop_assert!((g[3 * n + j] - fd).abs() < 1e-6, "{:?} at {:?} axis {}: {} vs FD {}", op, p, j, g[3 * n + j], fd);
                            checked += 1;
                        }
                        None => smooth = false,
                    }
                }
                if smooth && !matches!(op, CsgOp::SmoothUnion { .. }) {
                    prop_assert!((norm - 1.0).abs() < 1e-9, "{:?}: ‖∇d‖ = {}", op, norm);
                }
            }
        }
        // Creases are rare among random points: most derivatives were compared.
        prop_assert!(checked >= 4 * 16 * 3 * 3 / 4, "only {} of 192 derivatives checked", checked);
    }

    /// Where the plain union has its crease (`a = b`, points equidistant from two
    /// spheres), the smooth union is differentiable: finite differences exist there and
    /// equal `h∇a + (1 − h)∇b` with `h = ½`, and the value is `a − k/4`.
    #[test]
    fn smooth_union_is_differentiable_on_the_union_crease(seed in any::<u64>(), k in 0.01f64..1.0) {
        let mut rng = SplitMix64::new(seed);
        let mut u = |lo: f64, hi: f64| lo + (hi - lo) * rng.uniform();
        let (dev, f) = (Device::Cpu, DType::F64);
        let r = u(0.2, 0.6);
        let s1 = Sphere::new([-0.5, 0.0, 0.0], r, &dev, f).unwrap();
        let s2 = Sphere::new([0.5, 0.0, 0.0], r, &dev, f).unwrap();
        let csg = Csg { op: CsgOp::SmoothUnion { k }, a: Arc::new(s1), b: Arc::new(s2) };
        let p = [0.0, u(-1.0, 1.0), u(-1.0, 1.0)];
        let (d, g) = eval(&csg, &[p]);
        let dist_a = (0.25 + p[1] * p[1] + p[2] * p[2]).sqrt() - r;
        prop_assert!((d[0] - (dist_a - k / 4.0)).abs() < 1e-12);
        let m = dist_a + r;
        let expected = [0.0, p[1] / m, p[2] / m];
        for j in 0..3 {
            let mut fx = |x: f64| {
                let mut q = p;
                q[j] = x;
                eval(&csg, &[q]).0[0]
            };
            let fd = central_diff(&mut fx, p[j], 1e-6, 1.0);
            prop_assert!(fd.is_some(), "axis {}: a kink on the union's crease", j);
            prop_assert!((g[j] - fd.unwrap_or(f64::NAN)).abs() < 1e-7, "axis {}: {} vs {:?}", j, g[j], fd);
            prop_assert!((g[j] - expected[j]).abs() < 1e-12);
        }
    }
}

#[test]
fn csg_values_ties_and_nesting() {
    let (dev, f) = (Device::Cpu, DType::F64);
    let left: Operand = Arc::new(Sphere::new([-0.5, 0.0, 0.0], 0.75, &dev, f).unwrap());
    let right: Operand = Arc::new(Sphere::new([0.5, 0.0, 0.0], 0.75, &dev, f).unwrap());
    let csg = |op| Csg {
        op,
        a: left.clone(),
        b: right.clone(),
    };
    // On the mid-plane x = 0 both distances tie: min and max average the normals.
    let p = [
        [0.0, 0.0, 0.0],
        [0.0, 1.0, 0.0],
        [-2.0, 0.0, 0.0],
        [0.3, 0.0, 0.0],
    ];
    let m = 1.25f64.sqrt();
    let check = |op, d_expected: [f64; 4], g_expected: [f64; 12]| {
        let (d, g) = eval(&csg(op), &p);
        for (got, want) in d.iter().zip(d_expected).chain(g.iter().zip(g_expected)) {
            assert!((got - want).abs() < 1e-15, "{op:?}: {d:?} {g:?}");
        }
    };
    #[rustfmt::skip]
    check(
        CsgOp::Union,
        [-0.25, m - 0.75, 0.75, -0.55],
        [0.0, 0.0, 0.0, 0.0, 1.0 / m, 0.0, -1.0, 0.0, 0.0, -1.0, 0.0, 0.0],
    );
    #[rustfmt::skip]
    check(
        CsgOp::Intersection,
        [-0.25, m - 0.75, 1.75, 0.05],
        [0.0, 0.0, 0.0, 0.0, 1.0 / m, 0.0, -1.0, 0.0, 0.0, 1.0, 0.0, 0.0],
    );
    // Difference: the left sphere minus the right one; inside the right one, −∇b.
    #[rustfmt::skip]
    check(
        CsgOp::Difference,
        [0.25, m - 0.75, 0.75, 0.55],
        [1.0, 0.0, 0.0, 0.5 / m, 1.0 / m, 0.0, -1.0, 0.0, 0.0, 1.0, 0.0, 0.0],
    );
    // Smooth union: the union where |a − b| ≥ k, below it by k/4 where a = b.
    let (d, _) = eval(&csg(CsgOp::SmoothUnion { k: 0.1 }), &p);
    let (du, _) = eval(&csg(CsgOp::Union), &p);
    assert!((d[0] - (du[0] - 0.025)).abs() < 1e-15 && (d[1] - (du[1] - 0.025)).abs() < 1e-15);
    assert_eq!(&d[2..], &du[2..]);
    // Nesting, and a combination as SDF surface and occupancy.
    let nested = Csg {
        op: CsgOp::Difference,
        a: Arc::new(csg(CsgOp::Union)),
        b: Arc::new(Cuboid::new([0.0; 3], [2.0, 2.0, 0.1], &dev, f).unwrap()),
    };
    let (d, g) = eval(&nested, &[[-0.5, 0.0, 0.0], [-0.5, 0.0, 0.5]]);
    assert!((d[0] - 0.1).abs() < 1e-15 && (d[1] + 0.25).abs() < 1e-15);
    assert_eq!(&g[0..3], &[0.0, 0.0, -1.0]); // −∇ of the slab (+e_z on its mid-plane)
    assert_eq!(&g[3..6], &[0.0, 0.0, 1.0]);
    let sdf = nested.clone().sdf();
    assert_eq!(sdf.inside(), Inside::Negative);
    let occ = nested.occupancy(10.0);
    let p = Tensor::new(&[[-0.5f64, 0.0, 0.5]], &dev).unwrap();
    assert!((v64(&occ.value(&p).unwrap())[0] - 2.5).abs() < 1e-12);
    assert_eq!(format!("{:?}", csg(CsgOp::Union)), "Csg { op: Union, .. }");
}

/// Gradients reach both operands' parameters: the chosen operand's for min and max, the
/// blend's `h` and `1 − h` for the smooth union (as FD over the radius says).
#[test]
fn csg_parameters_are_trainable() {
    let dev = Device::Cpu;
    let ra = Var::new(0.4f64, &dev).unwrap();
    let rb = Var::new(0.3f64, &dev).unwrap();
    let sphere = |c: [f64; 3], r: &Tensor| Sphere {
        center: Tensor::new(&c, &dev).unwrap(),
        radius: r.clone(),
    };
    let build = |op, ra: &Tensor, rb: &Tensor| Csg {
        op,
        a: Arc::new(sphere([-0.3, 0.0, 0.0], ra)),
        b: Arc::new(sphere([0.3, 0.0, 0.0], rb)),
    };
    let p = Tensor::new(&[[0.013f64, 0.21, -0.05], [-0.9, 0.1, 0.2]], &dev).unwrap();
    for op in ops(0.3) {
        let csg = build(op, ra.as_tensor(), rb.as_tensor());
        let grads = csg
            .distance_and_grad(&p)
            .unwrap()
            .0
            .sum_all()
            .unwrap()
            .backward()
            .unwrap();
        for (which, var) in [(0, &ra), (1, &rb)] {
            let g = grads.get(var).map(|g| v64(g)[0]).unwrap_or(0.0);
            let mut fx = |x: f64| {
                let r = Tensor::new(x, &dev).unwrap();
                let c = if which == 0 {
                    build(op, &r, rb.as_tensor())
                } else {
                    build(op, ra.as_tensor(), &r)
                };
                v64(&c.distance_and_grad(&p).unwrap().0).iter().sum::<f64>()
            };
            let x0 = v64(var.as_tensor())[0];
            let fd = central_diff(&mut fx, x0, 1e-6, 1.0).expect("smooth in the radius");
            assert!(
                (g - fd).abs() < 1e-7,
                "{op:?}, radius {which}: {g} vs FD {fd}"
            );
        }
    }
}

#[test]
fn smooth_union_refuses_a_bad_blend_width_naming_k() {
    let dev = Device::Cpu;
    for dtype in [DType::F32, DType::F64] {
        let a: Operand = Arc::new(Sphere::new([0.0; 3], 0.5, &dev, dtype).unwrap());
        let b: Operand = Arc::new(Sphere::new([0.5, 0.0, 0.0], 0.5, &dev, dtype).unwrap());
        let p = Tensor::zeros((2, 3), dtype, &dev).unwrap();
        let mut bad = vec![0.0, -1.0, f64::NAN, f64::INFINITY, f64::NEG_INFINITY];
        if dtype == DType::F32 {
            bad.extend([1e-50, 1e39]); // zero and infinite in f32
        }
        for k in bad {
            let csg = Csg {
                op: CsgOp::SmoothUnion { k },
                a: a.clone(),
                b: b.clone(),
            };
            let e = csg.distance_and_grad(&p).unwrap_err().to_string();
            assert!(e.starts_with("k: "), "{dtype:?}, k = {k}: {e}");
        }
        let csg = Csg {
            op: CsgOp::SmoothUnion { k: 1e-30 },
            a: a.clone(),
            b: b.clone(),
        };
        let (d, g) = csg.distance_and_grad(&p).unwrap();
        assert!(v64(&d).iter().chain(&v64(&g)).all(|v| v.is_finite()));
        // Points are checked before the operands are evaluated.
        for op in ops(0.1) {
            let csg = Csg {
                op,
                a: a.clone(),
                b: b.clone(),
            };
            let e = csg
                .distance_and_grad(&Tensor::zeros((2, 4), dtype, &dev).unwrap())
                .unwrap_err()
                .to_string();
            assert!(e.starts_with("points: "), "{e}");
        }
    }
    // Operands of another dtype than the points: the operand's check names the points.
    let a: Operand = Arc::new(Sphere::new([0.0; 3], 0.5, &dev, DType::F32).unwrap());
    let b: Operand = Arc::new(Sphere::new([0.0; 3], 0.5, &dev, DType::F64).unwrap());
    let csg = Csg {
        op: CsgOp::Union,
        a,
        b,
    };
    let e = csg
        .distance_and_grad(&Tensor::zeros((1, 3), DType::F64, &dev).unwrap())
        .unwrap_err()
        .to_string();
    assert!(e.starts_with("points: expected dtype F32"), "{e}");
}
