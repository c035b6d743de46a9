//! Occupancy losses: values against closed forms, gradients against central finite
//! differences (f64 proptests), finiteness for extreme logits, and the samplers.
#![cfg(feature = "occupancy")]

mod common;

use candle_core::{DType, Device, Tensor, Var};
use neural_fields::mesh::{points_from_tensor, Mesh};
use neural_fields::occupancy::{kl_standard_normal, reconstruction_loss, reparameterize};
use neural_fields::occupancy::{marching_cubes, Grid};
use neural_fields::occupancy::{
    near_surface, uniform_in_padded_cube, winding_numbers, WindingConfig,
};
use proptest::prelude::*;

/// The inside test for real meshes: `|w(p)| > ½` for the generalised winding number `w`.
fn inside_mesh(mesh: &neural_fields::mesh::Mesh, points: &[[f64; 3]]) -> Vec<bool> {
    winding_numbers(mesh, points, &WindingConfig::default())
        .unwrap()
        .into_iter()
        .map(|w| w.abs() > 0.5)
        .collect()
}

fn t2(v: &[f64], r: usize, c: usize) -> Tensor {
    Tensor::from_vec(v.to_vec(), (r, c), &Device::Cpu).unwrap()
}

fn fd(f: &dyn Fn(&[f64]) -> f64, x: &[f64], i: usize, h: f64) -> f64 {
    let mut a = x.to_vec();
    let mut b = x.to_vec();
    a[i] += h;
    b[i] -= h;
    (f(&a) - f(&b)) / (2.0 * h)
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(48))]

    #[test]
    fn reconstruction_loss_gradient_matches_finite_differences(
        logits in proptest::collection::vec(-30.0f64..30.0, 6),
        targets in proptest::collection::vec(0.0f64..1.0, 6),
    ) {
        let loss_of = |x: &[f64]| reconstruction_loss(&t2(x, 2, 3), &t2(&targets, 2, 3)).unwrap().to_scalar::<f64>().unwrap();
        let v = Var::from_tensor(&t2(&logits, 2, 3)).unwrap();
        let l = reconstruction_loss(v.as_tensor(), &t2(&targets, 2, 3)).unwrap();
        let g = common::v64(l.backward().unwrap().get(&v).unwrap());
        for i in 0..6 {
            let num = fd(&loss_of, &logits, i, 1e-5);
            prop_assert!((g[i] - num).abs() < 1e-6, "{i}: {} vs {num}", g[i]);
            // closed form (σ(x) − y)/B with B = 2
            let s = 1.0 / (1.0 + (-logits[i]).exp());
            prop_assert!((g[i] - (s - targets[i]) / 2.0).abs() < 1e-12);
        }
    }

    #[test]
    fn kl_and_reparameterisation_gradients_match_finite_differences(
        mean in proptest::collection::vec(-5.0f64..5.0, 4),
        logvar in proptest::collection::vec(-10.0f64..5.0, 4),
        seed in 0u64..1000,
    ) {
        let kl_of = |m: &[f64], l: &[f64]| kl_standard_normal(&t2(m, 2, 2), &t2(l, 2, 2)).unwrap().sum_all().unwrap().to_scalar::<f64>().unwrap();
        let z_of = |m: &[f64], l: &[f64]| reparameterize(&t2(m, 2, 2), &t2(l, 2, 2), seed).unwrap().sqr().unwrap().sum_all().unwrap().to_scalar::<f64>().unwrap();
        let vm = Var::from_tensor(&t2(&mean, 2, 2)).unwrap();
        let vl = Var::from_tensor(&t2(&logvar, 2, 2)).unwrap();
        let kl = kl_standard_normal(vm.as_tensor(), vl.as_tensor()).unwrap().sum_all().unwrap();
        let z = reparameterize(vm.as_tensor(), vl.as_tensor(), seed).unwrap().sqr().unwrap().sum_all().unwrap();
        for (obj, f) in [(&kl, &kl_of as &dyn Fn(&[f64], &[f64]) -> f64), (&z, &z_of)] {
            let g = obj.backward().unwrap();
            let gm = common::v64(g.get(&vm).unwrap());
            let gl = common::v64(g.get(&vl).unwrap());
            for i in 0..4 {
                let nm = fd(&|x: &[f64]| f(x, &logvar), &mean, i, 1e-5);
                let nl = fd(&|x: &[f64]| f(&mean, x), &logvar, i, 1e-5);
                prop_assert!((gm[i] - nm).abs() < 1e-5 * (1.0 + nm.abs()), "mean {i}: {} vs {nm}", gm[i]);
                prop_assert!((gl[i] - nl).abs() < 1e-5 * (1.0 + nl.abs()), "logvar {i}: {} vs {nl}", gl[i]);
            }
        }
    }
}

#[test]
fn losses_are_finite_for_extreme_logits_in_f32_and_closed_forms_hold() {
    let d = Device::Cpu;
    let x = Var::from_tensor(&Tensor::new(&[[1e4f32, -1e4, 0.0, 88.0]], &d).unwrap()).unwrap();
    let y = Tensor::new(&[[0.0f32, 1.0, 0.5, 0.0]], &d).unwrap();
    let l = reconstruction_loss(x.as_tensor(), &y).unwrap();
    let lv = l.to_scalar::<f32>().unwrap();
    assert!((lv - (2e4 + 2f32.ln() + 88.0)).abs() < 1.0, "{lv}");
    let g = common::v64(l.backward().unwrap().get(&x).unwrap());
    assert!(g.iter().all(|v| v.is_finite()), "{g:?}");
    assert_eq!(g[0], 1.0);
    assert_eq!(g[1], -1.0);
    // KL is zero at the prior and ½(μ²) for unit variance.
    let m = Tensor::new(&[[0.0f64, 0.0], [2.0, 0.0]], &d).unwrap();
    let kl = common::v64(&kl_standard_normal(&m, &m.zeros_like().unwrap()).unwrap());
    assert_eq!(kl, vec![0.0, 2.0]);
    // Same seed, same sample; the sample's moments are those of N(μ, σ²).
    let mean = Tensor::full(1.5f64, (50_000, 1), &d).unwrap();
    let lv = Tensor::full((0.25f64).ln(), (50_000, 1), &d).unwrap();
    let z = common::v64(&reparameterize(&mean, &lv, 3).unwrap());
    assert_eq!(z, common::v64(&reparameterize(&mean, &lv, 3).unwrap()));
    let mu = z.iter().sum::<f64>() / z.len() as f64;
    let var = z.iter().map(|v| (v - mu).powi(2)).sum::<f64>() / z.len() as f64;
    assert!(
        (mu - 1.5).abs() < 0.01 && (var - 0.25).abs() < 0.01,
        "{mu} {var}"
    );
    // Errors name the argument.
    let e = kl_standard_normal(&m, &Tensor::zeros((3, 2), DType::F64, &d).unwrap())
        .unwrap_err()
        .to_string();
    assert!(e.starts_with("logvar"), "{e}");
    let e = reconstruction_loss(
        &Tensor::zeros(3, DType::F64, &d).unwrap(),
        &Tensor::zeros(3, DType::F64, &d).unwrap(),
    )
    .unwrap_err()
    .to_string();
    assert!(e.starts_with("logits"), "{e}");
}

fn sphere_mesh(n: usize) -> Mesh {
    let g = Grid::from_fn([n; 3], [-0.5; 3], [0.5; 3], |p| {
        (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt() - 0.35
    })
    .unwrap();
    marching_cubes(&g, 0.0, neural_fields::field::Inside::Negative).unwrap()
}

#[test]
fn winding_number_inside_test_is_exact_on_closed_meshes_and_robust_to_holes() {
    let mut mesh = sphere_mesh(25);
    let pts = points_from_tensor(
        &uniform_in_padded_cube(4000, 0.1, 5, &Device::Cpu, DType::F64).unwrap(),
    )
    .unwrap();
    let truth: Vec<bool> = pts
        .iter()
        .map(|p| (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt() < 0.35)
        .collect();
    let w = winding_numbers(&mesh, &pts, &WindingConfig::default()).unwrap();
    let exact = WindingConfig {
        force_reference: true,
    };
    let we = winding_numbers(&mesh, &pts, &exact).unwrap();
    let worst = w
        .iter()
        .zip(&we)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f64::max);
    assert!(worst < 0.02, "fast vs exact winding number: {worst}");
    let near =
        |p: &[f64; 3]| ((p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt() - 0.35).abs() < 0.01;
    for ((p, &t), &wi) in pts.iter().zip(&truth).zip(&w) {
        if !near(p) {
            assert!((wi - if t { 1.0 } else { 0.0 }).abs() < 0.02, "{p:?}: {wi}");
        }
    }
    // Punch holes (drop 2% of the faces) and flip the orientation: still right away from
    // the surface.
    let keep: Vec<[u32; 3]> = mesh
        .faces
        .iter()
        .enumerate()
        .filter(|(i, _)| i % 50 != 0)
        .map(|(_, f)| [f[0], f[2], f[1]])
        .collect();
    mesh.faces = keep;
    assert!(mesh.edge_report().0 > 0, "the mesh has holes now");
    let inside = inside_mesh(&mesh, &pts);
    let wrong = pts
        .iter()
        .zip(&truth)
        .zip(&inside)
        .filter(|((p, t), i)| !near(p) && *t != *i)
        .count();
    assert_eq!(wrong, 0);
    // Near-surface samples straddle the surface.
    let ns = near_surface(&mesh, 2000, 0.01, 1).unwrap();
    let ins = inside_mesh(&mesh, &ns).iter().filter(|&&b| b).count();
    assert!((600..1400).contains(&ins), "{ins}");
    let box_pts = points_from_tensor(
        &uniform_in_padded_cube(1000, 0.1, 2, &Device::Cpu, DType::F32).unwrap(),
    )
    .unwrap();
    assert!(box_pts.iter().flatten().all(|c| c.abs() <= 0.55));
    assert!(uniform_in_padded_cube(10, -1.0, 0, &Device::Cpu, DType::F32).is_err());
}
