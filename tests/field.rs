//! Analytic fields: exact distances and gradients (against finite differences), trainable
//! shape parameters, occupancy conventions and input validation.

mod common;

use candle_core::{DType, Device, Tensor, Var};
use common::{central_diff, uniform, v64};
use neural_fields::field::{
    Cuboid, Field, ImplicitSurface, Inside, Plane, SignedDistance, Sphere, Torus,
};
use neural_fields::rng::SplitMix64;
use proptest::prelude::*;

type DistanceFn = Box<dyn Fn(&Tensor) -> (Tensor, Tensor)>;

/// Every analytic shape with random parameters, as an SDF (`distance_and_grad`, whose
/// gradient has norm 1) and as occupancy logits `.occupancy(k)` (`value_and_grad`,
/// gradient norm `k`), with the norm `‖∇f‖` expected where the field is smooth.
fn shapes(seed: u64) -> Vec<(String, DistanceFn, f64)> {
    let mut rng = SplitMix64::new(seed);
    let mut u = |lo: f64, hi: f64| lo + (hi - lo) * rng.uniform();
    let d = Device::Cpu;
    let f = DType::F64;
    let c = [u(-0.2, 0.2), u(-0.2, 0.2), u(-0.2, 0.2)];
    let sphere = Sphere::new(c, u(0.1, 0.8), &d, f).unwrap();
    let cuboid = Cuboid::new(c, [u(0.1, 0.5), u(0.1, 0.5), u(0.1, 0.5)], &d, f).unwrap();
    let torus = Torus::new(c, u(0.3, 0.6), u(0.05, 0.25), &d, f).unwrap();
    let plane = Plane::new(
        [u(-1.0, 1.0), u(-1.0, 1.0), u(0.1, 1.0)],
        u(-0.5, 0.5),
        &d,
        f,
    )
    .unwrap();
    let k = u(0.5, 50.0);
    let mut out: Vec<(String, DistanceFn, f64)> = Vec::new();
    fn push<S: SignedDistance + Clone + 'static>(
        out: &mut Vec<(String, DistanceFn, f64)>,
        name: &str,
        shape: S,
        k: f64,
    ) {
        let occ = shape.clone().occupancy(k);
        out.push((
            format!("{name} sdf"),
            Box::new(move |p: &Tensor| shape.distance_and_grad(p).unwrap()),
            1.0,
        ));
        out.push((
            format!("{name} occupancy({k})"),
            Box::new(move |p: &Tensor| occ.value_and_grad(p).unwrap()),
            k,
        ));
    }
    push(&mut out, "sphere", sphere, k);
    push(&mut out, "cuboid", cuboid, k);
    push(&mut out, "torus", torus, k);
    push(&mut out, "plane", plane, k);
    out
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    /// ∇f equals central finite differences of f (away from the measure-zero creases,
    /// which the kink check skips), and ‖∇f‖ is 1 for the SDFs and k for the occupancy
    /// logits `−k·d` wherever f is smooth; for every analytic shape in both forms.
    #[test]
    fn analytic_gradients_match_finite_differences(seed in any::<u64>(), scale in prop_oneof![Just(1.0), Just(1e-3), Just(1e3)]) {
        let mut rng = SplitMix64::new(seed ^ 77);
        let points = uniform(&mut rng, 8, 3, -scale, scale, DType::F64);
        let p = v64(&points);
        let all = shapes(seed);
        prop_assert_eq!(all.len(), 8);
        for (name, shape, grad_norm) in all {
            let (dist, grad) = shape(&points);
            let (dist, grad) = (v64(&dist), v64(&grad));
            prop_assert!(dist.iter().chain(&grad).all(|v| v.is_finite()));
            for n in 0..8 {
                let mut smooth = true;
                for j in 0..3 {
                    let mut f = |x: f64| {
                        let mut q = p[3 * n..3 * n + 3].to_vec();
                        q[j] = x;
                        v64(&shape(&Tensor::from_vec(q, (1, 3), &Device::Cpu).unwrap()).0)[0]
                    };
                    let h = 1e-6 * scale.max(1.0);
                    match central_diff(&mut f, p[3 * n + j], h, grad_norm) {
                        Some(fd) => prop_assert!(
                            (grad[3 * n + j] - fd).abs() < 1e-6 * grad_norm,
                            "{} point {} axis {}: {} vs {} (f = {})", name, n, j, grad[3 * n + j], fd, dist[n]
                        ),
                        None => smooth = false,
                    }
                }
                let norm = (0..3).map(|j| grad[3 * n + j].powi(2)).sum::<f64>().sqrt();
                if smooth {
                    prop_assert!((norm - grad_norm).abs() < 1e-9 * grad_norm, "{}: ‖∇f‖ = {}", name, norm);
                }
            }
        }
    }
}

#[test]
fn sphere_and_torus_distances_are_exact() {
    let d = Device::Cpu;
    let sphere = Sphere::new([0.1, 0.0, 0.0], 0.5, &d, DType::F64).unwrap();
    let p = Tensor::new(&[[0.1f64, 0.0, 2.0], [0.1, 0.0, 0.0]], &d).unwrap();
    let (dist, grad) = sphere.distance_and_grad(&p).unwrap();
    assert_eq!(v64(&dist), vec![1.5, -0.5]);
    // The centre has no direction: the gradient there is 0, not NaN.
    assert_eq!(v64(&grad), vec![0.0, 0.0, 1.0, 0.0, 0.0, 0.0]);
    let torus = Torus::new([0.0; 3], 0.5, 0.1, &d, DType::F64).unwrap();
    let p = Tensor::new(
        &[
            [0.5f64, 0.0, 0.0],
            [0.0, 0.0, 0.0],
            [0.0, 0.8, 0.0],
            [0.5, 0.0, 0.3],
        ],
        &d,
    )
    .unwrap();
    let (dist, grad) = torus.distance_and_grad(&p).unwrap();
    let dist = v64(&dist);
    let expected = [-0.1, 0.4, 0.2, 0.2];
    for (a, b) in dist.iter().zip(expected) {
        assert!((a - b).abs() < 1e-12, "{dist:?}");
    }
    assert!(
        v64(&grad).iter().all(|v| v.is_finite()),
        "axis and core circle stay finite"
    );
}

#[test]
fn cuboid_is_exact_inside_outside_and_at_corners() {
    let d = Device::Cpu;
    let b = Cuboid::new([0.0; 3], [0.5, 0.25, 0.125], &d, DType::F64).unwrap();
    let p = Tensor::new(
        &[
            [0.0f64, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [0.8, 0.65, 0.125],
            [0.0, -0.2, 0.0],
        ],
        &d,
    )
    .unwrap();
    let (dist, grad) = b.distance_and_grad(&p).unwrap();
    let dist = v64(&dist);
    let expected = [-0.125, 0.5, 0.5, -0.05];
    for (a, e) in dist.iter().zip(expected) {
        assert!((a - e).abs() < 1e-12, "{dist:?}");
    }
    let g = v64(&grad);
    assert_eq!(&g[3..6], &[1.0, 0.0, 0.0]);
    assert!(
        (g[6] - 0.6).abs() < 1e-12 && (g[7] - 0.8).abs() < 1e-12,
        "{g:?}"
    );
    assert_eq!(&g[9..12], &[0.0, -1.0, 0.0]);
}

#[test]
fn shape_parameters_are_trainable() {
    let d = Device::Cpu;
    let center = Var::new(&[0.1f64, 0.2, 0.3], &d).unwrap();
    let radius = Var::new(0.5f64, &d).unwrap();
    let sphere = Sphere {
        center: center.as_tensor().clone(),
        radius: radius.as_tensor().clone(),
    };
    let p = Tensor::new(&[[1.0f64, -0.5, 0.25]], &d).unwrap();
    let (dist, grad) = sphere.distance_and_grad(&p).unwrap();
    let grads = dist.sum_all().unwrap().backward().unwrap();
    assert_eq!(v64(grads.get(&radius).unwrap()), vec![-1.0]);
    // ∂d/∂c = −∇ₚd.
    let gc = v64(grads.get(&center).unwrap());
    for (a, b) in gc.iter().zip(v64(&grad)) {
        assert!((a + b).abs() < 1e-12);
    }
}

#[test]
fn occupancy_is_negated_scaled_distance_with_positive_inside() {
    let d = Device::Cpu;
    let occ = Sphere::new([0.0; 3], 0.5, &d, DType::F32)
        .unwrap()
        .occupancy(20.0);
    let sdf = Sphere::new([0.0; 3], 0.5, &d, DType::F32).unwrap().sdf();
    assert_eq!(
        (occ.inside(), sdf.inside()),
        (Inside::Positive, Inside::Negative)
    );
    assert_eq!((occ.level(), Field::out_dim(&occ)), (0.0, 1));
    let p = Tensor::new(&[[0.0f32, 0.0, 0.25], [0.0, 0.75, 0.0]], &d).unwrap();
    let (v, g) = occ.value_and_grad(&p).unwrap();
    assert_eq!(v.dtype(), DType::F32);
    let v = v64(&v);
    assert!(
        (v[0] - 5.0).abs() < 1e-6 && (v[1] + 5.0).abs() < 1e-6,
        "{v:?}"
    );
    assert_eq!(v64(&g)[2], -20.0);
    assert_eq!(Field::forward(&sdf, &p).unwrap().dims(), &[2, 1]);
}

#[test]
fn bad_inputs_name_the_argument() {
    let d = Device::Cpu;
    let s = Sphere::new([0.0; 3], 0.5, &d, DType::F64).unwrap();
    let e = s
        .distance_and_grad(&Tensor::zeros((2, 4), DType::F64, &d).unwrap())
        .unwrap_err();
    assert!(
        e.to_string().starts_with("points: expected shape [N, 3]"),
        "{e}"
    );
    let e = s
        .distance_and_grad(&Tensor::zeros((2, 3), DType::F32, &d).unwrap())
        .unwrap_err();
    assert!(
        e.to_string().starts_with("points: expected dtype F64"),
        "{e}"
    );
    assert!(Sphere::new([0.0; 3], -1.0, &d, DType::F64)
        .unwrap_err()
        .to_string()
        .starts_with("radius"));
    // Non-finite parameters: the error names the constructor argument.
    let param_errors = [
        (
            Sphere::new([f64::NAN, 0.0, 0.0], 1.0, &d, DType::F64).map(|_| ()),
            "center: ",
        ),
        (
            Sphere::new([0.0; 3], f64::INFINITY, &d, DType::F64).map(|_| ()),
            "radius: ",
        ),
        (
            Cuboid::new([0.0, f64::INFINITY, 0.0], [1.0; 3], &d, DType::F64).map(|_| ()),
            "center: ",
        ),
        (
            Cuboid::new([0.0; 3], [1.0, f64::NAN, 1.0], &d, DType::F64).map(|_| ()),
            "half_extents: ",
        ),
        (
            Torus::new([0.0, 0.0, f64::NAN], 0.5, 0.1, &d, DType::F64).map(|_| ()),
            "center: ",
        ),
        (
            Torus::new([0.0; 3], f64::NAN, 0.1, &d, DType::F64).map(|_| ()),
            "major: ",
        ),
        (
            Plane::new([0.0, 0.0, 1.0], f64::NAN, &d, DType::F64).map(|_| ()),
            "offset: ",
        ),
        (
            Plane::new([f64::NAN, 0.0, 1.0], 0.0, &d, DType::F64).map(|_| ()),
            "normal: ",
        ),
    ];
    for (result, arg) in param_errors {
        let e = result.unwrap_err().to_string();
        assert!(e.starts_with(arg), "{e}");
    }
    assert!(Cuboid::new([0.0; 3], [1.0, 0.0, 1.0], &d, DType::F64)
        .unwrap_err()
        .to_string()
        .starts_with("half_extents"));
    assert!(Torus::new([0.0; 3], 0.5, 0.0, &d, DType::F64)
        .unwrap_err()
        .to_string()
        .starts_with("minor"));
    assert!(Plane::new([0.0; 3], 0.0, &d, DType::F64)
        .unwrap_err()
        .to_string()
        .starts_with("normal"));
    let occ = Sphere::new([0.0; 3], 0.5, &d, DType::F64)
        .unwrap()
        .occupancy(0.0);
    let p = Tensor::zeros((1, 3), DType::F64, &d).unwrap();
    assert!(occ
        .value(&p)
        .unwrap_err()
        .to_string()
        .starts_with("sharpness"));
}
