//! `dvr::march` and `dvr::sphere_trace`: root accuracy on analytic shapes (SDF and
//! occupancy, f64 and f32), exact evaluation counts, degenerate rays (each named), bad
//! input, chunking invariance, bounded marching and the step schedule.

#![allow(clippy::needless_range_loop)]

mod common;

use candle_core::{DType, Device, Tensor, Var};
use common::counting::Counting;
use common::hits::count;
use common::v64;
use neural_fields::camera::{ray_aabb, Intersection, Rays};
use neural_fields::dvr::{
    implicit_surface, march, sphere_trace, Hits, ImplicitConfig, MarchConfig, RayStatus,
    SecantRule, SphereTraceConfig, StepSchedule,
};
use neural_fields::field::{Cuboid, ImplicitSurface, Inside, Plane, SignedDistance, Sphere, Torus};
use neural_fields::rng::SplitMix64;
use neural_fields::Result;

const DEV: Device = Device::Cpu;

/// A host-side signed distance (the reference) for each test shape.
#[derive(Clone, Copy, Debug)]
enum Shape {
    Sphere { c: [f64; 3], r: f64 },
    Box { c: [f64; 3], h: [f64; 3] },
    Torus { c: [f64; 3], big: f64, small: f64 },
    Plane { n: [f64; 3], o: f64 },
}

fn norm(v: [f64; 3]) -> f64 {
    (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt()
}
fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

impl Shape {
    fn dist(&self, p: [f64; 3]) -> f64 {
        match *self {
            Shape::Sphere { c, r } => norm(sub(p, c)) - r,
            Shape::Box { c, h } => {
                let d = sub(p, c);
                let q = [d[0].abs() - h[0], d[1].abs() - h[1], d[2].abs() - h[2]];
                norm([q[0].max(0.0), q[1].max(0.0), q[2].max(0.0)])
                    + q[0].max(q[1]).max(q[2]).min(0.0)
            }
            Shape::Torus { c, big, small } => {
                let d = sub(p, c);
                let rho = (d[0] * d[0] + d[1] * d[1]).sqrt();
                ((rho - big).powi(2) + d[2] * d[2]).sqrt() - small
            }
            Shape::Plane { n, o } => {
                let l = norm(n);
                (n[0] * p[0] + n[1] * p[1] + n[2] * p[2]) / l - o
            }
        }
    }

    /// A point well inside (rays are aimed at it).
    fn target(&self, rng: &mut SplitMix64) -> [f64; 3] {
        let mut u = |a: f64| a * (2.0 * rng.uniform() - 1.0);
        match *self {
            Shape::Sphere { c, r } => [c[0] + u(0.4 * r), c[1] + u(0.4 * r), c[2] + u(0.4 * r)],
            Shape::Box { c, h } => [
                c[0] + u(0.5 * h[0]),
                c[1] + u(0.5 * h[1]),
                c[2] + u(0.5 * h[2]),
            ],
            Shape::Torus { c, big, .. } => {
                let a = std::f64::consts::PI * u(1.0);
                [c[0] + big * a.cos(), c[1] + big * a.sin(), c[2]]
            }
            Shape::Plane { n, o } => {
                let l = norm(n);
                let base = [n[0] / l * o, n[1] / l * o, n[2] / l * o];
                [base[0] + u(0.5), base[1] + u(0.5), base[2] + u(0.5) * 0.0]
            }
        }
    }

    fn sdf_surface(&self, dtype: DType) -> Box<dyn ImplicitSurface> {
        match *self {
            Shape::Sphere { c, r } => Box::new(Sphere::new(c, r, &DEV, dtype).unwrap().sdf()),
            Shape::Box { c, h } => Box::new(Cuboid::new(c, h, &DEV, dtype).unwrap().sdf()),
            Shape::Torus { c, big, small } => {
                Box::new(Torus::new(c, big, small, &DEV, dtype).unwrap().sdf())
            }
            Shape::Plane { n, o } => Box::new(Plane::new(n, o, &DEV, dtype).unwrap().sdf()),
        }
    }

    fn occ_surface(&self, dtype: DType, k: f64) -> Box<dyn ImplicitSurface> {
        match *self {
            Shape::Sphere { c, r } => {
                Box::new(Sphere::new(c, r, &DEV, dtype).unwrap().occupancy(k))
            }
            Shape::Box { c, h } => Box::new(Cuboid::new(c, h, &DEV, dtype).unwrap().occupancy(k)),
            Shape::Torus { c, big, small } => {
                Box::new(Torus::new(c, big, small, &DEV, dtype).unwrap().occupancy(k))
            }
            Shape::Plane { n, o } => Box::new(Plane::new(n, o, &DEV, dtype).unwrap().occupancy(k)),
        }
    }
}

/// Reference first entry of the ray into the shape (dense samples + 200 bisections), the
/// length of the first inside segment, and |cos| between ray and normal there.
fn reference(
    shape: &Shape,
    o: [f64; 3],
    w: [f64; 3],
    near: f64,
    far: f64,
) -> Option<(f64, f64, f64)> {
    let at = |t: f64| shape.dist([o[0] + t * w[0], o[1] + t * w[1], o[2] + t * w[2]]);
    let n = 20_000;
    let ts: Vec<f64> = (0..=n)
        .map(|j| near + (far - near) * j as f64 / n as f64)
        .collect();
    let j = (1..=n).find(|&j| at(ts[j]) < 0.0)?;
    let (mut a, mut b) = (ts[j - 1], ts[j]);
    for _ in 0..200 {
        let m = 0.5 * (a + b);
        if at(m) < 0.0 {
            b = m
        } else {
            a = m
        }
    }
    let entry = 0.5 * (a + b);
    let exit = (j..=n).find(|&k| at(ts[k]) >= 0.0).map_or(far, |k| ts[k]);
    let p = [
        o[0] + entry * w[0],
        o[1] + entry * w[1],
        o[2] + entry * w[2],
    ];
    let e = 1e-6;
    let g = [
        shape.dist([p[0] + e, p[1], p[2]]) - shape.dist([p[0] - e, p[1], p[2]]),
        shape.dist([p[0], p[1] + e, p[2]]) - shape.dist([p[0], p[1] - e, p[2]]),
        shape.dist([p[0], p[1], p[2] + e]) - shape.dist([p[0], p[1], p[2] - e]),
    ];
    let cos = (g[0] * w[0] + g[1] * w[1] + g[2] * w[2]).abs() / (norm(g) * norm(w));
    Some((entry, exit - entry, cos))
}

struct Batch {
    o: Vec<[f64; 3]>,
    w: Vec<[f64; 3]>,
    far: Vec<f64>,
}

/// `r` rays from distance 2 aimed at points inside `shape`, directions of random length
/// in [0.5, 2], with `[0, far]` covering distance 4; values rounded to `dtype`.
fn rays_at(shape: &Shape, r: usize, seed: u64, dtype: DType) -> Batch {
    let mut rng = SplitMix64::new(seed);
    let round = |x: f64| {
        if dtype == DType::F32 {
            f64::from(x as f32)
        } else {
            x
        }
    };
    let (mut os, mut ws, mut fars) = (vec![], vec![], vec![]);
    while os.len() < r {
        let target = shape.target(&mut rng);
        let mut d = [rng.normal(), rng.normal(), rng.normal()];
        if let Shape::Plane { n, .. } = shape {
            // Come from the outside (normal) side.
            let s = d[0] * n[0] + d[1] * n[1] + d[2] * n[2];
            if s > -0.3 * norm(*n) * norm(d) {
                continue;
            }
        }
        let l = norm(d);
        d = [d[0] / l, d[1] / l, d[2] / l];
        let o = [
            target[0] - 2.0 * d[0],
            target[1] - 2.0 * d[1],
            target[2] - 2.0 * d[2],
        ];
        let scale = 0.5 + 1.5 * rng.uniform();
        let w = [d[0] * scale, d[1] * scale, d[2] * scale];
        os.push(o.map(round));
        ws.push(w.map(round));
        fars.push(round(4.0 / scale));
    }
    Batch {
        o: os,
        w: ws,
        far: fars,
    }
}

/// The rays of `b` and the search range `[0, far]` on each.
fn tensors(b: &Batch, dtype: DType) -> (Rays, Intersection) {
    let r = b.o.len();
    let flat = |v: &Vec<[f64; 3]>| {
        Tensor::from_vec(
            v.iter().flatten().copied().collect::<Vec<_>>(),
            (r, 3),
            &DEV,
        )
        .unwrap()
        .to_dtype(dtype)
        .unwrap()
    };
    let near = Tensor::zeros(r, dtype, &DEV).unwrap();
    let far = Tensor::from_vec(b.far.clone(), r, &DEV)
        .unwrap()
        .to_dtype(dtype)
        .unwrap();
    (
        Rays::new(flat(&b.o), flat(&b.w)).unwrap(),
        Intersection::new(near, far).unwrap(),
    )
}

fn shapes() -> Vec<(&'static str, Shape)> {
    vec![
        (
            "sphere",
            Shape::Sphere {
                c: [0.125, -0.0625, 0.25],
                r: 0.5,
            },
        ),
        (
            "box",
            Shape::Box {
                c: [0.0625, 0.125, -0.125],
                h: [0.5, 0.25, 0.375],
            },
        ),
        (
            "torus",
            Shape::Torus {
                c: [0.0, 0.125, 0.0],
                big: 0.5,
                small: 0.1875,
            },
        ),
        (
            "plane",
            Shape::Plane {
                n: [0.25, -0.5, 1.0],
                o: 0.125,
            },
        ),
    ]
}

fn accuracy(dtype: DType, bound: f64) {
    let scene = 2.0;
    let cfg = MarchConfig {
        steps: 64,
        secant_steps: 8,
        ..MarchConfig::default()
    };
    for (name, shape) in shapes() {
        for occupancy in [false, true] {
            let field = if occupancy {
                shape.occ_surface(dtype, 10.0)
            } else {
                shape.sdf_surface(dtype)
            };
            let b = rays_at(&shape, 64, 11, dtype);
            let (rays, range) = tensors(&b, dtype);
            let hits = march(field.as_ref(), &rays, &range, &cfg).unwrap();
            let depth = v64(&hits.depth);
            let mut checked = 0;
            let mut worst: f64 = 0.0;
            for i in 0..b.o.len() {
                let Some((t_ref, seg, cos)) = reference(&shape, b.o[i], b.w[i], 0.0, b.far[i])
                else {
                    continue;
                };
                let spacing = b.far[i] / 63.0;
                if seg < 2.0 * spacing || cos < 0.05 {
                    continue; // a thin clip or a near-tangent entry: not this test's subject
                }
                assert_eq!(
                    hits.status[i],
                    RayStatus::Hit,
                    "{name} occ={occupancy} ray {i}"
                );
                let err = (depth[i] - t_ref).abs() * norm(b.w[i]) / scene;
                worst = worst.max(err);
                checked += 1;
            }
            assert!(checked >= 32, "{name}: only {checked} rays checked");
            println!("{dtype:?} {name} occupancy={occupancy}: {checked} rays, worst relative depth error {worst:.2e}");
            assert!(
                worst <= bound,
                "{name} occupancy={occupancy} {dtype:?}: depth error {worst:e} > {bound:e}"
            );
        }
    }
}

#[test]
fn depth_error_f64_within_1e_10_of_scene_size_with_64_steps_and_8_secant() {
    accuracy(DType::F64, 1e-10);
}

#[test]
fn depth_error_f32_within_1e_5_of_scene_size_with_64_steps_and_8_secant() {
    accuracy(DType::F32, 1e-5);
}

#[test]
fn evaluations_per_ray_are_exactly_steps_plus_secant_steps() {
    let sphere = Shape::Sphere {
        c: [0.0; 3],
        r: 0.5,
    };
    for (steps, secant, chunk) in [(64, 8, 1000), (16, 0, 7), (33, 5, 1_000_000), (3, 1, 1)] {
        for occupancy in [false, true] {
            let inner = if occupancy {
                sphere.occ_surface(DType::F64, 5.0)
            } else {
                sphere.sdf_surface(DType::F64)
            };
            let field = Counting::new(inner.as_ref());
            let b = rays_at(&sphere, 20, 3, DType::F64);
            let (rays, range) = tensors(&b, DType::F64);
            let cfg = MarchConfig {
                steps,
                secant_steps: secant,
                chunk_points: chunk,
                ..MarchConfig::default()
            };
            let hits = march(&field, &rays, &range, &cfg).unwrap();
            assert_eq!(
                count(&hits, RayStatus::Hit) + count(&hits, RayStatus::NotConverged),
                20
            );
            assert_eq!(
                field.points.get(),
                20 * (steps + secant),
                "steps {steps} secant {secant}"
            );
            assert_eq!(hits.evaluations, 20 * (steps + secant));
        }
    }
    // Misses cost `steps` only.
    let inner = sphere.sdf_surface(DType::F64);
    let field = Counting::new(inner.as_ref());
    let (rays, range) = problem(
        Tensor::new(&[[0.0f64, 0.0, -2.0], [0.0, 2.0, -2.0]], &DEV).unwrap(),
        Tensor::new(&[[0.0f64, 0.0, 1.0], [0.0, 0.0, 1.0]], &DEV).unwrap(),
        Tensor::zeros(2, DType::F64, &DEV).unwrap(),
        Tensor::new(&[4.0f64, 4.0], &DEV).unwrap(),
    );
    let cfg = MarchConfig {
        steps: 50,
        secant_steps: 6,
        ..MarchConfig::default()
    };
    let hits = march(&field, &rays, &range, &cfg).unwrap();
    assert_eq!(hits.status, vec![RayStatus::Hit, RayStatus::Miss]);
    assert_eq!(field.points.get(), 56 + 50);
}

#[test]
fn chunk_size_bounds_every_call_and_does_not_change_results() {
    let torus = Shape::Torus {
        c: [0.0; 3],
        big: 0.5,
        small: 0.2,
    };
    let inner = torus.sdf_surface(DType::F64);
    let b = rays_at(&torus, 30, 5, DType::F64);
    let (rays, range) = tensors(&b, DType::F64);
    let mut reference: Option<Hits> = None;
    for chunk in [1usize, 7, 100, 1 << 20] {
        let field = Counting::new(inner.as_ref());
        let cfg = MarchConfig {
            steps: 40,
            secant_steps: 4,
            chunk_points: chunk,
            ..MarchConfig::default()
        };
        let hits = march(&field, &rays, &range, &cfg).unwrap();
        // No single call sees more than `chunk_points` points (the sampling gathers
        // whole rays, but the evaluator splits them into chunks).
        assert!(
            field.max_call.get() <= chunk,
            "chunk {chunk}: a call with {} points",
            field.max_call.get()
        );
        assert!(field.max_call.get() >= 1);
        if chunk < 40 {
            // Small chunks are filled: the bound is attained, not just respected.
            assert_eq!(field.max_call.get(), chunk);
        }
        if let Some(r) = &reference {
            assert_eq!(v64(&r.depth), v64(&hits.depth));
            assert_eq!(r.status, hits.status);
        } else {
            reference = Some(hits);
        }
    }
}

/// Rays `(o, w)` and the search range `[near, far]` on each (every ray marked hit).
fn problem(o: Tensor, w: Tensor, near: Tensor, far: Tensor) -> (Rays, Intersection) {
    (
        Rays::new(o, w).unwrap(),
        Intersection::new(near, far).unwrap(),
    )
}

/// One f64 ray and its search range `[near, far]`.
fn one_ray(o: [f64; 3], w: [f64; 3], near: f64, far: f64) -> (Rays, Intersection) {
    (
        Rays::new(
            Tensor::new(&[o], &DEV).unwrap(),
            Tensor::new(&[w], &DEV).unwrap(),
        )
        .unwrap(),
        Intersection::new(
            Tensor::new(&[near], &DEV).unwrap(),
            Tensor::new(&[far], &DEV).unwrap(),
        )
        .unwrap(),
    )
}

fn all_finite(h: &Hits) {
    assert!(v64(&h.depth).iter().all(|v| v.is_finite()));
    assert!(v64(&h.points).iter().all(|v| v.is_finite()));
}

/// `implicit_surface` on a march's result, then `backward()`: asserts that the depths are
/// the march's, that every output (depth, points, value, gradient) is finite, and that
/// the gradients of `Σ t̂ + Σ p̂ + Σ f + Σ ∇f` w.r.t. every variable in `vars` are finite.
/// Returns `∂(Σ t̂)/∂v` for each variable (zeros where the graph does not reach it),
/// also checked finite.
fn implicit_and_backward<F: ImplicitSurface + ?Sized>(
    field: &F,
    rays: &Rays,
    hits: &Hits,
    vars: &[&Var],
) -> Vec<Vec<f64>> {
    let s = implicit_surface(field, rays, hits, &ImplicitConfig::default()).unwrap();
    let on: Vec<usize> = (0..hits.status.len())
        .filter(|&i| hits.status[i].has_surface())
        .collect();
    assert_eq!(s.indices.dim(0).unwrap(), on.len());
    let march_depth = v64(&hits.depth);
    let want: Vec<f64> = on.iter().map(|&i| march_depth[i]).collect();
    assert_eq!(v64(&s.depth), want, "t̂ is the march's depth");
    for (name, t) in [
        ("depth", &s.depth),
        ("points", &s.points),
        ("value", &s.value),
        ("gradient", &s.gradient),
    ] {
        let v = v64(t);
        assert!(v.iter().all(|x| x.is_finite()), "{name}: {v:?}");
    }
    let grads_of = |loss: &Tensor| -> Vec<Vec<f64>> {
        let g = loss.backward().unwrap();
        let out: Vec<Vec<f64>> = vars
            .iter()
            .map(|v| g.get(v).map_or_else(|| vec![0.0; v.elem_count()], v64))
            .collect();
        for (k, g) in out.iter().enumerate() {
            assert!(g.iter().all(|x| x.is_finite()), "variable {k}: {g:?}");
        }
        out
    };
    let sum = |t: &Tensor| t.sum_all().unwrap();
    let all = (sum(&s.depth) + sum(&s.points) + sum(&s.value) + sum(&s.gradient)).unwrap();
    grads_of(&all);
    grads_of(&sum(&s.depth))
}

/// The origins and directions of `rays` as variables, and rays built from them, so that
/// the implicit step differentiates them.
fn ray_vars(rays: &Rays) -> (Var, Var, Rays) {
    let o = Var::from_tensor(rays.origins()).unwrap();
    let w = Var::from_tensor(rays.directions()).unwrap();
    let vrays = Rays::new(o.as_tensor().clone(), w.as_tensor().clone()).unwrap();
    (o, w, vrays)
}

/// `|a − b| ≤ 1e-9`, with a message.
fn near_eq(a: f64, b: f64, what: &str) {
    assert!((a - b).abs() <= 1e-9, "{what}: {a} vs {b}");
}

#[test]
fn ray_starting_inside_is_reported_with_depth_near() {
    let s = Sphere::new([0.0; 3], 0.5, &DEV, DType::F64).unwrap();
    for field in [
        Box::new(s.clone().sdf()) as Box<dyn ImplicitSurface>,
        Box::new(s.occupancy(4.0)),
    ] {
        let (rays, range) = one_ray([0.0, 0.0, 0.1], [0.0, 0.0, 1.0], 0.25, 3.0);
        let h = march(field.as_ref(), &rays, &range, &MarchConfig::default()).unwrap();
        assert_eq!(h.status, vec![RayStatus::StartsInside]);
        assert_eq!(v64(&h.depth), vec![0.25]);
        assert_eq!(v64(&h.mask.to_dtype(DType::F64).unwrap()), vec![0.0]);
        all_finite(&h);
    }
}

#[test]
fn missing_ray_is_reported_with_depth_far() {
    let field = Sphere::new([0.0; 3], 0.5, &DEV, DType::F64).unwrap().sdf();
    let (rays, range) = one_ray([0.0, 0.7, -2.0], [0.0, 0.0, 1.0], 0.0, 4.0);
    let h = march(&field, &rays, &range, &MarchConfig::default()).unwrap();
    assert_eq!(h.status, vec![RayStatus::Miss]);
    assert_eq!(v64(&h.depth), vec![4.0]);
    all_finite(&h);
}

#[test]
fn tangent_ray_misses_and_nearly_tangent_ray_is_grazing() {
    let field = Sphere::new([0.0; 3], 0.5, &DEV, DType::F64).unwrap().sdf();
    // Exactly tangent: touches without entering.
    let (rays, range) = one_ray([0.0, 0.5, -2.0], [0.0, 0.0, 1.0], 0.0, 4.0);
    let h = march(&field, &rays, &range, &MarchConfig::default()).unwrap();
    assert_eq!(h.status, vec![RayStatus::Miss]);
    // Enters by 1e-9: a crossing exists (the samples are placed to see it), at cos ≈ 6e-5.
    let y = 0.5 - 1e-9;
    let t_mid = 2.0;
    let (rays, range) = one_ray([0.0, y, -2.0], [0.0, 0.0, 1.0], t_mid - 1.0, t_mid + 1e-6);
    let cfg = MarchConfig {
        steps: 2,
        secant_steps: 30,
        ..MarchConfig::default()
    };
    let h = march(&field, &rays, &range, &cfg).unwrap();
    assert_eq!(h.status, vec![RayStatus::Grazing]);
    let expected = t_mid - (0.25 - y * y).sqrt();
    assert!(
        (v64(&h.depth)[0] - expected).abs() < 1e-9,
        "{:?} vs {expected}",
        v64(&h.depth)
    );
    all_finite(&h);
}

#[test]
fn two_crossings_the_first_is_found() {
    // Two spheres on the ray, with learnable centres and radii: the nearer one is found,
    // at both sampling densities, and the implicit step differentiates it alone:
    // t = 2 + c_z − r for the near sphere, so ∂t/∂c_z = 1, ∂t/∂r = −1, ∂t/∂o_z = −1,
    // ∂t/∂w_z = −t, and nothing reaches the far sphere.
    let near_c = Var::new(&[0.0f64, 0.0, -0.5], &DEV).unwrap();
    let near_r = Var::new(0.25f64, &DEV).unwrap();
    let far_c = Var::new(&[0.0f64, 0.0, 0.5], &DEV).unwrap();
    let far_r = Var::new(0.25f64, &DEV).unwrap();
    let sphere = |c: &Var, r: &Var| Sphere {
        center: c.as_tensor().clone(),
        radius: r.as_tensor().clone(),
    };
    let union = Union(sphere(&near_c, &near_r).sdf(), sphere(&far_c, &far_r).sdf());
    let (rays, range) = one_ray([0.0, 0.0, -2.0], [0.0, 0.0, 1.0], 0.0, 4.0);
    let (ov, wv, vrays) = ray_vars(&rays);
    for steps in [16, 256] {
        let cfg = MarchConfig {
            steps,
            ..MarchConfig::default()
        };
        let h = march(&union, &rays, &range, &cfg).unwrap();
        assert_eq!(h.status, vec![RayStatus::Hit]);
        assert!(
            (v64(&h.depth)[0] - 1.25).abs() < 1e-12,
            "{:?}",
            v64(&h.depth)
        );
        let g = implicit_and_backward(
            &union,
            &vrays,
            &h,
            &[&near_c, &near_r, &far_c, &far_r, &ov, &wv],
        );
        near_eq(g[0][2], 1.0, "∂t/∂c_z (near sphere)");
        near_eq(g[1][0], -1.0, "∂t/∂r (near sphere)");
        assert!(g[2].iter().chain(&g[3]).all(|&x| x == 0.0), "{g:?}");
        near_eq(g[4][2], -1.0, "∂t/∂o_z");
        near_eq(g[5][2], -1.25, "∂t/∂w_z");
    }
    // A torus seen edge-on: entry into the near side of the tube, t = 2 − R − r.
    let major = Var::new(0.5f64, &DEV).unwrap();
    let minor = Var::new(0.125f64, &DEV).unwrap();
    let torus = Torus {
        center: Tensor::zeros(3, DType::F64, &DEV).unwrap(),
        major: major.as_tensor().clone(),
        minor: minor.as_tensor().clone(),
    }
    .sdf();
    let (rays, range) = one_ray([-2.0, 0.0, 0.0], [1.0, 0.0, 0.0], 0.0, 4.0);
    let h = march(&torus, &rays, &range, &MarchConfig::default()).unwrap();
    assert_eq!(h.status, vec![RayStatus::Hit]);
    assert!(
        (v64(&h.depth)[0] - 1.375).abs() < 1e-12,
        "{:?}",
        v64(&h.depth)
    );
    let (ov, wv, vrays) = ray_vars(&rays);
    let g = implicit_and_backward(&torus, &vrays, &h, &[&major, &minor, &ov, &wv]);
    near_eq(g[0][0], -1.0, "∂t/∂R");
    near_eq(g[1][0], -1.0, "∂t/∂r");
}

/// min of two SDFs (a union), for the two-crossings test.
struct Union<A, B>(A, B);
impl<A: ImplicitSurface, B: ImplicitSurface> ImplicitSurface for Union<A, B> {
    fn value(&self, p: &Tensor) -> Result<Tensor> {
        Ok(self.0.value(p)?.minimum(&self.1.value(p)?)?)
    }
    fn value_and_grad(&self, p: &Tensor) -> Result<(Tensor, Tensor)> {
        let (a, ga) = self.0.value_and_grad(p)?;
        let (b, gb) = self.1.value_and_grad(p)?;
        let first = a.le(&b)?;
        let g = first
            .unsqueeze(1)?
            .broadcast_as(ga.shape())?
            .where_cond(&ga, &gb)?;
        Ok((a.minimum(&b)?, g))
    }
    fn inside(&self) -> Inside {
        Inside::Negative
    }
}

#[test]
fn field_exactly_at_level_at_a_sample_is_found_exactly() {
    // Plane z = 0.5 (normal (0, 0, −1), learnable offset o = −0.5, so the SDF along the
    // ray is −t − o); samples at t = 0, 0.25, …, 1 put one exactly on it. The implicit
    // step at that sample: ∂t/∂o = −1, for the SDF and the occupancy logits alike.
    let normal = Var::new(&[0.0f64, 0.0, -1.0], &DEV).unwrap();
    let offset = Var::new(-0.5f64, &DEV).unwrap();
    let plane = Plane {
        normal: normal.as_tensor().clone(),
        offset: offset.as_tensor().clone(),
    };
    for field in [
        Box::new(plane.clone().sdf()) as Box<dyn ImplicitSurface>,
        Box::new(plane.occupancy(3.0)),
    ] {
        let (rays, range) = one_ray([0.0, 0.0, 0.0], [0.0, 0.0, 1.0], 0.0, 1.0);
        let (ov, wv, vrays) = ray_vars(&rays);
        for secant in [0, 1, 8] {
            let cfg = MarchConfig {
                steps: 5,
                secant_steps: secant,
                tolerance: 1.0,
                ..MarchConfig::default()
            };
            let h = march(field.as_ref(), &rays, &range, &cfg).unwrap();
            assert_eq!(h.status, vec![RayStatus::Hit], "secant {secant}");
            assert_eq!(v64(&h.depth), vec![0.5]);
            all_finite(&h);
            let g =
                implicit_and_backward(field.as_ref(), &vrays, &h, &[&normal, &offset, &ov, &wv]);
            near_eq(g[1][0], -1.0, "∂t/∂o (plane offset)");
            near_eq(g[2][2], -1.0, "∂t/∂o_z (ray origin)");
        }
    }
}

/// Values ±f64::MAX: `s_hi − s_lo` overflows, so every secant point is degenerate.
struct Step;
impl ImplicitSurface for Step {
    fn value(&self, p: &Tensor) -> Result<Tensor> {
        let z = p.narrow(1, 2, 1)?.squeeze(1)?;
        let big = Tensor::full(f64::MAX, z.shape(), z.device())?.to_dtype(z.dtype())?;
        Ok(z.ge(0.3)?.where_cond(&big, &big.neg()?)?)
    }
    fn value_and_grad(&self, p: &Tensor) -> Result<(Tensor, Tensor)> {
        Ok((self.value(p)?, p.zeros_like()?))
    }
    fn inside(&self) -> Inside {
        Inside::Positive
    }
}

#[test]
fn secant_denominator_zero_falls_back_to_bisection() {
    // The rule itself (equal values, overflow and NaN give the midpoint) is tested beside
    // it, in src/dvr/marching.rs.
    // A march on a field whose every secant denominator overflows: bisection converges.
    let (rays, range) = one_ray([0.0, 0.0, 0.0], [0.0, 0.0, 1.0], 0.0, 1.0);
    let cfg = MarchConfig {
        steps: 11,
        secant_steps: 30,
        ..MarchConfig::default()
    };
    let h = march(&Step, &rays, &range, &cfg).unwrap();
    // ∇f = 0: the status says the normal is degenerate.
    assert_eq!(h.status, vec![RayStatus::Grazing]);
    assert!((v64(&h.depth)[0] - 0.3).abs() < 1e-9, "{:?}", v64(&h.depth));
    all_finite(&h);
    let cfg = MarchConfig {
        grazing_threshold: None,
        ..cfg
    };
    let h = march(&Step, &rays, &range, &cfg).unwrap();
    assert_eq!(h.status, vec![RayStatus::Hit]);
    // The same with a learnable offset θ (f = ±f64::MAX + θ, θ = 0): the secant steps
    // still overflow, and the implicit step has ∇f = 0, so its denominator is floored
    // (guarded) at ε·min_gradient·‖w‖ = 1e-15 with the sign of +0: ∂t/∂θ = −1e15,
    // finite, and ∂t/∂o = ∂t/∂w = 0.
    let theta = Var::new(0.0f64, &DEV).unwrap();
    let field = ShiftedStep(theta.clone());
    for grazing_threshold in [Some(1e-3), None] {
        let cfg = MarchConfig {
            grazing_threshold,
            ..cfg.clone()
        };
        let h = march(&field, &rays, &range, &cfg).unwrap();
        let want = if grazing_threshold.is_some() {
            RayStatus::Grazing
        } else {
            RayStatus::Hit
        };
        assert_eq!(h.status, vec![want]);
        assert!((v64(&h.depth)[0] - 0.3).abs() < 1e-9, "{:?}", v64(&h.depth));
        let (ov, wv, vrays) = ray_vars(&rays);
        let s = implicit_surface(&field, &vrays, &h, &ImplicitConfig::default()).unwrap();
        assert_eq!(v64(&s.guarded.to_dtype(DType::F64).unwrap()), vec![1.0]);
        let g = implicit_and_backward(&field, &vrays, &h, &[&theta, &ov, &wv]);
        assert!((g[0][0] + 1e15).abs() <= 1.0, "∂t/∂θ = {:e}", g[0][0]);
        assert!(g[1].iter().chain(&g[2]).all(|&x| x == 0.0), "{g:?}");
    }
}

/// [`Step`] plus a learnable offset θ (a scalar variable).
struct ShiftedStep(Var);
impl ImplicitSurface for ShiftedStep {
    fn value(&self, p: &Tensor) -> Result<Tensor> {
        Ok(Step.value(p)?.broadcast_add(self.0.as_tensor())?)
    }
    fn value_and_grad(&self, p: &Tensor) -> Result<(Tensor, Tensor)> {
        Ok((self.value(p)?, p.zeros_like()?))
    }
    fn inside(&self) -> Inside {
        Inside::Positive
    }
}

#[test]
fn not_converged_is_reported_when_the_refinement_is_too_short() {
    let field = Sphere::new([0.0; 3], 0.5, &DEV, DType::F64).unwrap().sdf();
    let (rays, range) = one_ray([0.1, 0.2, -2.0], [0.0, 0.0, 1.0], 0.0, 4.0);
    let cfg = MarchConfig {
        steps: 8,
        secant_steps: 0,
        tolerance: 1e-6,
        ..MarchConfig::default()
    };
    let h = march(&field, &rays, &range, &cfg).unwrap();
    assert_eq!(h.status, vec![RayStatus::NotConverged]);
    let cfg = MarchConfig {
        secant_steps: 12,
        ..cfg
    };
    let h = march(&field, &rays, &range, &cfg).unwrap();
    assert_eq!(h.status, vec![RayStatus::Hit]);
}

#[test]
fn illinois_beats_plain_regula_falsi_on_a_curved_crossing() {
    let field = Sphere::new([0.0; 3], 0.5, &DEV, DType::F64)
        .unwrap()
        .occupancy(10.0);
    let (rays, range) = one_ray([0.3, 0.0, -2.0], [0.0, 0.0, 1.0], 0.0, 4.0);
    let exact = 2.0 - (0.25f64 - 0.09).sqrt();
    let err = |rule| {
        let cfg = MarchConfig {
            steps: 8,
            secant_steps: 6,
            rule,
            ..MarchConfig::default()
        };
        (v64(&march(&field, &rays, &range, &cfg).unwrap().depth)[0] - exact).abs()
    };
    let (e_rf, e_il) = (err(SecantRule::RegulaFalsi), err(SecantRule::Illinois));
    assert!(
        e_il < 1e-12 && e_il < e_rf,
        "illinois {e_il:e}, regula falsi {e_rf:e}"
    );
}

/// The argument an `Err(InvalidArgument)` names; also checks that its message starts
/// with that name.
fn err_arg<T: std::fmt::Debug>(r: Result<T>) -> String {
    let e = r.unwrap_err();
    let msg = e.to_string();
    match e {
        neural_fields::Error::InvalidArgument { arg, .. } => {
            assert!(msg.starts_with(&format!("{arg}: ")), "{msg}");
            arg.to_string()
        }
        e => panic!("unexpected {e}"),
    }
}

#[test]
fn bad_input_errs_naming_the_argument() {
    let field = Sphere::new([0.0; 3], 0.5, &DEV, DType::F64).unwrap().sdf();
    let o = Tensor::new(&[[0.0f64, 0.0, -2.0], [0.0, 0.0, -2.0]], &DEV).unwrap();
    let w = Tensor::new(&[[0.0f64, 0.0, 1.0], [0.0, 0.1, 1.0]], &DEV).unwrap();
    let n = Tensor::new(&[0.0f64, 0.0], &DEV).unwrap();
    let f = Tensor::new(&[4.0f64, 4.0], &DEV).unwrap();
    let c = MarchConfig::default();
    let st = SphereTraceConfig::default();
    let ic = ImplicitConfig::default();
    let rays = Rays::new(o.clone(), w.clone()).unwrap();
    let range = Intersection::new(n.clone(), f.clone()).unwrap();
    assert!(march(&field, &rays, &range, &c).is_ok());
    assert!(sphere_trace(&field, &rays, &range, &st).is_ok());

    // Bad rays: march, sphere_trace and implicit_surface take validated `Rays`, so what
    // they used to reject (naming `origins` / `directions`) is now rejected by
    // `Rays::new`, naming the same argument.
    let w1 = w.narrow(0, 0, 1).unwrap();
    assert_eq!(err_arg(Rays::new(o.clone(), w1.clone())), "directions");
    let bad_o = Tensor::new(&[[0.0f64, f64::NAN, -2.0], [0.0, 0.0, -2.0]], &DEV).unwrap();
    assert_eq!(err_arg(Rays::new(bad_o, w.clone())), "origins");
    let inf_o = Tensor::new(&[[0.0f64, f64::INFINITY, -2.0], [0.0, 0.0, -2.0]], &DEV).unwrap();
    assert_eq!(err_arg(Rays::new(inf_o, w.clone())), "origins");
    let zero_w = Tensor::new(&[[0.0f64, 0.0, 1.0], [0.0, 0.0, 0.0]], &DEV).unwrap();
    assert_eq!(err_arg(Rays::new(o.clone(), zero_w)), "directions");
    let o2 = Tensor::new(&[[0.0f64, 0.0], [0.0, 0.0]], &DEV).unwrap();
    assert_eq!(err_arg(Rays::new(o2, w.clone())), "origins");
    let w32 = w.to_dtype(DType::F32).unwrap();
    assert_eq!(err_arg(Rays::new(o.clone(), w32.clone())), "directions");
    let w4 = Tensor::new(&[[0.0f64, 0.0, 1.0, 0.0], [0.0, 0.1, 1.0, 0.0]], &DEV).unwrap();
    assert_eq!(err_arg(Rays::new(o.clone(), w4)), "directions");
    for bad in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
        let bad_w = Tensor::new(&[[0.0f64, 0.0, 1.0], [bad, 0.0, 1.0]], &DEV).unwrap();
        assert_eq!(err_arg(Rays::new(o.clone(), bad_w)), "directions");
    }

    // Bad ranges from `Intersection::new`: `far < near` names `far` (on any ray; it marks
    // every ray hit), and so do a `far` of the wrong shape, dtype or with non-finite
    // values.
    let f_lt = Tensor::new(&[-1.0f64, 4.0], &DEV).unwrap();
    assert_eq!(err_arg(Intersection::new(n.clone(), f_lt.clone())), "far");
    let f3 = Tensor::new(&[4.0f64, 4.0, 4.0], &DEV).unwrap();
    assert_eq!(err_arg(Intersection::new(n.clone(), f3.clone())), "far");
    let f21 = f.unsqueeze(1).unwrap();
    assert_eq!(err_arg(Intersection::new(n.clone(), f21.clone())), "far");
    let f32_ = f.to_dtype(DType::F32).unwrap();
    assert_eq!(err_arg(Intersection::new(n.clone(), f32_)), "far");
    let f_nan = Tensor::new(&[4.0f64, f64::NAN], &DEV).unwrap();
    assert_eq!(err_arg(Intersection::new(n.clone(), f_nan.clone())), "far");
    let n32 = n.to_dtype(DType::F32).unwrap();
    assert_eq!(err_arg(Intersection::new(n32.clone(), f.clone())), "far");
    let n_inf = Tensor::new(&[f64::INFINITY, 0.0], &DEV).unwrap();
    assert_eq!(err_arg(Intersection::new(n_inf.clone(), f.clone())), "near");
    let n21 = n.unsqueeze(1).unwrap();
    assert_eq!(err_arg(Intersection::new(n21.clone(), f21.clone())), "near");
    let n_int = Tensor::new(&[0u32, 0], &DEV).unwrap();
    assert_eq!(err_arg(Intersection::new(n_int, f.clone())), "near");
    // A valid range for 3 rays does not fit 2: its hit mask is checked first.
    let n3 = Tensor::new(&[0.0f64, 0.0, 0.0], &DEV).unwrap();
    let range3 = Intersection::new(n3.clone(), f3.clone()).unwrap();
    assert_eq!(err_arg(march(&field, &rays, &range3, &c)), "hit");
    assert_eq!(err_arg(sphere_trace(&field, &rays, &range3, &st)), "hit");

    // Bad ranges built field by field (as from a bounding volume): march and
    // sphere_trace name the bad field.
    let good = ray_aabb(&rays, [-0.55; 3], [0.55; 3]).unwrap();
    assert!(march(&field, &rays, &good, &c).is_ok());
    let with = |near: &Tensor, far: &Tensor, hit: &Tensor| Intersection {
        near: near.clone(),
        far: far.clone(),
        hit: hit.clone(),
    };
    let hit2 = Tensor::new(&[1u8, 1], &DEV).unwrap();
    let cases = [
        (with(&n3, &f, &hit2), "near"),
        (with(&n21, &f, &hit2), "near"),
        (with(&n, &f3, &hit2), "far"),
        (with(&n, &f21, &hit2), "far"),
        (with(&n, &f, &Tensor::new(&[1u8], &DEV).unwrap()), "hit"),
        (with(&n32, &f, &hit2), "near"),
        (with(&n, &f.to_dtype(DType::F32).unwrap(), &hit2), "far"),
        (with(&n, &f_nan, &hit2), "far"),
        (with(&n_inf, &f, &hit2), "near"),
        // far < near on a ray with hit = 1 (on a ray with hit = 0 it is ignored).
        (with(&f, &n, &hit2), "far"),
        (with(&n, &f_lt, &hit2), "far"),
    ];
    for (bounds, arg) in &cases {
        assert_eq!(err_arg(march(&field, &rays, bounds, &c)), *arg);
        assert_eq!(err_arg(sphere_trace(&field, &rays, bounds, &st)), *arg);
    }
    let hit01 = Tensor::new(&[1u8, 0], &DEV).unwrap();
    let swapped = with(
        &Tensor::new(&[0.0f64, 4.0], &DEV).unwrap(),
        &Tensor::new(&[4.0f64, 1.0], &DEV).unwrap(),
        &hit01,
    );
    let h = march(&field, &rays, &swapped, &c).unwrap();
    assert_eq!(h.status[1], RayStatus::Miss);
    assert_eq!(v64(&h.depth)[1], 0.0);
    let h = sphere_trace(&field, &rays, &swapped, &st).unwrap();
    assert_eq!(h.status[1], RayStatus::Miss);
    assert_eq!(v64(&h.depth)[1], 0.0);
    // Fewer rays than the range covers.
    let one = Rays::new(o.narrow(0, 0, 1).unwrap(), w1.clone()).unwrap();
    assert_eq!(err_arg(march(&field, &one, &good, &c)), "hit");

    // Configurations and fields.
    let c1 = MarchConfig {
        steps: 1,
        ..MarchConfig::default()
    };
    assert_eq!(err_arg(march(&field, &rays, &range, &c1)), "config.steps");
    let c0 = MarchConfig {
        chunk_points: 0,
        ..MarchConfig::default()
    };
    assert_eq!(
        err_arg(march(&field, &rays, &range, &c0)),
        "config.chunk_points"
    );
    let occ = Sphere::new([0.0; 3], 0.5, &DEV, DType::F64)
        .unwrap()
        .occupancy(2.0);
    assert_eq!(err_arg(sphere_trace(&occ, &rays, &range, &st)), "field");
    assert_eq!(err_arg(StepSchedule::new(vec![(5, 16)])), "milestones");

    // implicit_surface: hits of other rays (a valid march of these two rays).
    let hits = march(&field, &rays, &range, &c).unwrap();
    assert!(implicit_surface(&field, &rays, &hits, &ic).is_ok());
    assert_eq!(err_arg(implicit_surface(&field, &one, &hits, &ic)), "hits");
    let rays32 = Rays::new(o.to_dtype(DType::F32).unwrap(), w32).unwrap();
    assert_eq!(
        err_arg(implicit_surface(&field, &rays32, &hits, &ic)),
        "hits"
    );
}

/// A ray whose range is empty (`near = far`) used to be an error naming `far`; it is now
/// a miss at depth 0 that costs no evaluation, in `march` and `sphere_trace` alike, and
/// the other rays of the batch are unaffected.
#[test]
fn ray_with_near_equal_far_is_a_miss_without_evaluation() {
    let inner = Sphere::new([0.0; 3], 0.5, &DEV, DType::F64).unwrap().sdf();
    let o = Tensor::new(&[[0.0f64, 0.0, -2.0], [0.0, 0.0, -2.0]], &DEV).unwrap();
    let w = Tensor::new(&[[0.0f64, 0.0, 1.0], [0.0, 0.1, 1.0]], &DEV).unwrap();
    let n = Tensor::new(&[0.0f64, 0.0], &DEV).unwrap();
    let (rays, range) = problem(
        o.clone(),
        w.clone(),
        n.clone(),
        Tensor::new(&[4.0f64, 0.0], &DEV).unwrap(),
    );
    let cfg = MarchConfig {
        steps: 16,
        secant_steps: 4,
        ..MarchConfig::default()
    };
    let field = Counting::new(&inner);
    let h = march(&field, &rays, &range, &cfg).unwrap();
    assert_eq!(h.status, vec![RayStatus::Hit, RayStatus::Miss]);
    let d = v64(&h.depth);
    assert!((d[0] - 1.5).abs() < 1e-9, "{d:?}");
    assert_eq!(d[1], 0.0);
    assert_eq!(v64(&h.mask.to_dtype(DType::F64).unwrap()), vec![1.0, 0.0]);
    // Only ray 0 was evaluated: 16 samples and 4 secant steps.
    assert_eq!(field.points.get(), 20);
    assert_eq!(h.evaluations, 20);

    let field = Counting::new(&inner);
    let h = sphere_trace(&field, &rays, &range, &SphereTraceConfig::default()).unwrap();
    assert!(h.status[0].has_surface(), "{:?}", h.status);
    assert_eq!(h.status[1], RayStatus::Miss);
    assert_eq!(v64(&h.depth)[1], 0.0);
    // Every point evaluated lies on ray 0 (x = y = 0), none on ray 1.
    let single = problem(
        o.narrow(0, 0, 1).unwrap(),
        w.narrow(0, 0, 1).unwrap(),
        n.narrow(0, 0, 1).unwrap(),
        Tensor::new(&[4.0f64], &DEV).unwrap(),
    );
    let alone = Counting::new(&inner);
    sphere_trace(&alone, &single.0, &single.1, &SphereTraceConfig::default()).unwrap();
    assert_eq!(field.points.get(), alone.points.get());

    // A non-zero empty range (near = far = 3 on a hit ray) is a miss at depth 0 too.
    let (rays, range) = problem(
        o.clone(),
        w.clone(),
        Tensor::new(&[0.0f64, 3.0], &DEV).unwrap(),
        Tensor::new(&[4.0f64, 3.0], &DEV).unwrap(),
    );
    let field = Counting::new(&inner);
    let h = march(&field, &rays, &range, &cfg).unwrap();
    assert_eq!(h.status, vec![RayStatus::Hit, RayStatus::Miss]);
    assert_eq!(v64(&h.depth)[1], 0.0);
    assert_eq!(field.points.get(), 20);
}

#[test]
fn sphere_tracing_agrees_with_the_march_on_sdfs() {
    for (name, shape) in shapes() {
        if let Shape::Plane { .. } = shape {
            continue;
        }
        for dtype in [DType::F64, DType::F32] {
            let field = shape.sdf_surface(dtype);
            let b = rays_at(&shape, 48, 21, dtype);
            let (rays, range) = tensors(&b, dtype);
            let cfg = MarchConfig {
                steps: 256,
                secant_steps: 12,
                ..MarchConfig::default()
            };
            let m = march(field.as_ref(), &rays, &range, &cfg).unwrap();
            let s =
                sphere_trace(field.as_ref(), &rays, &range, &SphereTraceConfig::default()).unwrap();
            let (dm, ds) = (v64(&m.depth), v64(&s.depth));
            let tol = if dtype == DType::F64 { 1e-4 } else { 2e-4 };
            for i in 0..b.o.len() {
                if m.status[i] == RayStatus::Hit && s.status[i] == RayStatus::Hit {
                    // Sphere tracing stops within `threshold` of the surface.
                    assert!(
                        (dm[i] - ds[i]).abs() * norm(b.w[i]) < tol,
                        "{name} ray {i}: {} vs {}",
                        dm[i],
                        ds[i]
                    );
                }
                assert_eq!(
                    m.status[i].has_surface(),
                    s.status[i].has_surface(),
                    "{name} ray {i}"
                );
            }
            all_finite(&s);
        }
    }
}

#[test]
fn sphere_tracing_falls_back_to_sampling_and_steps_back_on_overshoot() {
    // f = 1.5·d overestimates the distance: steps land inside and must step back.
    struct Overshoot(neural_fields::field::Sdf<Sphere>);
    impl ImplicitSurface for Overshoot {
        fn value(&self, p: &Tensor) -> Result<Tensor> {
            Ok(self.0.value(p)?.affine(1.5, 0.0)?)
        }
        fn value_and_grad(&self, p: &Tensor) -> Result<(Tensor, Tensor)> {
            let (v, g) = self.0.value_and_grad(p)?;
            Ok((v.affine(1.5, 0.0)?, g.affine(1.5, 0.0)?))
        }
        fn inside(&self) -> Inside {
            Inside::Negative
        }
    }
    let field = Overshoot(Sphere::new([0.0; 3], 0.5, &DEV, DType::F64).unwrap().sdf());
    let (rays, range) = problem(
        Tensor::new(
            &[[0.0f64, 0.0, -2.0], [0.2, 0.1, -2.0], [0.0, 0.0, -0.2]],
            &DEV,
        )
        .unwrap(),
        Tensor::new(
            &[[0.0f64, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]],
            &DEV,
        )
        .unwrap(),
        Tensor::zeros(3, DType::F64, &DEV).unwrap(),
        Tensor::new(&[4.0f64, 4.0, 4.0], &DEV).unwrap(),
    );
    let cfg = SphereTraceConfig {
        max_iters: 3,
        ..SphereTraceConfig::default()
    };
    let h = sphere_trace(&field, &rays, &range, &cfg).unwrap();
    let d = v64(&h.depth);
    assert_eq!(h.status[2], RayStatus::StartsInside);
    for (i, expected) in [(0, 1.5), (1, 2.0 - (0.25f64 - 0.05).sqrt())] {
        assert!(h.status[i].has_surface(), "{:?}", h.status);
        assert!(
            (d[i] - expected).abs() < 1e-6,
            "ray {i}: {} vs {expected}",
            d[i]
        );
    }
}

#[test]
fn march_skips_rays_outside_the_box_without_evaluating_them() {
    let inner = Sphere::new([0.0; 3], 0.5, &DEV, DType::F64).unwrap().sdf();
    let field = Counting::new(&inner);
    let rays = Rays::new(
        Tensor::new(&[[0.0f64, 0.0, -2.0], [0.0, 3.0, -2.0]], &DEV).unwrap(),
        Tensor::new(&[[0.0f64, 0.0, 1.0], [0.0, 0.0, 1.0]], &DEV).unwrap(),
    )
    .unwrap();
    let bounds = ray_aabb(&rays, [-0.55; 3], [0.55; 3]).unwrap();
    let cfg = MarchConfig {
        steps: 32,
        secant_steps: 8,
        ..MarchConfig::default()
    };
    let h = march(&field, &rays, &bounds, &cfg).unwrap();
    assert_eq!(h.status, vec![RayStatus::Hit, RayStatus::Miss]);
    assert!((v64(&h.depth)[0] - 1.5).abs() < 1e-12);
    assert_eq!(v64(&h.depth)[1], 0.0, "a ray outside the box has depth 0");
    assert_eq!(field.points.get(), 40);
}

#[test]
fn step_schedule_goes_coarse_to_fine() {
    let s = StepSchedule::default();
    assert_eq!(
        [0, 49_999, 50_000, 150_000, 10_000_000]
            .map(|i| s.config_at(i, &MarchConfig::default()).steps),
        [16, 16, 32, 64, 128]
    );
    let custom = StepSchedule::new(vec![(0, 8), (10, 24)]).unwrap();
    let c = custom.config_at(12, &MarchConfig::default());
    assert_eq!(c.steps, 24);
    assert_eq!(c.secant_steps, MarchConfig::default().secant_steps);
}
