//! DVR root finding: depth error and run time against march steps × secant steps, and
//! against sphere-tracing iterations, on an analytic torus (f64) and on a trained 4×64
//! ReLU Mlp (f32; IDR geometric initialisation, then fitted to the torus's SDF), each
//! against its own high-accuracy march (4096 steps + 40 secant steps).

use crate::report::{median_seconds, v64, Row, Table, TIME_PER_CALL};
use candle_core::{DType, Device, Tensor};
use candle_nn::{Optimizer, VarMap};
use neural_fields::camera::{ray_sphere, Camera, Convention, Intersection, Intrinsics, Rays};
use neural_fields::dvr::{march, sphere_trace, Hits, MarchConfig, SphereTraceConfig};
use neural_fields::field::{ImplicitSurface, SignedDistance, Torus};
use neural_fields::glam::DVec3;
use neural_fields::nn::{adam, build_seeded, mlp, Activation, Mlp, MlpConfig};
use neural_fields::rng::SplitMix64;

fn scene(side: usize, dtype: DType) -> (Rays, Intersection) {
    let k = Intrinsics::from_fov_y(side, side, 0.7).unwrap();
    let eye = DVec3::new(0.4, 1.6, 1.8);
    let cam = Camera::look_at(k, eye, DVec3::ZERO, DVec3::Z, Convention::OpenGl).unwrap();
    let rays = cam.rays(&Device::Cpu, dtype).unwrap();
    let bounds = ray_sphere(&rays, [0.0; 3], 1.0).unwrap();
    (rays, bounds)
}

/// Mean |t − t_ref| over the rays the reference hits (a ray that finds no surface counts
/// with its far bound), in units of the scene radius (1).
fn depth_error(h: &Hits, reference: &Hits, far: &[f64]) -> f64 {
    let (d, r) = (v64(&h.depth), v64(&reference.depth));
    let mut sum = 0.0;
    let mut n = 0usize;
    for i in 0..d.len() {
        if reference.status[i].has_surface() {
            let t = if h.status[i].has_surface() {
                d[i]
            } else {
                far[i]
            };
            sum += (t - r[i]).abs();
            n += 1;
        }
    }
    sum / n.max(1) as f64
}

/// The reference march: 4096 samples + 40 secant steps (1024 + 40 in quick mode).
fn accurate(quick: bool) -> MarchConfig {
    MarchConfig {
        steps: if quick { 1024 } else { 4096 },
        secant_steps: 40,
        tolerance: 1.0,
        ..MarchConfig::default()
    }
}

/// The camera rays (16² in quick mode, 32² otherwise), their bounds, the reference
/// march of `field` along them and their far bounds on the host.
fn reference_scene<F: ImplicitSurface + ?Sized>(
    field: &F,
    dtype: DType,
    quick: bool,
) -> (Rays, Intersection, Hits, Vec<f64>) {
    let (rays, bounds) = scene(if quick { 16 } else { 32 }, dtype);
    let reference = march(field, &rays, &bounds, &accurate(quick)).unwrap();
    let far = v64(&bounds.far);
    (rays, bounds, reference, far)
}

/// One row of a depth table: `run` once for the depth error against `reference` (with
/// the rays' far bounds), then `reps` more times for the median wall time.
fn depth_row(
    series: String,
    knob: usize,
    reps: usize,
    (reference, far): (&Hits, &[f64]),
    run: impl Fn() -> Hits,
) -> Row {
    let hits = run();
    Row {
        series,
        knob: knob as f64,
        error: depth_error(&hits, reference, far),
        seconds: median_seconds(reps, || drop(run())),
        work: hits.status.len() as f64,
    }
}

fn march_table<F: ImplicitSurface + ?Sized>(
    field: &F,
    title: &str,
    what: &str,
    dtype: DType,
    quick: bool,
) -> Table {
    let (rays, bounds, reference, far) = reference_scene(field, dtype, quick);
    let steps: &[usize] = if quick {
        &[16, 64, 256]
    } else {
        &[16, 32, 64, 128, 256, 512, 1024]
    };
    let reps = if quick { 1 } else { 3 };
    let mut rows = Vec::new();
    for &secant in &[0usize, 2, 8] {
        for &n in steps {
            let cfg = MarchConfig {
                steps: n,
                secant_steps: secant,
                ..MarchConfig::default()
            };
            rows.push(depth_row(
                format!("{secant} secant steps"),
                n,
                reps,
                (&reference, &far),
                || march(field, &rays, &bounds, &cfg).unwrap(),
            ));
        }
    }
    Table {
        title: title.into(),
        description: format!(
            "{what}; {} camera rays clipped to the unit sphere; `march` with n evenly \
             spaced samples and k secant steps (Illinois); error = mean |t − t_ref| over the \
             rays the reference (4096 steps + 40 secant; 1024 in quick mode) hits, a ray with no surface counting \
             with its far bound; time = median wall time of one march of all rays.",
            rays.len()
        ),
        knob: "samples per ray".into(),
        error_name: "mean abs(t − t_ref)".into(),
        work_unit: "rays".into(),
        time_name: TIME_PER_CALL.into(),
        rows,
    }
}

fn sphere_trace_table<F: ImplicitSurface + ?Sized>(
    field: &F,
    title: &str,
    what: &str,
    dtype: DType,
    quick: bool,
) -> Table {
    let (rays, bounds, reference, far) = reference_scene(field, dtype, quick);
    let reps = if quick { 1 } else { 3 };
    let iters: &[usize] = if quick {
        &[5, 20]
    } else {
        &[2, 5, 10, 20, 40, 80]
    };
    let mut rows = Vec::new();
    for (series, fallback) in [
        (
            "IDR fallback (100 samples + 8 secant)",
            MarchConfig {
                steps: 100,
                secant_steps: 8,
                ..MarchConfig::default()
            },
        ),
        (
            "crude fallback (4 samples, no secant)",
            MarchConfig {
                steps: 4,
                secant_steps: 0,
                ..MarchConfig::default()
            },
        ),
    ] {
        for &it in iters {
            let cfg = SphereTraceConfig {
                max_iters: it,
                fallback: fallback.clone(),
                ..SphereTraceConfig::default()
            };
            // Rays that miss the bounding sphere (hit = 0) are misses, never evaluated.
            rows.push(depth_row(
                series.into(),
                it,
                reps,
                (&reference, &far),
                || sphere_trace(field, &rays, &bounds, &cfg).unwrap(),
            ));
        }
    }
    Table {
        title: title.into(),
        description: format!(
            "{what}, {} camera rays; IDR-style sphere tracing from \
             both ends (threshold 5e-5, step back 0.5) for the given number of iterations, \
             unconverged rays finished by the fallback march; error and time as in the march \
             tables (reference: 4096 samples + 40 secant steps). Rays that converge stop \
             within the threshold of the surface, so the error floor is about the threshold; \
             fewer iterations hand more rays to the (more accurate) fallback.",
            rays.len()
        ),
        knob: "sphere-tracing iterations".into(),
        error_name: "mean abs(t − t_ref)".into(),
        work_unit: "rays".into(),
        time_name: TIME_PER_CALL.into(),
        rows,
    }
}

/// A 4×64 ReLU Mlp started from IDR's geometric initialisation (a sphere of radius 0.5)
/// and fitted to the torus's SDF by Adam on mean |f − sdf| over uniform points in
/// [−1, 1]³. Returns the network and its final mean |f − sdf| on fresh points.
fn trained_mlp(torus: &dyn ImplicitSurface, quick: bool) -> (Mlp, f64) {
    let (dev, dt) = (Device::Cpu, DType::F32);
    let cfg = MlpConfig {
        hidden: 64,
        depth: 4,
        activation: Activation::Relu,
        ..MlpConfig::sdf(0.5)
    };
    let varmap = VarMap::new();
    let net = build_seeded(&varmap, dt, &dev, 3, |vb| mlp(&cfg, vb)).unwrap();
    let mut opt = adam(&varmap, 1e-3).unwrap();
    let mut rng = SplitMix64::new(17);
    let mut batch = |n: usize| {
        let p = rng.uniform_tensor(&[n, 3], -1.0, 1.0, dt, &dev).unwrap();
        let target = torus
            .value(&p.to_dtype(DType::F64).unwrap())
            .unwrap()
            .to_dtype(dt)
            .unwrap();
        (p, target)
    };
    let l1 = |net: &Mlp, p: &Tensor, target: &Tensor| {
        (net.value(p).unwrap() - target)
            .unwrap()
            .abs()
            .unwrap()
            .mean_all()
            .unwrap()
    };
    for _ in 0..if quick { 20 } else { 1500 } {
        let (p, target) = batch(4096);
        opt.backward_step(&l1(&net, &p, &target)).unwrap();
    }
    let (p, target) = batch(65_536);
    let err = l1(&net, &p, &target).to_scalar::<f32>().unwrap();
    (net, f64::from(err))
}

/// The DVR studies (see the module docs).
pub fn run(quick: bool) -> Vec<Table> {
    let torus = Torus::new([0.0; 3], 0.5, 0.2, &Device::Cpu, DType::F64)
        .unwrap()
        .sdf();
    let (net, fit) = trained_mlp(&torus, quick);
    let net_what = format!(
        "4×64 ReLU Mlp, IDR geometric initialisation then fitted to the torus's SDF (mean \
         |f − sdf| = {fit:.1e}), f32, against its own f32 reference march"
    );
    vec![
        march_table(
            &torus,
            "DVR march depth error vs samples (torus SDF, f64)",
            "Torus SDF (R = 0.5, r = 0.2), f64",
            DType::F64,
            quick,
        ),
        march_table(
            &net,
            "DVR march depth error vs samples (trained 4x64 ReLU Mlp, f32)",
            &net_what,
            DType::F32,
            quick,
        ),
        sphere_trace_table(
            &torus,
            "DVR sphere tracing depth error vs iterations (torus SDF)",
            "Torus SDF (R = 0.5, r = 0.2), f64",
            DType::F64,
            quick,
        ),
        sphere_trace_table(
            &net,
            "DVR sphere tracing depth error vs iterations (trained 4x64 ReLU Mlp, f32)",
            &net_what,
            DType::F32,
            quick,
        ),
    ]
}
