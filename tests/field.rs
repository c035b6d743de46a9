//! Analytic fields: exact distances and gradients (against finite differences), trainable
//! shape parameters, occupancy conventions and input validation.

mod common;

use candle_core::{DType, Device, Tensor, Var};
use common::{central_diff, uniform, v64};
use neural_fields::field::{
    Capsule, Csg, CsgOp, Cuboid, Cylinder, Field, ImplicitSurface, Inside, Plane, RoundedBox,
    SignedDistance, Sphere, Torus,
};
use neural_fields::rng::SplitMix64;
use proptest::prelude::*;
use std::sync::Arc;

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
    let h = [u(0.1, 0.5), u(0.1, 0.5), u(0.1, 0.5)];
    let r = u(0.05, 1.0) * h.iter().copied().fold(f64::INFINITY, f64::min);
    let rounded = RoundedBox::new(c, h, r, &d, f).unwrap();
    let end = [u(-0.5, 0.5), u(-0.5, 0.5), u(-0.5, 0.5)];
    let capsule = Capsule::new(c, end, u(0.05, 0.4), &d, f).unwrap();
    let cylinder = Cylinder::new(c, end, u(0.05, 0.4), &d, f).unwrap();
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
    push(&mut out, "rounded box", rounded, k);
    push(&mut out, "capsule", capsule, k);
    push(&mut out, "cylinder", cylinder, k);
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
        prop_assert_eq!(all.len(), 14);
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

/// Checks `∇d` of `shape` against central finite differences (step `1e-7·max(1, |p|∞)`)
/// at every point where `d` is smooth, and `‖∇d‖ = 1` there (the shapes are exact SDFs);
/// returns how many points were smooth along all three axes.
fn fd_check(name: &str, shape: &dyn SignedDistance, points: &[[f64; 3]]) -> usize {
    let dev = Device::Cpu;
    let flat: Vec<f64> = points.concat();
    let p = Tensor::from_vec(flat, (points.len(), 3), &dev).unwrap();
    let (dist, grad) = shape.distance_and_grad(&p).unwrap();
    let (dist, grad) = (v64(&dist), v64(&grad));
    assert!(
        dist.iter().chain(&grad).all(|v| v.is_finite()),
        "{name}: not finite"
    );
    let mut smooth_points = 0;
    for (n, point) in points.iter().enumerate() {
        let h = 1e-7 * point.iter().fold(1.0f64, |m, v| m.max(v.abs()));
        let mut smooth = true;
        for j in 0..3 {
            let mut f = |x: f64| {
                let mut q = point.to_vec();
                q[j] = x;
                let q = Tensor::from_vec(q, (1, 3), &dev).unwrap();
                v64(&shape.distance_and_grad(&q).unwrap().0)[0]
            };
            match central_diff(&mut f, point[j], h, 1.0) {
                Some(fd) => assert!(
                    (grad[3 * n + j] - fd).abs() < 1e-6,
                    "{name} at {point:?}, axis {j}: ∇d = {} but FD {fd} (d = {})",
                    grad[3 * n + j],
                    dist[n]
                ),
                None => smooth = false,
            }
        }
        if smooth {
            smooth_points += 1;
            let norm = grad[3 * n..3 * n + 3]
                .iter()
                .map(|g| g * g)
                .sum::<f64>()
                .sqrt();
            assert!(
                (norm - 1.0).abs() < 1e-9,
                "{name} at {point:?}: ‖∇d‖ = {norm}"
            );
        }
    }
    smooth_points
}

fn unit_vector(rng: &mut SplitMix64) -> [f64; 3] {
    loop {
        let v = [
            2.0 * rng.uniform() - 1.0,
            2.0 * rng.uniform() - 1.0,
            2.0 * rng.uniform() - 1.0,
        ];
        let n = v.iter().map(|x| x * x).sum::<f64>().sqrt();
        if n > 0.1 && n <= 1.0 {
            return v.map(|x| x / n);
        }
    }
}

fn add(a: [f64; 3], b: [f64; 3], s: f64) -> [f64; 3] {
    [a[0] + s * b[0], a[1] + s * b[1], a[2] + s * b[2]]
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// A unit vector orthogonal to the unit vector `u`.
fn orthogonal(rng: &mut SplitMix64, u: [f64; 3]) -> [f64; 3] {
    loop {
        let v = unit_vector(rng);
        let w = add(v, u, -dot(v, u));
        let n = dot(w, w).sqrt();
        if n > 0.1 {
            return w.map(|x| x / n);
        }
    }
}

/// Random points around the shapes' centres and far away (~1e6).
fn spread_points(rng: &mut SplitMix64, around: [f64; 3]) -> Vec<[f64; 3]> {
    let mut pts = Vec::new();
    for scale in [0.3, 1.0, 3.0, 1e6] {
        for _ in 0..4 {
            let dir = unit_vector(rng);
            pts.push(add(around, dir, scale * (0.2 + rng.uniform())));
        }
    }
    pts
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(48))]

    /// The rounded box's gradient equals finite differences of its distance just inside
    /// and outside its faces, around its rounded edges and corners, and at random and far
    /// points; `‖∇d‖ = 1` wherever d is smooth.
    #[test]
    fn rounded_box_gradient_matches_fd_near_faces_and_edges(seed in any::<u64>()) {
        let mut rng = SplitMix64::new(seed);
        let mut u = |lo: f64, hi: f64| lo + (hi - lo) * rng.uniform();
        let c = [u(-0.3, 0.3), u(-0.3, 0.3), u(-0.3, 0.3)];
        let h = [u(0.1, 1.0), u(0.1, 1.0), u(0.1, 1.0)];
        let hmin = h.iter().copied().fold(f64::INFINITY, f64::min);
        let r = if u(0.0, 1.0) < 0.2 { hmin } else { u(0.05, 1.0) * hmin };
        let shape = RoundedBox::new(c, h, r, &Device::Cpu, DType::F64).unwrap();
        let mut rng = SplitMix64::new(seed ^ 3);
        let mut pts = spread_points(&mut rng, c);
        let mut near = 0;
        for _ in 0..24 {
            let eps = [1e-3, 1e-2, 0.1][rng.below(3) as usize] * if rng.uniform() < 0.5 { -1.0 } else { 1.0 };
            let j = rng.below(3) as usize;
            let sj = if rng.uniform() < 0.5 { -1.0 } else { 1.0 };
            // On the flat part of face j (or of its edges with a rounded neighbour).
            let mut p = [0.0; 3];
            for (k, pk) in p.iter_mut().enumerate() {
                *pk = c[k] + (h[k] - r) * (2.0 * rng.uniform() - 1.0);
            }
            p[j] = c[j] + sj * (h[j] + eps);
            pts.push(p);
            // Around a rounded edge along axis k: the inner box's edge plus (r + ε) in
            // the plane of the two other axes.
            let k = (j + 1) % 3;
            let theta = u_angle(&mut rng);
            let mut q = [0.0; 3];
            q[k] = c[k] + (h[k] - r) * (2.0 * rng.uniform() - 1.0);
            let (a1, a2) = ((k + 1) % 3, (k + 2) % 3);
            let (s1, s2) = (sj, if rng.uniform() < 0.5 { -1.0 } else { 1.0 });
            q[a1] = c[a1] + s1 * ((h[a1] - r) + (r + eps) * theta.cos());
            q[a2] = c[a2] + s2 * ((h[a2] - r) + (r + eps) * theta.sin());
            pts.push(q);
            near += 2;
        }
        let smooth = fd_check("rounded box", &shape, &pts);
        // Only points within an FD step of a crease (the inner medial planes) may be skipped.
        prop_assert!(smooth >= (pts.len() * 3) / 4, "{} of {} points smooth ({} near the surface)", smooth, pts.len(), near);
    }

    /// The capsule's gradient equals finite differences near its segment (1e-3 to 0.1
    /// away, beside it and beyond both ends), around its surface, at random and far
    /// points, also for a capsule whose ends coincide (a sphere).
    #[test]
    fn capsule_gradient_matches_fd_near_the_segment(seed in any::<u64>(), degenerate in any::<bool>()) {
        let mut rng = SplitMix64::new(seed);
        let mut u = |lo: f64, hi: f64| lo + (hi - lo) * rng.uniform();
        let a = [u(-0.5, 0.5), u(-0.5, 0.5), u(-0.5, 0.5)];
        let b = if degenerate { a } else { [u(-0.5, 0.5), u(-0.5, 0.5), u(-0.5, 0.5)] };
        let r = u(0.05, 0.5);
        let shape = Capsule::new(a, b, r, &Device::Cpu, DType::F64).unwrap();
        let mut rng = SplitMix64::new(seed ^ 5);
        let mut pts = spread_points(&mut rng, a);
        let ba = add(b, a, -1.0);
        for _ in 0..24 {
            // `off` away from the segment's point at t: orthogonal to it inside, on the
            // outer half-sphere at an end.
            let t = [0.0, 1.0, rng.uniform()][rng.below(3) as usize];
            let off = [1e-3, 1e-2, 0.1, r - 1e-3, r + 1e-3, 2.0 * r][rng.below(6) as usize];
            let dir = match t {
                0.0 | 1.0 => {
                    let v = unit_vector(&mut rng);
                    let outward = if t == 0.0 { -dot(v, ba) } else { dot(v, ba) };
                    if outward < 0.0 { v.map(|x| -x) } else { v }
                }
                _ => orthogonal(&mut rng, ba.map(|x| x / dot(ba, ba).sqrt().max(1e-300))),
            };
            pts.push(add(add(a, ba, t), dir, off));
        }
        let smooth = fd_check("capsule", &shape, &pts);
        // The capsule's only crease is its segment, at least 1e-3 from every point.
        prop_assert_eq!(smooth, pts.len());
    }

    /// The capped cylinder's gradient equals finite differences around its rim circle
    /// (outside, where the distance turns from the side to the cap, and inside), near
    /// its axis (1e-3 off it, and on it where a cap is nearest), near side and caps, and
    /// at random and far points.
    #[test]
    fn cylinder_gradient_matches_fd_near_rim_and_axis(seed in any::<u64>()) {
        let mut rng = SplitMix64::new(seed);
        let mut u = |lo: f64, hi: f64| lo + (hi - lo) * rng.uniform();
        let a = [u(-0.5, 0.5), u(-0.5, 0.5), u(-0.5, 0.5)];
        let dir = unit_vector(&mut SplitMix64::new(seed ^ 11));
        let len = u(0.1, 1.5);
        let b = add(a, dir, len);
        let r = u(0.05, 0.8);
        let shape = Cylinder::new(a, b, r, &Device::Cpu, DType::F64).unwrap();
        let mut rng = SplitMix64::new(seed ^ 7);
        let m = add(a, dir, len / 2.0);
        let mut pts = spread_points(&mut rng, m);
        for _ in 0..12 {
            let e = orthogonal(&mut rng, dir);
            let s = if rng.uniform() < 0.5 { -1.0 } else { 1.0 };
            // Around the rim: (ρ, y) = (r, L/2) + ε(cos θ, sin θ), θ all around.
            let eps = [1e-3, 1e-2, 0.05][rng.below(3) as usize];
            let theta = 2.0 * std::f64::consts::PI * rng.uniform();
            let rho = r + eps * theta.cos();
            let y = s * (len / 2.0 + eps * theta.sin());
            pts.push(add(add(m, dir, y), e, rho));
            // Near the axis: 1e-3 off it at any height, and on it where a cap is nearer.
            let y = s * len * (0.6 * rng.uniform());
            pts.push(add(add(m, dir, y), e, 1e-3));
            let y_cap = s * (len / 2.0 - 0.5 * r.min(len / 2.0) * rng.uniform() + 0.5 * rng.uniform());
            pts.push(add(m, dir, y_cap));
            // Just inside and outside the side and a cap.
            let off = [-1e-3, 1e-3][rng.below(2) as usize];
            pts.push(add(add(m, dir, s * len * 0.4 * rng.uniform()), e, (r + off).max(1e-3)));
            pts.push(add(add(m, dir, s * (len / 2.0 + off)), e, r * 0.9 * rng.uniform()));
        }
        let smooth = fd_check("cylinder", &shape, &pts);
        // Skipped: points within an FD step of the rim or of the inner creases (the
        // cone where side and cap are equally near, the axis where the side is nearest).
        prop_assert!(smooth >= (pts.len() * 3) / 4, "{} of {} points smooth", smooth, pts.len());
    }
}

fn u_angle(rng: &mut SplitMix64) -> f64 {
    0.5 * std::f64::consts::PI * rng.uniform()
}

fn assert_close(got: &[f64], expected: &[f64], tol: f64, what: &str) {
    assert_eq!(got.len(), expected.len(), "{what}");
    for (g, e) in got.iter().zip(expected) {
        assert!((g - e).abs() <= tol, "{what}: {got:?} vs {expected:?}");
    }
}

#[test]
fn new_shapes_have_the_closed_form_distances() {
    let d = Device::Cpu;
    let f = DType::F64;
    // Rounded box: faces, rounded edge and corner, inside; r = min h flattens the inner
    // box along that axis; r = h everywhere is the sphere.
    let b = RoundedBox::new([1.0, 0.0, 0.0], [1.0, 0.5, 0.25], 0.25, &d, f).unwrap();
    let s3 = 1.0 / 3f64.sqrt();
    let p = Tensor::new(
        &[
            [2.5f64, 0.0, 0.0],
            [1.0, -0.5, 0.0],
            [1.75 + 0.3, 0.25 + 0.4, 0.0],
            [1.75 + s3, -0.25 - s3, s3],
            [1.0, 0.0, 0.0],
            [1.1, 0.1, 0.1],
        ],
        &d,
    )
    .unwrap();
    let (dist, grad) = b.distance_and_grad(&p).unwrap();
    assert_close(
        &v64(&dist),
        &[0.5, 0.0, 0.25, 0.75, -0.25, -0.15],
        1e-12,
        "rounded box",
    );
    let g = v64(&grad);
    assert_close(&g[6..9], &[0.6, 0.8, 0.0], 1e-12, "edge normal");
    assert_close(&g[9..12], &[s3, -s3, s3], 1e-12, "corner normal");
    assert_close(&g[15..18], &[0.0, 0.0, 1.0], 1e-12, "inside");
    let ball = RoundedBox::new([0.0; 3], [0.5; 3], 0.5, &d, f).unwrap();
    let sphere = Sphere::new([0.0; 3], 0.5, &d, f).unwrap();
    let p = Tensor::new(
        &[[0.3f64, -0.2, 0.1], [2.0, 1.0, -3.0], [0.0, 0.0, 0.0]],
        &d,
    )
    .unwrap();
    let (db, gb) = ball.distance_and_grad(&p).unwrap();
    let (ds, gs) = sphere.distance_and_grad(&p).unwrap();
    assert_close(&v64(&db), &v64(&ds), 1e-12, "rounded box r = h is a sphere");
    assert_close(&v64(&gb)[..6], &v64(&gs)[..6], 1e-12, "its normals");
    assert_close(&v64(&gb)[6..], &[1.0 / 3.0; 3], 1e-12, "centre: averaged");

    // Capsule: beside, beyond either end, on the segment; a = b is a sphere.
    let c = Capsule::new([1.0, 1.0, 0.0], [1.0, 1.0, 2.0], 0.5, &d, f).unwrap();
    let p = Tensor::new(
        &[
            [1.0f64, 4.0, 1.5],
            [1.0, 1.0, -1.0],
            [1.9, 1.0, 3.2],
            [1.0, 1.0, 0.75],
            [1.2, 1.0, 1.0],
        ],
        &d,
    )
    .unwrap();
    let (dist, grad) = c.distance_and_grad(&p).unwrap();
    assert_close(&v64(&dist), &[2.5, 0.5, 1.0, -0.5, -0.3], 1e-12, "capsule");
    assert_close(
        &v64(&grad),
        &[
            0.0, 1.0, 0.0, 0.0, 0.0, -1.0, 0.6, 0.0, 0.8, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0,
        ],
        1e-12,
        "capsule normals",
    );
    let dot = Capsule::new([0.5, 0.0, 0.0], [0.5, 0.0, 0.0], 0.25, &d, f).unwrap();
    let ball = Sphere::new([0.5, 0.0, 0.0], 0.25, &d, f).unwrap();
    let p = Tensor::new(&[[0.5f64, 0.0, 0.0], [1.0, 2.0, -1.0], [0.4, 0.1, 0.0]], &d).unwrap();
    let (dc, gc) = dot.distance_and_grad(&p).unwrap();
    let (ds, gs) = ball.distance_and_grad(&p).unwrap();
    assert_close(&v64(&dc), &v64(&ds), 1e-12, "capsule a = b is a sphere");
    assert_close(&v64(&gc), &v64(&gs), 1e-12, "its normals (0 at the centre)");

    // Cylinder from (0, 0, 0) to (2, 0, 0), radius 1: side, caps, rim, inside, axis.
    let cyl = Cylinder::new([0.0; 3], [2.0, 0.0, 0.0], 1.0, &d, f).unwrap();
    let p = Tensor::new(
        &[
            [1.5f64, 0.0, 3.0],
            [-0.5, 0.2, 0.3],
            [2.3, 0.0, -1.4],
            [1.0, 0.5, 0.0],
            [1.9, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [2.0, 1.0, 0.0],
            [0.1, 0.0, 0.0],
        ],
        &d,
    )
    .unwrap();
    let (dist, grad) = cyl.distance_and_grad(&p).unwrap();
    assert_close(
        &v64(&dist),
        &[2.0, 0.5, 0.5, -0.5, -0.1, -1.0, 0.0, -0.1],
        1e-12,
        "cylinder",
    );
    assert_close(
        &v64(&grad),
        &[
            0.0, 0.0, 1.0, // side
            -1.0, 0.0, 0.0, // cap a
            0.6, 0.0, -0.8, // rim region
            0.0, 1.0, 0.0, // inside, side nearer
            1.0, 0.0, 0.0, // inside on the axis, cap nearer
            0.5, 0.0, 0.0, // the centre: side (ê = 0 on the axis) and cap tie
            0.5, 0.5, 0.0, // the rim: side and cap averaged
            -1.0, 0.0, 0.0, // on the axis near cap a
        ],
        1e-12,
        "cylinder normals",
    );
}

/// Each new shape's distance and spatial gradient are differentiable w.r.t. its parameter
/// tensors: the backward of `Σ d + Σ w ⊙ ∇d` (random w) equals finite differences of it
/// over each parameter, and `∂d/∂(translation) = −∇ₚd`.
#[test]
fn new_shape_parameters_are_trainable() {
    let dev = Device::Cpu;
    type Build = fn(&[Tensor]) -> Box<dyn SignedDistance>;
    let cases: [(&str, [Vec<f64>; 3], Build); 3] = [
        (
            "rounded box",
            [vec![0.1, -0.2, 0.05], vec![0.6, 0.4, 0.5], vec![0.15]],
            |t| {
                Box::new(RoundedBox {
                    center: t[0].clone(),
                    half_extents: t[1].clone(),
                    radius: t[2].clone(),
                })
            },
        ),
        (
            "capsule",
            [vec![0.1, -0.2, 0.05], vec![0.5, 0.3, -0.4], vec![0.2]],
            |t| {
                Box::new(Capsule {
                    a: t[0].clone(),
                    b: t[1].clone(),
                    radius: t[2].clone(),
                })
            },
        ),
        (
            "cylinder",
            [vec![0.1, -0.2, 0.05], vec![0.5, 0.3, -0.4], vec![0.3]],
            |t| {
                Box::new(Cylinder {
                    a: t[0].clone(),
                    b: t[1].clone(),
                    radius: t[2].clone(),
                })
            },
        ),
    ];
    // Off every crease of the distance and of its gradient (as round numbers would not be).
    let points = Tensor::new(
        &[
            [0.913, 0.107, 0.219],
            [-0.417, 0.523, -0.311],
            [0.2034, -0.1171, 0.0123],
            [0.3137, 0.0591, -0.2077],
            [1.5123, -1.2341, 0.7013],
        ],
        &dev,
    )
    .unwrap();
    let w = Tensor::new(
        &[
            [0.3f64, -0.7, 0.2],
            [1.1, 0.4, -0.5],
            [-0.2, 0.9, 0.6],
            [0.5, 0.5, -1.0],
            [0.8, -0.3, 0.1],
        ],
        &dev,
    )
    .unwrap();
    let loss = |shape: &dyn SignedDistance| {
        let (d, g) = shape.distance_and_grad(&points).unwrap();
        (d.sum_all().unwrap() + (g * &w).unwrap().sum_all().unwrap()).unwrap()
    };
    let tensor = |v: &[f64]| {
        let t = Tensor::new(v, &dev).unwrap();
        if v.len() == 1 {
            t.squeeze(0).unwrap()
        } else {
            t
        }
    };
    for (name, values, build) in cases {
        let vars: Vec<Var> = values
            .iter()
            .map(|v| Var::from_tensor(&tensor(v)).unwrap())
            .collect();
        let tensors: Vec<Tensor> = vars.iter().map(|v| v.as_tensor().clone()).collect();
        let grads = loss(&*build(&tensors)).backward().unwrap();
        for (i, var) in vars.iter().enumerate() {
            let g = v64(grads.get(var).unwrap());
            for (j, gj) in g.iter().enumerate() {
                let mut f = |x: f64| {
                    let mut moved = values.clone();
                    moved[i][j] = x;
                    let ts: Vec<Tensor> = moved.iter().map(|v| tensor(v)).collect();
                    v64(&loss(&*build(&ts)))[0]
                };
                let fd = central_diff(&mut f, values[i][j], 1e-6, 1.0)
                    .unwrap_or_else(|| panic!("{name}: parameter {i}.{j} at a kink"));
                assert!(
                    (gj - fd).abs() < 1e-6,
                    "{name}: ∂/∂param {i}.{j} = {gj}, FD {fd}"
                );
            }
        }
        // Translation: moving every point parameter by δ moves the shape by δ.
        let (_, gp) = build(&tensors).distance_and_grad(&points).unwrap();
        let moved: Vec<Var> = vars[..if name == "rounded box" { 1 } else { 2 }].to_vec();
        let (d, _) = build(&tensors).distance_and_grad(&points).unwrap();
        let grads = d.sum_all().unwrap().backward().unwrap();
        let mut total = vec![0.0; 3];
        for var in &moved {
            for (t, g) in total.iter_mut().zip(v64(grads.get(var).unwrap())) {
                *t += g;
            }
        }
        let gp = v64(&gp);
        let sum_gp: Vec<f64> = (0..3)
            .map(|j| -(0..5).map(|n| gp[3 * n + j]).sum::<f64>())
            .collect();
        assert_close(&total, &sum_gp, 1e-12, name);
    }
}

/// f32 evaluations agree with f64 ones, in the points' dtype.
#[test]
fn new_shapes_agree_in_f32_and_f64() {
    let dev = Device::Cpu;
    let mut rng = SplitMix64::new(5);
    let p64 = uniform(&mut rng, 64, 3, -1.5, 1.5, DType::F64);
    let p32 = p64.to_dtype(DType::F32).unwrap();
    for dtype_pair in [(DType::F64, &p64), (DType::F32, &p32)] {
        let (dtype, p) = dtype_pair;
        let shapes: Vec<Box<dyn SignedDistance>> = vec![
            Box::new(RoundedBox::new([0.1, 0.0, -0.1], [0.7, 0.5, 0.3], 0.2, &dev, dtype).unwrap()),
            Box::new(Capsule::new([0.1, 0.0, -0.1], [-0.4, 0.6, 0.3], 0.3, &dev, dtype).unwrap()),
            Box::new(Cylinder::new([0.1, 0.0, -0.1], [-0.4, 0.6, 0.3], 0.3, &dev, dtype).unwrap()),
        ];
        for shape in &shapes {
            let (d, g) = shape.distance_and_grad(p).unwrap();
            assert_eq!((d.dtype(), g.dtype()), (dtype, dtype));
            assert_eq!((d.dims(), g.dims()), (&[64][..], &[64, 3][..]));
        }
    }
    let build = |dtype| -> Vec<Box<dyn SignedDistance>> {
        vec![
            Box::new(RoundedBox::new([0.1, 0.0, -0.1], [0.7, 0.5, 0.3], 0.2, &dev, dtype).unwrap()),
            Box::new(Capsule::new([0.1, 0.0, -0.1], [-0.4, 0.6, 0.3], 0.3, &dev, dtype).unwrap()),
            Box::new(Cylinder::new([0.1, 0.0, -0.1], [-0.4, 0.6, 0.3], 0.3, &dev, dtype).unwrap()),
        ]
    };
    for (s64, s32) in build(DType::F64).iter().zip(build(DType::F32)) {
        let (d64, g64) = s64.distance_and_grad(&p64).unwrap();
        let (d32, g32) = s32.distance_and_grad(&p32).unwrap();
        assert_close(&v64(&d32), &v64(&d64), 1e-6, "f32 distance");
        // Gradients agree except within f32 round-off of a crease, where they may jump.
        let (g32, g64) = (v64(&g32), v64(&g64));
        let agree = (0..64)
            .filter(|&n| (0..3).all(|j| (g32[3 * n + j] - g64[3 * n + j]).abs() < 1e-5))
            .count();
        assert!(agree >= 62, "{agree} of 64 gradients agree");
    }
}

#[test]
fn new_shapes_refuse_bad_parameters_naming_them() {
    let d = Device::Cpu;
    let f = DType::F64;
    let errors = [
        (
            RoundedBox::new([f64::NAN, 0.0, 0.0], [1.0; 3], 0.1, &d, f).map(|_| ()),
            "center: ",
        ),
        (
            RoundedBox::new([0.0; 3], [1.0, -1.0, 1.0], 0.1, &d, f).map(|_| ()),
            "half_extents: ",
        ),
        (
            RoundedBox::new([0.0; 3], [1.0, f64::INFINITY, 1.0], 0.1, &d, f).map(|_| ()),
            "half_extents: ",
        ),
        (
            RoundedBox::new([0.0; 3], [1.0, 0.5, 1.0], 0.0, &d, f).map(|_| ()),
            "radius: ",
        ),
        (
            RoundedBox::new([0.0; 3], [1.0, 0.5, 1.0], 0.6, &d, f).map(|_| ()),
            "radius: ",
        ),
        (
            RoundedBox::new([0.0; 3], [1.0, 0.5, 1.0], f64::NAN, &d, f).map(|_| ()),
            "radius: ",
        ),
        (
            Capsule::new([0.0, f64::NAN, 0.0], [1.0; 3], 0.1, &d, f).map(|_| ()),
            "a: ",
        ),
        (
            Capsule::new([0.0; 3], [1.0, 1.0, f64::INFINITY], 0.1, &d, f).map(|_| ()),
            "b: ",
        ),
        (
            Capsule::new([-1e308, 0.0, 0.0], [1e308, 0.0, 0.0], 0.1, &d, f).map(|_| ()),
            "b: ",
        ),
        (
            Capsule::new([0.0; 3], [1.0; 3], -0.1, &d, f).map(|_| ()),
            "radius: ",
        ),
        (
            Capsule::new([0.0; 3], [1.0; 3], f64::NAN, &d, f).map(|_| ()),
            "radius: ",
        ),
        (
            Cylinder::new([f64::INFINITY, 0.0, 0.0], [1.0; 3], 0.1, &d, f).map(|_| ()),
            "a: ",
        ),
        (
            Cylinder::new([0.0; 3], [f64::NAN, 0.0, 0.0], 0.1, &d, f).map(|_| ()),
            "b: ",
        ),
        (
            Cylinder::new([0.5; 3], [0.5; 3], 0.1, &d, f).map(|_| ()),
            "b: ",
        ),
        (
            Cylinder::new([0.0; 3], [1.0; 3], 0.0, &d, f).map(|_| ()),
            "radius: ",
        ),
        (
            Cylinder::new([0.0; 3], [1.0; 3], f64::NAN, &d, f).map(|_| ()),
            "radius: ",
        ),
    ];
    for (result, arg) in errors {
        let e = result.unwrap_err().to_string();
        assert!(e.starts_with(arg), "{arg}: {e}");
    }
    // Points: wrong shape, dtype; parameters checked against the points.
    let shapes: Vec<Box<dyn SignedDistance>> = vec![
        Box::new(RoundedBox::new([0.0; 3], [1.0; 3], 0.5, &d, f).unwrap()),
        Box::new(Capsule::new([0.0; 3], [1.0; 3], 0.5, &d, f).unwrap()),
        Box::new(Cylinder::new([0.0; 3], [1.0; 3], 0.5, &d, f).unwrap()),
    ];
    for s in &shapes {
        let e = s
            .distance_and_grad(&Tensor::zeros((2, 2), f, &d).unwrap())
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
        let e = s
            .distance_and_grad(&Tensor::zeros(3, f, &d).unwrap())
            .unwrap_err();
        assert!(e.to_string().starts_with("points: "), "{e}");
    }
}

/// An empty batch (which `check_points` accepts, and the marchers pass when no ray hits)
/// gives empty results: candle refuses the maximum of nothing, which every shape's norm
/// took.
#[test]
fn every_shape_accepts_an_empty_batch() {
    let d = Device::Cpu;
    let f = DType::F64;
    let shapes: Vec<Box<dyn SignedDistance>> = vec![
        Box::new(Sphere::new([0.0; 3], 0.5, &d, f).unwrap()),
        Box::new(Cuboid::new([0.0; 3], [1.0; 3], &d, f).unwrap()),
        Box::new(Torus::new([0.0; 3], 0.5, 0.1, &d, f).unwrap()),
        Box::new(Plane::new([0.0, 0.0, 1.0], 0.0, &d, f).unwrap()),
        Box::new(RoundedBox::new([0.0; 3], [1.0; 3], 0.5, &d, f).unwrap()),
        Box::new(Capsule::new([0.0; 3], [1.0; 3], 0.5, &d, f).unwrap()),
        Box::new(Cylinder::new([0.0; 3], [1.0; 3], 0.5, &d, f).unwrap()),
        Box::new(Csg {
            op: CsgOp::SmoothUnion { k: 0.1 },
            a: Arc::new(Sphere::new([0.0; 3], 0.5, &d, f).unwrap()),
            b: Arc::new(Cuboid::new([0.0; 3], [1.0; 3], &d, f).unwrap()),
        }),
    ];
    for s in &shapes {
        let (dist, grad) = s
            .distance_and_grad(&Tensor::zeros((0, 3), f, &d).unwrap())
            .unwrap();
        assert_eq!((dist.dims(), grad.dims()), (&[0][..], &[0, 3][..]));
    }
}

/// The boxes' parameter gradients agree with their spatial gradients where the distance
/// takes the inside branch with a tie: exactly on a face (`max q = 0`, where `min(·, 0)`
/// used to pass half the gradient) and at a cube's centre (three axes tie; candle's `max`
/// used to give each the full gradient, three times the spatial subgradient's share).
#[test]
fn box_parameter_gradients_match_the_spatial_gradient_on_faces_and_ties() {
    let d = Device::Cpu;
    let center = Var::new(&[0.0f64, 0.0, 0.0], &d).unwrap();
    let half = Var::new(&[0.5f64, 0.25, 0.125], &d).unwrap();
    let b = Cuboid {
        center: center.as_tensor().clone(),
        half_extents: half.as_tensor().clone(),
    };
    // On the face x = 0.5, inside the face.
    let p = Tensor::new(&[[0.5f64, 0.1, -0.05]], &d).unwrap();
    let (dist, grad) = b.distance_and_grad(&p).unwrap();
    assert_eq!((v64(&dist), v64(&grad)), (vec![0.0], vec![1.0, 0.0, 0.0]));
    let grads = dist.sum_all().unwrap().backward().unwrap();
    assert_eq!(v64(grads.get(&center).unwrap()), vec![-1.0, 0.0, 0.0]);
    assert_eq!(v64(grads.get(&half).unwrap()), vec![-1.0, 0.0, 0.0]);
    // The centre of a cube: the gradients share the tie equally.
    let half = Var::new(&[0.5f64, 0.5, 0.5], &d).unwrap();
    let cube = Cuboid {
        center: center.as_tensor().clone(),
        half_extents: half.as_tensor().clone(),
    };
    let p = Tensor::new(&[[0.0f64, 0.0, 0.0]], &d).unwrap();
    let (dist, grad) = cube.distance_and_grad(&p).unwrap();
    assert_eq!(v64(&dist), vec![-0.5]);
    assert_close(&v64(&grad), &[1.0 / 3.0; 3], 1e-15, "spatial");
    let grads = dist.sum_all().unwrap().backward().unwrap();
    assert_close(
        &v64(grads.get(&half).unwrap()),
        &[-1.0 / 3.0; 3],
        1e-15,
        "half-extents",
    );
}
