//! `dvr::implicit_surface`: the implicit depth gradient against central finite
//! differences of the depth found by a high-accuracy march (f64), w.r.t. Mlp weights, an
//! analytic sphere's radius and centre, a latent code, ray origins and directions, and a
//! camera pose; plus values, f32, and degenerate rays (finite, guarded, excluded).

#![allow(clippy::needless_range_loop)]

mod common;

use candle_core::{DType, Device, Tensor, Var};
use candle_nn::{VarBuilder, VarMap};
use common::counting::Counting;
use common::hits::count;
use common::{central_diff, close, v64};
use glam::DVec3;
use neural_fields::camera::{
    pose_rays, Camera, Convention, Intersection, Intrinsics, PoseParam, Rays,
};
use neural_fields::dvr::{
    implicit_surface, march, Hits, ImplicitConfig, MarchConfig, RayStatus, SurfacePoints,
};
use neural_fields::field::{Conditioned, ImplicitSurface, Inside, SignedDistance, Sphere, Torus};
use neural_fields::nn::{build_seeded, mlp, Activation, Mlp, MlpConfig};
use neural_fields::rng::SplitMix64;
use proptest::prelude::*;

const DEV: Device = Device::Cpu;

/// Rays from distance 2 towards random points within `spread` of `center`;
/// `[0, 4/|w|]` bounds; directions of random length in [0.5, 2].
fn rays(seed: u64, r: usize, center: [f64; 3], spread: f64) -> (Tensor, Tensor, Tensor, Tensor) {
    let mut rng = SplitMix64::new(seed);
    let (mut o, mut w, mut far) = (vec![], vec![], vec![]);
    for _ in 0..r {
        let target: Vec<f64> = center
            .iter()
            .map(|c| c + spread * (2.0 * rng.uniform() - 1.0))
            .collect();
        let d = [rng.normal(), rng.normal(), rng.normal()];
        let l = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        let s = 0.5 + 1.5 * rng.uniform();
        for k in 0..3 {
            o.push(target[k] - 2.0 * d[k] / l);
            w.push(s * d[k] / l);
        }
        far.push(4.0 / s);
    }
    (
        Tensor::from_vec(o, (r, 3), &DEV).unwrap(),
        Tensor::from_vec(w, (r, 3), &DEV).unwrap(),
        Tensor::zeros(r, DType::F64, &DEV).unwrap(),
        Tensor::from_vec(far, r, &DEV).unwrap(),
    )
}

/// Validated rays `(o, w)` (sharing their graph) and the range `[n, fa]` on each.
fn problem(o: &Tensor, w: &Tensor, n: &Tensor, fa: &Tensor) -> (Rays, Intersection) {
    (
        Rays::new(o.clone(), w.clone()).unwrap(),
        Intersection::new(n.clone(), fa.clone()).unwrap(),
    )
}

/// `L = Σ cᵢ tᵢ` over the rays, from a high-accuracy march.
fn loss_from_march<F: ImplicitSurface + ?Sized>(
    f: &F,
    o: &Tensor,
    w: &Tensor,
    n: &Tensor,
    fa: &Tensor,
    c: &[f64],
) -> f64 {
    let (rays, range) = problem(o, w, n, fa);
    let h = march(f, &rays, &range, &common::hits::accurate_march()).unwrap();
    v64(&h.depth).iter().zip(c).map(|(t, c)| t * c).sum()
}

/// Which rays hit cleanly, from the implicit step `s` of the march `h`: a crossing is
/// found and the angle is not grazing (|cos(∇f, w)| ≥ 0.1); the tests do not apply to
/// the others.
fn clean_hits(s: &SurfacePoints, w: &Tensor, h: &Hits) -> Vec<bool> {
    // `gradient` has one row per hit ray (in `indices` order).
    let g = v64(&s.gradient);
    let wv = v64(&w.detach());
    let mut ok = vec![false; h.status.len()];
    let idx = s.indices.to_vec1::<u32>().unwrap();
    for (j, &i) in idx.iter().enumerate() {
        let i = i as usize;
        let (g, w) = (&g[3 * j..3 * j + 3], &wv[3 * i..3 * i + 3]);
        let dot: f64 = g.iter().zip(w).map(|(a, b)| a * b).sum();
        let ng: f64 = g.iter().map(|a| a * a).sum::<f64>().sqrt();
        let nw: f64 = w.iter().map(|a| a * a).sum::<f64>().sqrt();
        ok[i] = h.status[i] == RayStatus::Hit && dot.abs() >= 0.1 * ng * nw;
    }
    ok
}

/// Up to `r` rays that hit `f` cleanly ([`clean_hits`]), chosen from 4·`r` candidates
/// drawn by [`rays`] (`center = 0`, `spread = 0.15`): their indices among the candidates
/// and `(o, w, near, far)`. Requiring `r` random rays to hit at once rejected most
/// proptest cases on the bumpy Mlp (PROPTEST_CASES=256 aborted with "Too many global
/// rejects"); drawing candidates and keeping the clean ones rejects almost none.
/// `f` is evaluated on the candidates (with per-ray codes it needs 4·`r` of them).
fn hitting_rays<F: ImplicitSurface + ?Sized>(
    seed: u64,
    r: usize,
    f: &F,
) -> (Tensor, Tensor, Tensor, Tensor, Tensor) {
    let n = 4 * r;
    let (o, w, near, far) = rays(seed, n, [0.0; 3], 0.15);
    let (rays, range) = problem(&o, &w, &near, &far);
    let h = march(f, &rays, &range, &common::hits::accurate_march()).unwrap();
    let s = implicit_surface(f, &rays, &h, &ImplicitConfig::default()).unwrap();
    let keep: Vec<u32> = clean_hits(&s, &w, &h)
        .iter()
        .enumerate()
        .filter(|(_, ok)| **ok)
        .map(|(i, _)| i as u32)
        .take(r)
        .collect();
    let idx = Tensor::new(keep.as_slice(), &DEV).unwrap();
    let pick = |t: &Tensor| t.index_select(&idx, 0).unwrap();
    (idx.clone(), pick(&o), pick(&w), pick(&near), pick(&far))
}

/// March + implicit step; `None` if some ray does not hit cleanly ([`clean_hits`]),
/// where the test does not apply.
fn implicit_loss<F: ImplicitSurface + ?Sized>(
    f: &F,
    o: &Tensor,
    w: &Tensor,
    n: &Tensor,
    fa: &Tensor,
    c: &[f64],
) -> Option<(Tensor, Hits)> {
    let (detached, range) = problem(&o.detach(), &w.detach(), n, fa);
    let h = march(f, &detached, &range, &common::hits::accurate_march()).unwrap();
    if h.status.iter().any(|s| *s != RayStatus::Hit) {
        return None;
    }
    let rays = Rays::new(o.clone(), w.clone()).unwrap();
    let s = implicit_surface(f, &rays, &h, &ImplicitConfig::default()).unwrap();
    if clean_hits(&s, w, &h).contains(&false) {
        return None;
    }
    assert_eq!(
        v64(&s.depth),
        v64(&h.depth),
        "the value of t̂ is the march's depth"
    );
    let ct = Tensor::from_vec(c.to_vec(), c.len(), &DEV).unwrap();
    Some(((s.depth * ct).unwrap().sum_all().unwrap(), h))
}

fn entry(v: &Var, i: usize) -> f64 {
    v64(v.as_tensor())[i]
}

/// FD of `loss()` along entry `i` of `v` (restored afterwards).
fn fd(v: &Var, i: usize, loss: &mut dyn FnMut() -> f64) -> Option<f64> {
    let x0 = entry(v, i);
    let mut f = |x: f64| {
        common::set_entry(v, i, x);
        loss()
    };
    let d = central_diff(&mut f, x0, 1e-5, 1.0);
    common::set_entry(v, i, x0);
    d
}

/// Compares implicit gradients with finite differences and counts how many entries
/// the FD could check: `central_diff` returns `None` where its stencil crossed a kink,
/// and a test whose entries are mostly skipped would pass without checking anything.
#[derive(Default)]
struct FdChecks {
    checked: usize,
    total: usize,
}

impl FdChecks {
    fn check(
        &mut self,
        name: &str,
        analytic: f64,
        numeric: Option<f64>,
    ) -> Result<(), TestCaseError> {
        self.total += 1;
        if let Some(n) = numeric {
            self.checked += 1;
            prop_assert!(
                close(analytic, n, 1e-6, 1e-3),
                "{name}: implicit {analytic:e} vs FD {n:e}"
            );
        }
        Ok(())
    }

    /// At least half of the entries were compared; otherwise the case is rejected (not
    /// passed): proptest then draws another, and fails the test when too many are
    /// rejected, so every passing case compared at least half of its entries. (Failing
    /// here instead made PROPTEST_CASES=256 fail on the rare seeds where `central_diff`
    /// finds the stencil not smooth in most entries — about 1 case in 50 on the softplus
    /// (β = 10) Mlp, e.g. seed 17153234324806895028 for the latent code and
    /// 11354795438458203958 for the Mlp weights; not yet investigated.)
    fn enough(&self) -> Result<(), TestCaseError> {
        if self.total > 0 && 2 * self.checked >= self.total {
            Ok(())
        } else {
            Err(TestCaseError::reject(format!(
                "finite differences checked only {} of {} entries",
                self.checked, self.total
            )))
        }
    }
}

fn coeffs(seed: u64, r: usize) -> Vec<f64> {
    let mut rng = SplitMix64::new(seed ^ 0xC0FFEE);
    (0..r).map(|_| rng.normal()).collect()
}

/// An SDF Mlp (geometric init to a sphere of radius 0.5), with every weight perturbed so
/// that the shape is not a sphere.
fn bumpy_mlp(seed: u64, code_dim: usize) -> (VarMap, Mlp) {
    let varmap = VarMap::new();
    let cfg = MlpConfig {
        hidden: 16,
        depth: 2,
        code_dim,
        activation: Activation::Softplus { beta: 10.0 },
        ..MlpConfig::sdf(0.5)
    };
    let net = build_seeded(&varmap, DType::F64, &DEV, seed, |vb| mlp(&cfg, vb)).unwrap();
    let mut rng = SplitMix64::new(seed ^ 99);
    let data = varmap.data().lock().unwrap();
    let mut names: Vec<&String> = data.keys().collect();
    names.sort();
    for name in names {
        let v = &data[name];
        let noise = common::normal_tensor(&mut rng, v.dims(), 0.0, 0.1, DType::F64, &DEV).unwrap();
        v.set(&(v.as_tensor() + noise).unwrap()).unwrap();
    }
    drop(data);
    drop(net);
    // Rebuild: a blocked weight (geometric init with codes) is concatenated from its
    // variables when the network is built, so the perturbation must come first.
    let net = mlp(&cfg, VarBuilder::from_varmap(&varmap, DType::F64, &DEV)).unwrap();
    (varmap, net)
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(10))]

    /// (a) ∂L/∂θ for the weights of an Mlp SDF.
    #[test]
    fn depth_gradient_wrt_mlp_weights_matches_finite_differences(seed in any::<u64>()) {
        let mut checks = FdChecks::default();
        let (varmap, net) = bumpy_mlp(seed, 0);
        let (idx, o, w, n, fa) = hitting_rays(seed, 4, &net);
        prop_assume!(idx.dim(0).unwrap() >= 2);
        let c = coeffs(seed, idx.dim(0).unwrap());
        let hit = implicit_loss(&net, &o, &w, &n, &fa, &c);
        prop_assume!(hit.is_some());
        let (l, _) = hit.unwrap();
        let grads = l.backward().unwrap();
        let mut rng = SplitMix64::new(seed ^ 5);
        let vars = common::sorted_vars(&varmap);
        for _ in 0..6 {
            let v = &vars[rng.below(vars.len() as u64) as usize];
            let i = rng.below(v.elem_count() as u64) as usize;
            let analytic = grads.get(v).map_or(0.0, |g| v64(g)[i]);
            let numeric = fd(v, i, &mut || loss_from_march(&net, &o, &w, &n, &fa, &c));
            checks.check("weight", analytic, numeric)?;
        }
        checks.enough()?;
    }

    /// (b) ∂L/∂r and ∂L/∂c for an analytic sphere with a learnable radius and centre,
    /// as an SDF and as occupancy logits.
    #[test]
    fn depth_gradient_wrt_sphere_radius_and_centre_matches_finite_differences(
        seed in any::<u64>(), occupancy in any::<bool>(), radius in 0.2f64..0.9
    ) {
        let mut checks = FdChecks::default();
        let mut rng = SplitMix64::new(seed);
        let c0 = [0.2 * rng.normal(), 0.2 * rng.normal(), 0.2 * rng.normal()];
        let center = Var::new(&c0, &DEV).unwrap();
        let r = Var::new(radius, &DEV).unwrap();
        let sphere = Sphere { center: center.as_tensor().clone(), radius: r.as_tensor().clone() };
        let field: Box<dyn ImplicitSurface> = if occupancy {
            Box::new(sphere.occupancy(7.0))
        } else {
            Box::new(sphere.sdf())
        };
        let (o, w, n, fa) = rays(seed, 5, c0, 0.5 * radius);
        let c = coeffs(seed, 5);
        let hit = implicit_loss(field.as_ref(), &o, &w, &n, &fa, &c);
        prop_assume!(hit.is_some());
        let (l, _) = hit.unwrap();
        let grads = l.backward().unwrap();
        let mut loss = || loss_from_march(field.as_ref(), &o, &w, &n, &fa, &c);
        checks.check("radius", v64(grads.get(&r).unwrap())[0], fd(&r, 0, &mut loss))?;
        for k in 0..3 {
            checks.check("centre", v64(grads.get(&center).unwrap())[k], fd(&center, k, &mut loss))?;
        }
        checks.enough()?;
    }

    /// (c) ∂L/∂z for the latent code of a conditional Mlp bound by `Conditioned`.
    #[test]
    fn depth_gradient_wrt_latent_code_matches_finite_differences(seed in any::<u64>()) {
        let mut checks = FdChecks::default();
        let (_varmap, net) = bumpy_mlp(seed, 4);
        let mut rng = SplitMix64::new(seed ^ 3);
        let z = Var::from_tensor(&common::normal_tensor(&mut rng, &[4], 0.0, 0.5, DType::F64, &DEV).unwrap()).unwrap();
        let field = Conditioned::new(&net, z.as_tensor().clone()).unwrap();
        let (idx, o, w, n, fa) = hitting_rays(seed, 4, &field);
        prop_assume!(idx.dim(0).unwrap() >= 2);
        let c = coeffs(seed, idx.dim(0).unwrap());
        let hit = implicit_loss(&field, &o, &w, &n, &fa, &c);
        prop_assume!(hit.is_some());
        let (l, _) = hit.unwrap();
        let g = v64(l.backward().unwrap().get(&z).unwrap());
        prop_assert!(g.iter().any(|v| v.abs() > 1e-6), "the code has an effect: {g:?}");
        for k in 0..4 {
            let mut loss = || {
                let f = Conditioned::new(&net, z.as_tensor().clone()).unwrap();
                loss_from_march(&f, &o, &w, &n, &fa, &c)
            };
            checks.check("code", g[k], fd(&z, k, &mut loss))?;
        }
        checks.enough()?;
    }

    /// (c′) One code per ray: `Conditioned` with an `[R, D]` code marches every ray with
    /// its own code, and ∂L/∂zᵣ equals finite differences of the march for every entry
    /// (a ray's depth depends on its own row only).
    #[test]
    fn depth_gradient_wrt_per_ray_codes_matches_finite_differences(seed in any::<u64>()) {
        let mut checks = FdChecks::default();
        let (_varmap, net) = bumpy_mlp(seed, 4);
        // Codes for 16 candidate rays; the rays that hit cleanly keep their own rows.
        let mut rng = SplitMix64::new(seed ^ 7);
        let z_all = common::normal_tensor(&mut rng, &[16, 4], 0.0, 0.5, DType::F64, &DEV).unwrap();
        let all_codes = Conditioned::new(&net, z_all.clone()).unwrap();
        let (idx, o, w, n, fa) = hitting_rays(seed, 4, &all_codes);
        let r = idx.dim(0).unwrap();
        prop_assume!(r >= 2);
        let z = Var::from_tensor(&z_all.index_select(&idx, 0).unwrap()).unwrap();
        let field = Conditioned::new(&net, z.as_tensor().clone()).unwrap();
        let c = coeffs(seed, r);
        let hit = implicit_loss(&field, &o, &w, &n, &fa, &c);
        prop_assume!(hit.is_some());
        let (l, _) = hit.unwrap();
        let g = v64(l.backward().unwrap().get(&z).unwrap());
        for i in 0..4 * r {
            let mut loss = || {
                let f = Conditioned::new(&net, z.as_tensor().clone()).unwrap();
                loss_from_march(&f, &o, &w, &n, &fa, &c)
            };
            checks.check("per-ray code", g[i], fd(&z, i, &mut loss))?;
        }
        checks.enough()?;
    }

    /// (d, e) ∂L/∂o and ∂L/∂w for every ray coordinate, on a torus (SDF and occupancy)
    /// and on an Mlp.
    #[test]
    fn depth_gradient_wrt_ray_origins_and_directions_matches_finite_differences(
        seed in any::<u64>(), which in 0usize..3
    ) {
        let mut checks = FdChecks::default();
        let torus = Torus::new([0.0; 3], 0.5, 0.2, &DEV, DType::F64).unwrap();
        let (_vm, net) = bumpy_mlp(seed, 0);
        let field: Box<dyn ImplicitSurface> = match which {
            0 => Box::new(torus.sdf()),
            1 => Box::new(torus.occupancy(4.0)),
            _ => Box::new(net),
        };
        let (o0, w0, n, fa) = if which < 2 { rays(seed, 3, [0.5, 0.0, 0.0], 0.1) } else { rays(seed, 3, [0.0; 3], 0.15) };
        let o = Var::from_tensor(&o0).unwrap();
        let w = Var::from_tensor(&w0).unwrap();
        let c = coeffs(seed, 3);
        let hit = implicit_loss(field.as_ref(), o.as_tensor(), w.as_tensor(), &n, &fa, &c);
        prop_assume!(hit.is_some());
        let (l, _) = hit.unwrap();
        let grads = l.backward().unwrap();
        let (go, gw) = (v64(grads.get(&o).unwrap()), v64(grads.get(&w).unwrap()));
        for i in 0..9 {
            let mut loss = || loss_from_march(field.as_ref(), o.as_tensor(), w.as_tensor(), &n, &fa, &c);
            checks.check("origin", go[i], fd(&o, i, &mut loss))?;
            let mut loss = || loss_from_march(field.as_ref(), o.as_tensor(), w.as_tensor(), &n, &fa, &c);
            checks.check("direction", gw[i], fd(&w, i, &mut loss))?;
        }
        checks.enough()?;
    }
}

#[test]
fn depth_gradient_reaches_the_camera_pose_and_matches_finite_differences() {
    let k = Intrinsics::from_fov_y(16, 12, 0.7).unwrap();
    let cam = Camera::look_at(
        k,
        DVec3::new(0.3, 0.4, 2.5),
        DVec3::ZERO,
        DVec3::Y,
        Convention::OpenGl,
    )
    .unwrap();
    let pose = PoseParam::from_affine(&cam.cam_to_world(), &DEV, DType::F64).unwrap();
    let views = Tensor::zeros(3, DType::U32, &DEV).unwrap();
    let pixels = Tensor::new(&[[8.5f64, 6.5], [7.0, 5.0], [9.5, 7.5]], &DEV).unwrap();
    let field = Sphere::new([0.0, 0.05, 0.0], 0.6, &DEV, DType::F64)
        .unwrap()
        .occupancy(3.0);
    let c = [1.0, -0.7, 0.4];
    let n = Tensor::zeros(3, DType::F64, &DEV).unwrap();
    let fa = Tensor::new(&[5.0f64, 5.0, 5.0], &DEV).unwrap();
    let rays = pose_rays(std::slice::from_ref(&pose), &[cam], &views, &pixels).unwrap();
    let (l, _) = implicit_loss(&field, rays.origins(), rays.directions(), &n, &fa, &c).unwrap();
    let grads = l.backward().unwrap();
    let mut loss = || {
        let r = pose_rays(std::slice::from_ref(&pose), &[cam], &views, &pixels).unwrap();
        loss_from_march(&field, r.origins(), r.directions(), &n, &fa, &c)
    };
    let gq = v64(grads.get(&pose.rotation).unwrap());
    let gt = v64(grads.get(&pose.translation).unwrap());
    for i in 0..4 {
        let numeric = fd(&pose.rotation, i, &mut loss).unwrap();
        assert!(
            close(gq[i], numeric, 1e-6, 1e-3),
            "rotation {i}: {} vs {numeric}",
            gq[i]
        );
    }
    for i in 0..3 {
        let numeric = fd(&pose.translation, i, &mut loss).unwrap();
        assert!(
            close(gt[i], numeric, 1e-6, 1e-3),
            "translation {i}: {} vs {numeric}",
            gt[i]
        );
    }
    assert!(gt.iter().any(|g| g.abs() > 1e-3));
}

#[test]
fn f32_surface_points_equal_the_march_and_have_finite_gradients() {
    let r = Var::new(0.5f32, &DEV).unwrap();
    let sphere = Sphere {
        center: Tensor::zeros(3, DType::F32, &DEV).unwrap(),
        radius: r.as_tensor().clone(),
    };
    let field = sphere.sdf();
    let o = Tensor::new(&[[0.1f32, 0.0, -2.0], [0.0, 0.2, -2.0]], &DEV).unwrap();
    let w = Tensor::new(&[[0.0f32, 0.0, 1.0], [0.0, 0.0, 2.0]], &DEV).unwrap();
    let n = Tensor::zeros(2, DType::F32, &DEV).unwrap();
    let fa = Tensor::new(&[4.0f32, 2.0], &DEV).unwrap();
    let (rays, range) = problem(&o, &w, &n, &fa);
    let h = march(&field, &rays, &range, &MarchConfig::default()).unwrap();
    let s = implicit_surface(&field, &rays, &h, &ImplicitConfig::default()).unwrap();
    assert_eq!(s.depth.dtype(), DType::F32);
    assert_eq!(v64(&s.depth), v64(&h.depth));
    let p = v64(&s.points);
    let hp = v64(&h.points);
    for (a, b) in p.iter().zip(&hp) {
        assert!((a - b).abs() < 1e-6);
    }
    let g = v64(s
        .depth
        .sum_all()
        .unwrap()
        .backward()
        .unwrap()
        .get(&r)
        .unwrap())[0];
    // ∂t/∂r = −1/(∇f·w)·(−1)... for an SDF sphere, ∂t/∂r = −(∂f/∂r)/(∇f·w) = 1/(n·w) < 0.
    assert!(g.is_finite() && g < 0.0, "{g}");
}

#[test]
fn grazing_ray_gets_a_guarded_finite_gradient_with_the_right_sign() {
    let r = Var::new(0.5f64, &DEV).unwrap();
    let field = Sphere {
        center: Tensor::zeros(3, DType::F64, &DEV).unwrap(),
        radius: r.as_tensor().clone(),
    }
    .sdf();
    let y = 0.5 - 1e-12;
    let o = Tensor::new(&[[0.0f64, y, -2.0]], &DEV).unwrap();
    let w = Tensor::new(&[[0.0f64, 0.0, 1.0]], &DEV).unwrap();
    let n = Tensor::new(&[1.0f64], &DEV).unwrap();
    let fa = Tensor::new(&[2.0f64 + 1e-9], &DEV).unwrap();
    let cfg = MarchConfig {
        steps: 2,
        secant_steps: 40,
        ..MarchConfig::default()
    };
    let (rays, range) = problem(&o, &w, &n, &fa);
    let h = march(&field, &rays, &range, &cfg).unwrap();
    assert_eq!(h.status, vec![RayStatus::Grazing]);
    let s = implicit_surface(&field, &rays, &h, &ImplicitConfig::default()).unwrap();
    assert_eq!(v64(&s.guarded.to_dtype(DType::F64).unwrap()), vec![1.0]);
    let g = v64(s
        .depth
        .sum_all()
        .unwrap()
        .backward()
        .unwrap()
        .get(&r)
        .unwrap())[0];
    // Growing the sphere moves the entry point towards the camera: negative, bounded by 1/ε.
    assert!((-1e3 - 1e-9..0.0).contains(&g), "{g}");
}

#[test]
fn rays_without_surface_are_excluded_and_get_zero_gradient() {
    let field = Sphere::new([0.0; 3], 0.5, &DEV, DType::F64).unwrap().sdf();
    let o = Var::new(
        &[[0.0f64, 0.0, -2.0], [0.0, 0.0, 0.1], [0.0, 3.0, -2.0]],
        &DEV,
    )
    .unwrap();
    let w = Var::new(
        &[[0.0f64, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]],
        &DEV,
    )
    .unwrap();
    let n = Tensor::zeros(3, DType::F64, &DEV).unwrap();
    let fa = Tensor::new(&[4.0f64, 4.0, 4.0], &DEV).unwrap();
    let (rays, range) = problem(o.as_tensor(), w.as_tensor(), &n, &fa);
    let h = march(&field, &rays, &range, &MarchConfig::default()).unwrap();
    assert_eq!(
        h.status,
        vec![RayStatus::Hit, RayStatus::StartsInside, RayStatus::Miss]
    );
    let s = implicit_surface(&field, &rays, &h, &ImplicitConfig::default()).unwrap();
    assert_eq!(s.indices.to_vec1::<u32>().unwrap(), vec![0]);
    let grads = s.points.sum_all().unwrap().backward().unwrap();
    let go = v64(grads.get(&o).unwrap());
    assert!(go.iter().all(|v| v.is_finite()));
    assert!(go[3..].iter().all(|&v| v == 0.0), "{go:?}");
    // ∂t/∂o_z = −∇f_z/(∇f·w) = −1 on the axis; p̂_z = o_z + t̂ → ∂p̂_z/∂o_z = 0.
    assert!(go[2].abs() < 1e-12, "{go:?}");
    // No hits at all: empty outputs.
    let (miss_rays, miss_range) = problem(
        &o.as_tensor().narrow(0, 2, 1).unwrap(),
        &w.as_tensor().narrow(0, 2, 1).unwrap(),
        &n.narrow(0, 0, 1).unwrap(),
        &fa.narrow(0, 0, 1).unwrap(),
    );
    let miss = march(&field, &miss_rays, &miss_range, &MarchConfig::default()).unwrap();
    let e = implicit_surface(&field, &miss_rays, &miss, &ImplicitConfig::default()).unwrap();
    assert_eq!(e.indices.dim(0).unwrap(), 0);
    assert_eq!(e.depth.dims(), [0]);
    assert_eq!(e.points.dims(), [0, 3]);
}

/// ∇f = 0 at the surface (a step field): the denominator is floored, nothing is NaN.
#[test]
fn zero_spatial_gradient_is_guarded_without_nan() {
    struct Step(Var);
    impl ImplicitSurface for Step {
        fn value(&self, p: &Tensor) -> neural_fields::Result<Tensor> {
            let z = p.narrow(1, 2, 1)?.squeeze(1)?;
            let one = z.ones_like()?;
            Ok(z.ge(0.3)?
                .where_cond(&one, &one.neg()?)?
                .broadcast_mul(self.0.as_tensor())?)
        }
        fn value_and_grad(&self, p: &Tensor) -> neural_fields::Result<(Tensor, Tensor)> {
            Ok((self.value(p)?, p.zeros_like()?))
        }
        fn inside(&self) -> Inside {
            Inside::Positive
        }
    }
    let a = Var::new(2.0f64, &DEV).unwrap();
    let field = Step(a.clone());
    let o = Tensor::new(&[[0.0f64, 0.0, 0.0]], &DEV).unwrap();
    let w = Tensor::new(&[[0.0f64, 0.0, 1.0]], &DEV).unwrap();
    let (rays, range) = problem(
        &o,
        &w,
        &Tensor::new(&[0.0f64], &DEV).unwrap(),
        &Tensor::new(&[1.0f64], &DEV).unwrap(),
    );
    let h = march(&field, &rays, &range, &MarchConfig::default()).unwrap();
    let s = implicit_surface(&field, &rays, &h, &ImplicitConfig::default()).unwrap();
    assert_eq!(v64(&s.guarded.to_dtype(DType::F64).unwrap()), vec![1.0]);
    let g = v64(s
        .depth
        .sum_all()
        .unwrap()
        .backward()
        .unwrap()
        .get(&a)
        .unwrap());
    assert!(g.iter().all(|v| v.is_finite()), "{g:?}");
}

#[test]
fn implicit_surface_rejects_hits_of_other_rays() {
    let field = Sphere::new([0.0; 3], 0.5, &DEV, DType::F64).unwrap().sdf();
    let o = Tensor::new(&[[0.0f64, 0.0, -2.0], [0.0, 0.1, -2.0]], &DEV).unwrap();
    let w = Tensor::new(&[[0.0f64, 0.0, 1.0], [0.0, 0.0, 1.0]], &DEV).unwrap();
    let n = Tensor::zeros(2, DType::F64, &DEV).unwrap();
    let fa = Tensor::new(&[4.0f64, 4.0], &DEV).unwrap();
    let (rays, range) = problem(&o, &w, &n, &fa);
    let h = march(&field, &rays, &range, &MarchConfig::default()).unwrap();
    assert!(implicit_surface(&field, &rays, &h, &ImplicitConfig::default()).is_ok());
    let first = rays.narrow(0, 1).unwrap();
    match implicit_surface(&field, &first, &h, &ImplicitConfig::default()).unwrap_err() {
        neural_fields::Error::InvalidArgument { arg, .. } => assert_eq!(arg, "hits"),
        e => panic!("{e}"),
    }
    // A zero direction, which implicit_surface used to reject, cannot reach it any more:
    // `Rays::new` rejects it, naming the same argument.
    let zero = Tensor::new(&[[0.0f64, 0.0, 1.0], [0.0, 0.0, 0.0]], &DEV).unwrap();
    match Rays::new(o.clone(), zero).unwrap_err() {
        neural_fields::Error::InvalidArgument { arg, .. } => assert_eq!(arg, "directions"),
        e => panic!("{e}"),
    }
}

/// Regression: the guard's gradient floor scales with ‖w‖, so short directions get the
/// exact gradient `∂t/∂r (λw) = ∂t/∂r (w)/λ` (an absolute floor on ‖∇f‖‖w‖ distorted it).
#[test]
fn implicit_gradient_is_exact_for_very_short_directions() {
    let r = Var::new(0.5f64, &DEV).unwrap();
    let field = Sphere {
        center: Tensor::zeros(3, DType::F64, &DEV).unwrap(),
        radius: r.as_tensor().clone(),
    }
    .sdf();
    let grad_for = |lambda: f64| {
        let o = Tensor::new(&[[0.1f64, 0.2, -2.0]], &DEV).unwrap();
        let w = Tensor::new(&[[0.0f64, 0.0, lambda]], &DEV).unwrap();
        let n = Tensor::new(&[0.0f64], &DEV).unwrap();
        let fa = Tensor::new(&[4.0 / lambda], &DEV).unwrap();
        let (rays, range) = problem(&o, &w, &n, &fa);
        let h = march(&field, &rays, &range, &common::hits::accurate_march()).unwrap();
        let s = implicit_surface(&field, &rays, &h, &ImplicitConfig::default()).unwrap();
        v64(s
            .depth
            .sum_all()
            .unwrap()
            .backward()
            .unwrap()
            .get(&r)
            .unwrap())[0]
    };
    let (g1, g_short) = (grad_for(1.0), grad_for(1e-15));
    assert!(
        close(g_short * 1e-15, g1, 1e-9, 0.0),
        "{g_short:e} vs {g1:e}"
    );
}

/// A sphere SDF whose radius is its one-entry code: f(p, z) = ‖p‖ − z.
struct CodedSphere;

impl neural_fields::field::ConditionalField for CodedSphere {
    fn code_dim(&self) -> usize {
        1
    }
    fn out_dim(&self) -> usize {
        1
    }
    fn forward_with_code(&self, points: &Tensor, codes: &Tensor) -> neural_fields::Result<Tensor> {
        let norm = points.sqr()?.sum_keepdim(1)?.sqrt()?;
        Ok((norm - codes)?)
    }
    fn value_and_grad_with_code(
        &self,
        points: &Tensor,
        codes: &Tensor,
    ) -> neural_fields::Result<(Tensor, Tensor)> {
        let norm = points.sqr()?.sum_keepdim(1)?.sqrt()?;
        let grad = points.broadcast_div(&norm)?;
        Ok(((norm - codes)?.squeeze(1)?, grad))
    }
    fn inside(&self) -> Inside {
        Inside::Negative
    }
}

/// One code per ray, closed form: rays from (0, 0, −2) along +z through spheres of
/// radii z = (0.3, 0.5, 0.7) bound as a `[3, 1]` code hit at depth 2 − zᵣ (march and
/// implicit step), and ∂t̂ᵣ/∂zₛ = −1 for r = s, 0 otherwise. A shared `[1]` code gives
/// every ray the same depth, and a code with fewer rows than rays is an error naming
/// `code`.
#[test]
fn per_ray_codes_give_each_ray_its_own_surface() {
    let radii = [0.3f64, 0.5, 0.7];
    let z = Var::from_tensor(&Tensor::new(&[[0.3f64], [0.5], [0.7]], &DEV).unwrap()).unwrap();
    let o = Tensor::new(&[[0.0f64, 0.0, -2.0]; 3], &DEV).unwrap();
    let w = Tensor::new(&[[0.0f64, 0.0, 1.0]; 3], &DEV).unwrap();
    let n = Tensor::zeros(3, DType::F64, &DEV).unwrap();
    let fa = Tensor::new(&[4.0f64; 3], &DEV).unwrap();
    let field = Conditioned::new(&CodedSphere, z.as_tensor().clone()).unwrap();
    let (rays, range) = problem(&o, &w, &n, &fa);
    let h = march(&field, &rays, &range, &MarchConfig::default()).unwrap();
    assert_eq!(h.status, vec![RayStatus::Hit; 3]);
    for (t, r) in v64(&h.depth).iter().zip(radii) {
        assert!((t - (2.0 - r)).abs() < 1e-10, "{t} vs {}", 2.0 - r);
    }
    let s = implicit_surface(&field, &rays, &h, &ImplicitConfig::default()).unwrap();
    for r in 0..3 {
        let g = s.depth.get(r).unwrap().backward().unwrap();
        let gz = v64(g.get(&z).unwrap());
        for (k, v) in gz.iter().enumerate() {
            let want = if k == r { -1.0 } else { 0.0 };
            assert!((v - want).abs() < 1e-12, "∂t̂{r}/∂z{k} = {v}");
        }
    }
    let shared = Tensor::new(&[0.5f64], &DEV).unwrap();
    let hs = march(
        &Conditioned::new(&CodedSphere, shared).unwrap(),
        &rays,
        &range,
        &MarchConfig::default(),
    )
    .unwrap();
    assert!(v64(&hs.depth).iter().all(|t| (t - 1.5).abs() < 1e-10));
    let short = Conditioned::new(&CodedSphere, z.as_tensor().narrow(0, 0, 2).unwrap()).unwrap();
    match march(&short, &rays, &range, &MarchConfig::default()) {
        Err(neural_fields::Error::InvalidArgument { arg, .. }) => assert_eq!(arg, "code"),
        other => panic!("{other:?}"),
    }
}

/// The implicit step costs one field evaluation: a single call, over exactly the `H`
/// rays with a surface (misses and rays starting inside are not evaluated), for a plain
/// field and for one with a code per ray (the `_on_rays` path); none without hits.
#[test]
fn implicit_surface_evaluates_the_field_once_over_exactly_the_hit_rays() {
    let sphere = Sphere::new([0.0; 3], 0.5, &DEV, DType::F64).unwrap().sdf();
    let (o, w, n, fa) = rays(7, 32, [0.0; 3], 0.8);
    // One more ray that starts inside.
    let o = Tensor::cat(&[&o, &Tensor::new(&[[0.0f64, 0.0, 0.1]], &DEV).unwrap()], 0).unwrap();
    let w = Tensor::cat(&[&w, &Tensor::new(&[[0.0f64, 0.0, 1.0]], &DEV).unwrap()], 0).unwrap();
    let n = Tensor::cat(&[&n, &Tensor::zeros(1, DType::F64, &DEV).unwrap()], 0).unwrap();
    let fa = Tensor::cat(&[&fa, &Tensor::new(&[4.0f64], &DEV).unwrap()], 0).unwrap();
    let r = 33;
    let z = Tensor::full(0.5f64, (r, 1), &DEV).unwrap();
    let coded = Conditioned::new(&CodedSphere, z).unwrap();
    let fields: [(&str, &dyn ImplicitSurface); 2] = [("sphere", &sphere), ("coded", &coded)];
    let (rays, range) = problem(&o, &w, &n, &fa);
    for (name, field) in fields {
        let h = march(field, &rays, &range, &MarchConfig::default()).unwrap();
        let hit = h.status.iter().filter(|s| s.has_surface()).count();
        assert!(
            hit > 0 && count(&h, RayStatus::Miss) > 0 && count(&h, RayStatus::StartsInside) == 1,
            "{name}: {:?}",
            h.status
        );
        let counted = Counting::new(field);
        let s = implicit_surface(&counted, &rays, &h, &ImplicitConfig::default()).unwrap();
        assert_eq!(s.indices.dim(0).unwrap(), hit, "{name}");
        assert_eq!(counted.calls.get(), 1, "{name}: calls");
        assert_eq!(counted.points.get(), hit, "{name}: points");
        assert_eq!(counted.max_call.get(), hit, "{name}: points in the call");
    }
    // No ray with a surface: no evaluation at all.
    let miss_o = Tensor::new(&[[0.0f64, 3.0, -2.0]], &DEV).unwrap();
    let miss_w = Tensor::new(&[[0.0f64, 0.0, 1.0]], &DEV).unwrap();
    let one = |x: f64| Tensor::new(&[x], &DEV).unwrap();
    let (miss_rays, miss_range) = problem(&miss_o, &miss_w, &one(0.0), &one(4.0));
    let h = march(&sphere, &miss_rays, &miss_range, &MarchConfig::default()).unwrap();
    let counted = Counting::new(&sphere);
    let s = implicit_surface(&counted, &miss_rays, &h, &ImplicitConfig::default()).unwrap();
    assert_eq!(s.indices.dim(0).unwrap(), 0);
    assert_eq!((counted.calls.get(), counted.points.get()), (0, 0));
}
