//! CUDA against CPU: the crate's reference paths give the same results on an NVIDIA GPU
//! as on the CPU, in f32 and f64.
//!
//! Every case builds its inputs on the host from a fixed seed, copies them to the device
//! under test, runs the same code there and on the CPU, and compares every output and
//! every gradient (from `backward()`): relative error `|gpu − cpu| / max(1, |cpu|)` at
//! most 1e-4 in f32 and 1e-10 in f64 (march depths: absolute 1e-5 / 1e-10; the implicit
//! gradients of near-grazing rays in f32: 1e-2, see `mlp_dvr`), all values
//! finite, discrete outputs (ray statuses, masks, mesh faces, evaluation counts) equal.
//! On the CPU `volume::composite` runs the fused kernel and on CUDA the reference path,
//! so those two are compared with each other as well.
//!
//! Only built with the `cuda` feature, which is only used on machines with a GPU:
//! without a usable GPU every test **fails** (it does not skip). Run it with
//!
//! ```text
//! cargo test --release --features cuda --test cuda
//! ```
//!
//! on a machine with nvcc (tested with CUDA 13.0) and an NVIDIA GPU; add
//! `-- --nocapture` for the largest error of every comparison.
#![cfg(feature = "cuda")]

mod common;

use candle_core::{DType, Device, Tensor, Var};
use candle_nn::VarMap;
use common::v64;
use neural_fields::camera::{
    pose_rays, ray_aabb, ray_sphere, Camera, Convention, Intersection, Intrinsics, PixelFilter,
    PoseParam, Rays,
};
use neural_fields::dvr::{
    implicit_surface, march, sphere_trace, ImplicitConfig, MarchConfig, SphereTraceConfig,
};
use neural_fields::encoding::PointEncoding;
use neural_fields::encoding::{integrated_pe, Encoding, FourierFeatures, FrequencyEncoding};
use neural_fields::field::{Cuboid, ImplicitSurface, Inside, Plane, SignedDistance, Sphere, Torus};
use neural_fields::glam::DVec3;
use neural_fields::nn::{build_seeded, mlp, Activation, MlpConfig};
use neural_fields::occupancy::{marching_cubes, mise, Grid, MiseConfig};
use neural_fields::rng::SplitMix64;
use neural_fields::volume::{
    anneal_near_far, composite, distortion_loss, merge_sorted, render_weights, sample_pdf,
    stratified, visible_mask, CompositeConfig, Intervals, Jitter, Layout, ANNEAL_MID_RATIO,
    ANNEAL_P_START, PDF_PADDING,
};
use neural_fields::Result;

/// The device under test. Panics (fails the test) when no CUDA GPU can be opened.
fn gpu() -> Device {
    Device::new_cuda(0).unwrap_or_else(|e| {
        panic!("tests/cuda.rs needs an NVIDIA GPU: Device::new_cuda(0) failed: {e}")
    })
}

/// One output of a case, compared between the two devices.
enum Out {
    /// A tensor on the case's device: relative tolerance of the dtype.
    T(Tensor),
    /// A tensor on the case's device with an absolute tolerance `(f32, f64)`.
    Abs(Tensor, f64, f64),
    /// A tensor on the case's device with a relative tolerance `(f32, f64)`.
    Rel(Tensor, f64, f64),
    /// Host values (meshes, grids): relative tolerance of the dtype.
    Host(Vec<f64>),
    /// Must be equal (rendered with `Debug`).
    Eq(String),
}

type Outs = Vec<(String, Out)>;

fn rel_tol(dtype: DType) -> f64 {
    if dtype == DType::F32 {
        1e-4
    } else {
        1e-10
    }
}

/// Compares `gpu` with `cpu` values; returns the largest error or a failure message.
fn compare_values(
    gpu: &[f64],
    cpu: &[f64],
    tol: f64,
    relative: bool,
) -> std::result::Result<f64, String> {
    if gpu.len() != cpu.len() {
        return Err(format!(
            "{} values on the GPU, {} on the CPU",
            gpu.len(),
            cpu.len()
        ));
    }
    let mut worst = (0.0f64, 0usize);
    for (i, (&a, &b)) in gpu.iter().zip(cpu).enumerate() {
        if !(a.is_finite() && b.is_finite()) {
            return Err(format!("not finite at {i}: gpu {a}, cpu {b}"));
        }
        let scale = if relative { b.abs().max(1.0) } else { 1.0 };
        let err = (a - b).abs() / scale;
        if err > worst.0 {
            worst = (err, i);
        }
    }
    if worst.0 > tol {
        let i = worst.1;
        return Err(format!(
            "error {:.3e} > {tol:e} at {i}: gpu {:e}, cpu {:e}",
            worst.0, gpu[i], cpu[i]
        ));
    }
    Ok(worst.0)
}

/// Checks that a tensor output of the GPU run stayed on the GPU, with the expected dtype.
fn on_device(t: &Tensor, dev: &Device) -> std::result::Result<(), String> {
    if !t.device().same_device(dev) {
        return Err(format!("on {:?}, expected {:?}", t.device(), dev));
    }
    Ok(())
}

fn compare_out(
    gpu: &Out,
    cpu: &Out,
    dtype: DType,
    dev: &Device,
) -> std::result::Result<String, String> {
    let tol = rel_tol(dtype);
    match (gpu, cpu) {
        (Out::T(a), Out::T(b))
        | (Out::Abs(a, _, _), Out::Abs(b, _, _))
        | (Out::Rel(a, _, _), Out::Rel(b, _, _)) => {
            on_device(a, dev)?;
            if a.dims() != b.dims() {
                return Err(format!(
                    "shape {:?} on the GPU, {:?} on the CPU",
                    a.dims(),
                    b.dims()
                ));
            }
            if a.dtype() != b.dtype() {
                return Err(format!(
                    "dtype {:?} on the GPU, {:?} on the CPU",
                    a.dtype(),
                    b.dtype()
                ));
            }
            let (va, vb) = (v64(a), v64(b));
            let (tol, relative) = match gpu {
                Out::Abs(_, t32, t64) => (if dtype == DType::F32 { *t32 } else { *t64 }, false),
                Out::Rel(_, t32, t64) => (if dtype == DType::F32 { *t32 } else { *t64 }, true),
                _ => (tol, true),
            };
            let worst = compare_values(&va, &vb, tol, relative)?;
            Ok(format!(
                "{:?} max {} error {worst:.2e}",
                a.dims(),
                if relative { "rel" } else { "abs" }
            ))
        }
        (Out::Host(a), Out::Host(b)) => {
            let worst = compare_values(a, b, tol, true)?;
            Ok(format!(
                "{} host values, max rel error {worst:.2e}",
                a.len()
            ))
        }
        (Out::Eq(a), Out::Eq(b)) => {
            if a == b {
                Ok("equal".into())
            } else if a.len() < 300 {
                Err(format!("gpu {a} != cpu {b}"))
            } else {
                Err(format!(
                    "differ (first {} chars equal)",
                    a.chars().zip(b.chars()).take_while(|(x, y)| x == y).count()
                ))
            }
        }
        _ => Err("output kinds differ".into()),
    }
}

/// Runs `case` on the CPU and on the GPU in f32 and f64 and compares every output;
/// collects all failures, then panics with the list.
fn check(name: &str, case: impl Fn(&Device, DType) -> Result<Outs>) {
    let dev = gpu();
    let mut failures = Vec::new();
    for dtype in [DType::F32, DType::F64] {
        let cpu = match case(&Device::Cpu, dtype) {
            Ok(o) => o,
            Err(e) => {
                failures.push(format!("{name} {dtype:?}: CPU run failed: {e}"));
                continue;
            }
        };
        let gpu = match case(&dev, dtype) {
            Ok(o) => o,
            Err(e) => {
                failures.push(format!("{name} {dtype:?}: CUDA run failed: {e}"));
                continue;
            }
        };
        let names = |o: &Outs| o.iter().map(|(n, _)| n.clone()).collect::<Vec<_>>();
        if names(&gpu) != names(&cpu) {
            failures.push(format!(
                "{name} {dtype:?}: different outputs {:?} / {:?}",
                names(&gpu),
                names(&cpu)
            ));
            continue;
        }
        for ((what, a), (_, b)) in gpu.iter().zip(&cpu) {
            match compare_out(a, b, dtype, &dev) {
                Ok(msg) => println!("ok   {name} {dtype:?} {what}: {msg}"),
                Err(msg) => {
                    println!("FAIL {name} {dtype:?} {what}: {msg}");
                    failures.push(format!("{name} {dtype:?} {what}: {msg}"));
                }
            }
        }
    }
    assert!(
        failures.is_empty(),
        "{} failure(s):\n{}",
        failures.len(),
        failures.join("\n")
    );
}

/// Seeded uniform host values in `[lo, hi)`, built on the CPU in `dtype` and copied to
/// `dev` (so both devices see identical inputs).
fn uniform(
    rng: &mut SplitMix64,
    shape: &[usize],
    lo: f64,
    hi: f64,
    dtype: DType,
    dev: &Device,
) -> Result<Tensor> {
    Ok(rng
        .uniform_tensor(shape, lo, hi, dtype, &Device::Cpu)?
        .to_device(dev)?)
}

/// The gradient of `var` in `grads` (an error if there is none).
fn grad(grads: &candle_core::backprop::GradStore, var: &Var, what: &str) -> Result<Out> {
    grads.get(var).map(|g| Out::T(g.clone())).ok_or_else(|| {
        candle_core::Error::Msg(format!("grads: expected a gradient for {what}, got none")).into()
    })
}

/// `Σ t ⊙ u` with `u` seeded uniform in `[−1, 1)`: a loss with generic upstream gradients.
fn probe(t: &Tensor, rng: &mut SplitMix64) -> Result<Tensor> {
    let u = uniform(rng, t.dims(), -1.0, 1.0, t.dtype(), &Device::Cpu)?.to_device(t.device())?;
    Ok((t * u)?.sum_all()?)
}

// --- volume ---------------------------------------------------------------------------

fn composite_case(dev: &Device, dtype: DType) -> Result<Outs> {
    let (r, s, c) = (48, 40, 3);
    let mut rng = SplitMix64::new(11);
    let cpu = Device::Cpu;
    // Densities with exact zeros (relu of a shifted uniform), short intervals from t = 2.
    let sig = rng
        .uniform_tensor(&[r, s], -1.0, 6.0, dtype, &cpu)?
        .relu()?;
    let del = rng.uniform_tensor(&[r, s], 0.01, 0.08, dtype, &cpu)?;
    let (st_h, en_h) = common::intervals::starts_ends(&v64(&del), &vec![s; r]);
    let from_host = |v: Vec<f64>| -> Result<Var> {
        let t = Tensor::from_vec(v, (r, s), &cpu)?.affine(1.0, 2.0)?;
        Ok(Var::from_tensor(&t.to_dtype(dtype)?.to_device(dev)?)?)
    };
    let (starts, ends) = (from_host(st_h)?, from_host(en_h)?);
    let iv = Intervals::new(
        starts.as_tensor().clone(),
        ends.as_tensor().clone(),
        Layout::Batched,
    )?;
    let col = rng.uniform_tensor(&[r, s, c], 0.0, 1.0, dtype, &cpu)?;
    let bg = rng.uniform_tensor(&[c], 0.0, 1.0, dtype, &cpu)?;
    // Directions of norms in [0.5, 2) (δ scaled per ray).
    let dirs = rng.uniform_tensor(&[r, 3], 0.3, 1.1, dtype, &cpu)?;
    let sig = Var::from_tensor(&sig.to_device(dev)?)?;
    let col = Var::from_tensor(&col.to_device(dev)?)?;
    let bg = Var::from_tensor(&bg.to_device(dev)?)?;
    let dirs = Var::from_tensor(&dirs.to_device(dev)?)?;
    let rays = Rays::new(Tensor::zeros((r, 3), dtype, dev)?, dirs.as_tensor().clone())?;
    let cfg = CompositeConfig {
        opaque_last: false,
        background: Some(bg.as_tensor().clone()),
        force_reference: false,
    };
    let reference = CompositeConfig {
        force_reference: true,
        ..cfg.clone()
    };
    let mut out: Outs = Vec::new();

    // `composite` is the fused kernel on the CPU and the reference path on CUDA, so its
    // comparison is CUDA reference against CPU fused; `force_reference` runs the
    // reference path on both.
    for (label, config, with_rays) in [
        ("composite", &cfg, false),
        ("composite (force_reference)", &reference, false),
        ("composite_rays", &cfg, true),
        ("composite_rays_reference", &reference, true),
    ] {
        let mut up = SplitMix64::new(5);
        let res = composite(&sig, &col, &iv, with_rays.then_some(&rays), config)?;
        let loss = ((probe(&res.color, &mut up)? + probe(&res.opacity, &mut up)?)?
            + probe(&res.depth, &mut up)?)?;
        let g = loss.backward()?;
        out.push((format!("{label}.color"), Out::T(res.color.clone())));
        out.push((format!("{label}.opacity"), Out::T(res.opacity.clone())));
        out.push((format!("{label}.depth"), Out::T(res.depth.clone())));
        out.push((
            format!("{label}.normalized_depth"),
            Out::T(res.normalized_depth(1e-3)?),
        ));
        out.push((format!("{label}.d/dsigmas"), grad(&g, &sig, "sigmas")?));
        out.push((format!("{label}.d/dstarts"), grad(&g, &starts, "starts")?));
        out.push((format!("{label}.d/dends"), grad(&g, &ends, "ends")?));
        out.push((format!("{label}.d/dcolors"), grad(&g, &col, "colors")?));
        out.push((
            format!("{label}.d/dbackground"),
            grad(&g, &bg, "background")?,
        ));
        if with_rays {
            out.push((
                format!("{label}.d/ddirections"),
                grad(&g, &dirs, "directions")?,
            ));
        }
    }
    // Render weights, opaque last interval.
    let opaque = CompositeConfig {
        opaque_last: true,
        ..CompositeConfig::default()
    };
    let w = render_weights(&sig, &iv, None, &opaque)?;
    let mut up = SplitMix64::new(6);
    let g = probe(&w.weights, &mut up)?.backward()?;
    out.push(("render_weights.weights".into(), Out::T(w.weights.clone())));
    out.push((
        "render_weights.transmittance".into(),
        Out::T(w.transmittance.clone()),
    ));
    out.push(("render_weights.alphas".into(), Out::T(w.alphas.clone())));
    out.push(("render_weights.d/dsigmas".into(), grad(&g, &sig, "sigmas")?));
    out.push((
        "render_weights.d/dstarts".into(),
        grad(&g, &starts, "starts")?,
    ));
    out.push(("render_weights.d/dends".into(), grad(&g, &ends, "ends")?));

    // Early termination and the packed layout.
    let mask = visible_mask(&sig, &iv, None, 1e-3)?;
    out.push(("visible_mask".into(), Out::T(mask.clone())));
    let (kept, idx) = iv.retain(&mask)?;
    let Layout::Packed(packed) = kept.layout else {
        unreachable!("retain returns the packed layout")
    };
    out.push(("packed.offsets".into(), Out::T(packed.offsets.clone())));
    let m = packed.ray_indices.dim(0)?;
    let ps = sig.as_tensor().flatten_all()?.index_select(&idx, 0)?;
    let pst = starts.as_tensor().flatten_all()?.index_select(&idx, 0)?;
    let pen = ends.as_tensor().flatten_all()?.index_select(&idx, 0)?;
    let pc = col.as_tensor().reshape((r * s, c))?.index_select(&idx, 0)?;
    let piv = Intervals::new(pst, pen, Layout::Packed(packed.clone()))?;
    let ps = Var::from_tensor(&ps)?;
    let pc = Var::from_tensor(&pc)?;
    let pcfg = CompositeConfig {
        opaque_last: true,
        background: Some(bg.as_tensor().clone()),
        force_reference: false,
    };
    let preference = CompositeConfig {
        force_reference: true,
        ..pcfg.clone()
    };
    for (label, config) in [
        ("composite (packed)", &pcfg),
        ("composite (packed, force_reference)", &preference),
    ] {
        let mut up = SplitMix64::new(7);
        let res = composite(&ps, &pc, &piv, None, config)?;
        let loss = ((probe(&res.color, &mut up)? + probe(&res.opacity, &mut up)?)?
            + probe(&res.depth, &mut up)?)?;
        let g = loss.backward()?;
        out.push((format!("{label}.color"), Out::T(res.color.clone())));
        out.push((format!("{label}.opacity"), Out::T(res.opacity.clone())));
        out.push((format!("{label}.depth"), Out::T(res.depth.clone())));
        out.push((
            format!("{label}.d/dsigmas"),
            grad(&g, &ps, "packed sigmas")?,
        ));
        out.push((
            format!("{label}.d/dcolors"),
            grad(&g, &pc, "packed colors")?,
        ));
    }
    out.push(("packed.n_samples".into(), Out::Eq(format!("{m}"))));

    // Distortion loss on the same intervals.
    let dl = distortion_loss(&w.weights, &iv)?;
    let g = dl.sum_all()?.backward()?;
    out.push(("distortion_loss".into(), Out::T(dl)));
    out.push((
        "distortion_loss.d/dsigmas".into(),
        grad(&g, &sig, "sigmas")?,
    ));
    Ok(out)
}

fn sampling_case(dev: &Device, dtype: DType) -> Result<Outs> {
    let r = 40;
    let mut rng = SplitMix64::new(21);
    let near_h = rng.uniform_tensor(&[r], 0.5, 1.5, dtype, &Device::Cpu)?;
    let far_h = (&near_h + rng.uniform_tensor(&[r], 1.0, 3.0, dtype, &Device::Cpu)?)?;
    let near = Var::from_tensor(&near_h.to_device(dev)?)?;
    let far = Var::from_tensor(&far_h.to_device(dev)?)?;
    let dirs = uniform(&mut rng, &[r, 3], -1.0, 1.0, dtype, dev)?;
    let rays = Rays::new(Tensor::zeros((r, 3), dtype, dev)?, dirs)?;
    let mut out: Outs = Vec::new();
    for (label, jitter) in [
        ("none", Jitter::None),
        ("per_sample", Jitter::PerSample),
        ("single", Jitter::SingleJitter),
    ] {
        let iv = stratified(&near, &far, 32, jitter, 9)?;
        let mut up = SplitMix64::new(3);
        let loss = (probe(&iv.starts, &mut up)? + probe(&iv.ends, &mut up)?)?;
        let g = loss.backward()?;
        out.push((
            format!("stratified.{label}.starts"),
            Out::T(iv.starts.clone()),
        ));
        out.push((format!("stratified.{label}.ends"), Out::T(iv.ends.clone())));
        out.push((
            format!("stratified.{label}.d/dnear"),
            grad(&g, &near, "near")?,
        ));
        out.push((format!("stratified.{label}.d/dfar"), grad(&g, &far, "far")?));
    }
    let iv = stratified(&near, &far, 32, Jitter::PerSample, 10)?;
    let mids = iv.midpoints()?;
    let deltas = iv.deltas(Some(&rays))?;
    out.push(("midpoints".into(), Out::T(mids.clone())));
    out.push(("deltas".into(), Out::T(deltas.clone())));
    // The bins of `sample_pdf` (0.1's `edges`): the starts and the last end.
    out.push(("intervals.starts".into(), Out::T(iv.starts.clone())));
    out.push(("intervals.ends".into(), Out::T(iv.ends.clone())));
    out.push(("positions".into(), Out::T(iv.positions(&rays)?)));
    let sig = rng
        .uniform_tensor(&[r, 32], -2.0, 8.0, dtype, &Device::Cpu)?
        .relu()?
        .to_device(dev)?;
    let w = render_weights(&sig, &iv, Some(&rays), &CompositeConfig::default())?
        .weights
        .detach();
    for (label, det) in [("deterministic", true), ("random", false)] {
        let fine = sample_pdf(&iv, &w, 48, det, 4, PDF_PADDING)?;
        out.push((format!("sample_pdf.{label}"), Out::T(fine.clone())));
        let merged = merge_sorted(&mids, &fine)?;
        out.push((format!("merge_sorted.{label}"), Out::T(merged.clone())));
        let iv2 = Intervals::from_samples(&merged, &near, &far)?;
        out.push((
            format!("from_samples.{label}.starts"),
            Out::T(iv2.starts.clone()),
        ));
        out.push((
            format!("from_samples.{label}.ends"),
            Out::T(iv2.ends.clone()),
        ));
    }
    let (n2, f2) = anneal_near_far(&near, &far, 10, 100, ANNEAL_P_START, ANNEAL_MID_RATIO)?;
    out.push(("anneal.near".into(), Out::T(n2)));
    out.push(("anneal.far".into(), Out::T(f2)));
    Ok(out)
}

// --- networks, encodings, fields ------------------------------------------------------

/// IDR-style SDF network (frequency encoding, skip, geometric init) and a conditioned
/// occupancy-style network with several outputs, seeded identically on every device.
fn mlp_configs() -> Result<(MlpConfig, MlpConfig)> {
    let sdf = MlpConfig {
        hidden: 32,
        depth: 4,
        skips: vec![2],
        encoding: PointEncoding::Frequency(FrequencyEncoding::new(3, 4)?),
        ..MlpConfig::sdf(0.5)
    };
    let cond = MlpConfig {
        out_dim: 4,
        code_dim: 2,
        hidden: 48,
        depth: 3,
        activation: Activation::Softplus { beta: 10.0 },
        ..MlpConfig::default()
    };
    Ok((sdf, cond))
}

fn sorted_vars(varmap: &VarMap) -> Vec<(String, Var)> {
    let data = varmap.data().lock().unwrap();
    let mut v: Vec<(String, Var)> = data.iter().map(|(k, v)| (k.clone(), v.clone())).collect();
    v.sort_by(|a, b| a.0.cmp(&b.0));
    v
}

fn mlp_case(dev: &Device, dtype: DType) -> Result<Outs> {
    let (sdf_cfg, cond_cfg) = mlp_configs()?;
    let mut rng = SplitMix64::new(31);
    let points = Var::from_tensor(&uniform(&mut rng, &[256, 3], -0.7, 0.7, dtype, dev)?)?;
    let mut out: Outs = Vec::new();

    // SDF network: value_and_grad, and a loss on the normals (eikonal) into the weights.
    let vm = VarMap::new();
    let net = build_seeded(&vm, dtype, dev, 42, |vb| mlp(&sdf_cfg, vb))?;
    for (name, var) in sorted_vars(&vm) {
        out.push((format!("sdf.init.{name}"), Out::T(var.as_tensor().clone())));
    }
    let (v, g) = net.value_and_grad(&points)?;
    out.push(("sdf.value".into(), Out::T(v.clone())));
    out.push(("sdf.grad".into(), Out::T(g.clone())));
    let eikonal = (g.sqr()?.sum(1)?.sqrt()? - 1.0)?.sqr()?.mean_all()?;
    let loss = (eikonal + v.sqr()?.mean_all()?)?;
    let grads = loss.backward()?;
    for (name, var) in sorted_vars(&vm) {
        out.push((
            format!("sdf.d(eikonal)/d{name}"),
            grad(&grads, &var, &name)?,
        ));
    }
    out.push((
        "sdf.d(eikonal)/dpoints".into(),
        grad(&grads, &points, "points")?,
    ));

    // Conditioned network: forward_with_jacobian over all outputs, gradients into the
    // weights and the codes.
    let vm = VarMap::new();
    let net = build_seeded(&vm, dtype, dev, 43, |vb| mlp(&cond_cfg, vb))?;
    let codes = Var::from_tensor(&uniform(&mut rng, &[256, 2], -1.0, 1.0, dtype, dev)?)?;
    let (y, j) = net.forward_with_jacobian(&points, Some(&codes))?;
    let mut up = SplitMix64::new(2);
    let grads = (probe(&y, &mut up)? + probe(&j, &mut up)?)?.backward()?;
    out.push(("cond.y".into(), Out::T(y)));
    out.push(("cond.jacobian".into(), Out::T(j)));
    for (name, var) in sorted_vars(&vm) {
        out.push((format!("cond.d/d{name}"), grad(&grads, &var, &name)?));
    }
    out.push(("cond.d/dcodes".into(), grad(&grads, &codes, "codes")?));
    Ok(out)
}

fn encoding_case(dev: &Device, dtype: DType) -> Result<Outs> {
    let mut rng = SplitMix64::new(41);
    let n = 128;
    let x = Var::from_tensor(&uniform(&mut rng, &[n, 3], -2.0, 2.0, dtype, dev)?)?;
    let eye = Tensor::eye(3, dtype, dev)?
        .unsqueeze(0)?
        .broadcast_as((n, 3, 3))?
        .contiguous()?;
    let mut out: Outs = Vec::new();
    let freq = FrequencyEncoding::new(3, 10)?;
    let fourier = FourierFeatures::new(3, 16, 10.0, 5, dev, dtype)?;
    let mut plain = FrequencyEncoding::new(3, 8)?;
    plain.use_pi = false;
    plain.include_input = false;
    let encs: [(&str, &dyn Encoding); 3] = [
        ("frequency", &freq),
        ("frequency_no_pi", &plain),
        ("fourier", &fourier),
    ];
    for (label, enc) in encs {
        let y = enc.forward(&x)?;
        let (y2, dy) = enc.forward_jvp(&x, &eye)?;
        let mut up = SplitMix64::new(1);
        let g = (probe(&y, &mut up)? + probe(&dy, &mut up)?)?.backward()?;
        out.push((format!("{label}.forward"), Out::T(y)));
        out.push((format!("{label}.jvp.value"), Out::T(y2)));
        out.push((format!("{label}.jvp.tangent"), Out::T(dy)));
        out.push((format!("{label}.d/dx"), grad(&g, &x, "x")?));
    }
    let var = uniform(&mut rng, &[n, 3], 0.0, 0.01, dtype, dev)?;
    let ipe = integrated_pe(&x, &var, 0, 8)?;
    let mut up = SplitMix64::new(1);
    let g = probe(&ipe, &mut up)?.backward()?;
    out.push(("integrated_pe".into(), Out::T(ipe)));
    out.push(("integrated_pe.d/dmeans".into(), grad(&g, &x, "means")?));
    Ok(out)
}

fn camera_case(dev: &Device, dtype: DType) -> Result<Outs> {
    let k = Intrinsics::from_fov_y(40, 30, 0.9)?;
    let cam = Camera::look_at(
        k,
        DVec3::new(0.3, 0.4, 3.0),
        DVec3::new(0.02, -0.01, 0.0),
        DVec3::Y,
        Convention::OpenGl,
    )?;
    let cv = Camera::look_at(
        k,
        DVec3::new(-2.0, 0.7, 1.9),
        DVec3::ZERO,
        DVec3::Z,
        Convention::OpenCv,
    )?;
    let rays = cam.rays(dev, dtype)?;
    let w = k.width;
    let picks: Vec<u32> = (0u32..100)
        .map(|i| (i * 37) % (w * k.height) as u32)
        .collect();
    let px: Vec<f64> = picks
        .iter()
        .flat_map(|&i| [(i as usize % w) as f64 + 0.5, (i as usize / w) as f64 + 0.5])
        .collect();
    let rr = cv.rays_for_pixels(&Tensor::from_vec(px, (100, 2), dev)?.to_dtype(dtype)?)?;
    let idx = Tensor::from_vec(picks, 100, dev)?;
    let mut out: Outs = vec![
        ("rays.origins".into(), Out::T(rays.origins().clone())),
        ("rays.directions".into(), Out::T(rays.directions().clone())),
        ("random_rays.origins".into(), Out::T(rr.origins().clone())),
        (
            "random_rays.directions".into(),
            Out::T(rr.directions().clone()),
        ),
        ("random_rays.pixels".into(), Out::T(idx)),
    ];
    // A learnable pose: gradients of the ray directions reach the quaternion.
    let pose = PoseParam::from_affine(&cv.cam_to_world(), dev, dtype)?;
    let pixels = cv.subpixel_grid(1, PixelFilter::Box, dev, dtype)?;
    let views = Tensor::zeros(pixels.dim(0)?, DType::U32, dev)?;
    let pr = pose_rays(std::slice::from_ref(&pose), &[cv], &views, &pixels)?;
    let mut up = SplitMix64::new(4);
    let g = probe(pr.directions(), &mut up)?.backward()?;
    out.push(("pose.directions".into(), Out::T(pr.directions().clone())));
    out.push((
        "pose.d/drotation".into(),
        grad(&g, &pose.rotation, "rotation")?,
    ));

    let o = Var::from_tensor(rays.origins())?;
    let d = Var::from_tensor(rays.directions())?;
    let vrays = Rays::new(o.as_tensor().clone(), d.as_tensor().clone())?;
    for (label, hit) in [
        (
            "ray_aabb",
            ray_aabb(&vrays, [-1.0, -0.8, -0.9], [1.0, 0.8, 0.9])?,
        ),
        ("ray_sphere", ray_sphere(&vrays, [0.1, 0.0, -0.1], 0.9)?),
    ] {
        let mut up = SplitMix64::new(5);
        let g = (probe(&hit.near, &mut up)? + probe(&hit.far, &mut up)?)?.backward()?;
        out.push((format!("{label}.near"), Out::T(hit.near.clone())));
        out.push((format!("{label}.far"), Out::T(hit.far.clone())));
        out.push((format!("{label}.hit"), Out::T(hit.hit.clone())));
        out.push((format!("{label}.d/dorigins"), grad(&g, &o, "origins")?));
        out.push((
            format!("{label}.d/ddirections"),
            grad(&g, &d, "directions")?,
        ));
    }
    Ok(out)
}

/// A sphere whose centre and radius are `Var`s on `dev` in `dtype` (built on the CPU in
/// f64 and converted, so both devices start from the same rounded values).
fn learnable_sphere(
    center: [f64; 3],
    radius: f64,
    dev: &Device,
    dtype: DType,
) -> Result<(Var, Var, Sphere)> {
    let var =
        |t: Tensor| -> Result<Var> { Ok(Var::from_tensor(&t.to_dtype(dtype)?.to_device(dev)?)?) };
    let center = var(Tensor::new(&center, &Device::Cpu)?)?;
    let radius = var(Tensor::new(radius, &Device::Cpu)?)?;
    let sphere = Sphere {
        center: center.as_tensor().clone(),
        radius: radius.as_tensor().clone(),
    };
    Ok((center, radius, sphere))
}

fn field_case(dev: &Device, dtype: DType) -> Result<Outs> {
    let mut rng = SplitMix64::new(51);
    let points = uniform(&mut rng, &[300, 3], -1.2, 1.2, dtype, dev)?;
    let (center, radius, sphere) = learnable_sphere([0.05, -0.1, 0.02], 0.7, dev, dtype)?;
    let mut out: Outs = Vec::new();
    let (d, g) = sphere.distance_and_grad(&points)?;
    let mut up = SplitMix64::new(6);
    let grads = (probe(&d, &mut up)? + probe(&g, &mut up)?)?.backward()?;
    out.push(("sphere.distance".into(), Out::T(d)));
    out.push(("sphere.grad".into(), Out::T(g)));
    out.push(("sphere.d/dcenter".into(), grad(&grads, &center, "center")?));
    out.push(("sphere.d/dradius".into(), grad(&grads, &radius, "radius")?));
    let shapes: Vec<(&str, Box<dyn ImplicitSurface>)> = vec![
        (
            "cuboid.sdf",
            Box::new(Cuboid::new([0.1, 0.0, -0.1], [0.5, 0.3, 0.4], dev, dtype)?.sdf()),
        ),
        (
            "torus.sdf",
            Box::new(Torus::new([0.0, 0.1, 0.0], 0.5, 0.2, dev, dtype)?.sdf()),
        ),
        (
            "torus.occupancy",
            Box::new(Torus::new([0.0, 0.1, 0.0], 0.5, 0.2, dev, dtype)?.occupancy(10.0)),
        ),
        (
            "plane.sdf",
            Box::new(Plane::new([0.3, -1.0, 0.2], 0.1, dev, dtype)?.sdf()),
        ),
    ];
    for (label, s) in shapes {
        let (v, g) = s.value_and_grad(&points)?;
        out.push((format!("{label}.value"), Out::T(v)));
        out.push((format!("{label}.grad"), Out::T(g)));
    }
    Ok(out)
}

// --- DVR ------------------------------------------------------------------------------

fn dvr_case(dev: &Device, dtype: DType) -> Result<Outs> {
    let depth_tol = |t: &Tensor| Out::Abs(t.clone(), 1e-5, 1e-10);
    let (center, radius, sphere) = learnable_sphere([0.05, -0.03, 0.02], 0.6, dev, dtype)?;
    let sdf = sphere.sdf();
    let k = Intrinsics::from_fov_y(32, 24, 0.8)?;
    let cam = Camera::look_at(
        k,
        DVec3::new(0.2, 0.3, 2.5),
        DVec3::ZERO,
        DVec3::Y,
        Convention::OpenGl,
    )?;
    let rays = cam.rays(dev, dtype)?;
    let o = Var::from_tensor(rays.origins())?;
    let d = Var::from_tensor(rays.directions())?;
    let rays = Rays::new(o.as_tensor().clone(), d.as_tensor().clone())?;
    let bounds = ray_sphere(
        &Rays::new(rays.origins().detach(), rays.directions().detach())?,
        [0.0; 3],
        1.0,
    )?;
    let mut out: Outs = Vec::new();

    // The march bounded by a sphere (0.1's `march_bounded`).
    let hits = march(&sdf, &rays, &bounds, &MarchConfig::default())?;
    out.push(("march_in_sphere.depth".into(), depth_tol(&hits.depth)));
    out.push((
        "march_in_sphere.points".into(),
        Out::Abs(hits.points.clone(), 1e-5, 1e-10),
    ));
    out.push((
        "march_in_sphere.status".into(),
        Out::Eq(format!("{:?}", hits.status)),
    ));
    out.push(("march_in_sphere.mask".into(), Out::T(hits.mask.clone())));
    out.push((
        "march_in_sphere.evaluations".into(),
        Out::Eq(format!("{}", hits.evaluations)),
    ));
    let surf = implicit_surface(&sdf, &rays, &hits, &ImplicitConfig::default())?;
    let mut up = SplitMix64::new(7);
    let g = (surf.depth.sum_all()? + probe(&surf.points, &mut up)?)?.backward()?;
    out.push(("implicit.indices".into(), Out::T(surf.indices.clone())));
    out.push(("implicit.depth".into(), depth_tol(&surf.depth)));
    out.push((
        "implicit.points".into(),
        Out::Abs(surf.points.clone(), 1e-5, 1e-10),
    ));
    out.push((
        "implicit.value".into(),
        Out::Abs(surf.value.clone(), 1e-5, 1e-10),
    ));
    out.push(("implicit.gradient".into(), Out::T(surf.gradient.clone())));
    out.push(("implicit.guarded".into(), Out::T(surf.guarded.clone())));
    out.push(("implicit.d/dradius".into(), grad(&g, &radius, "radius")?));
    out.push(("implicit.d/dcenter".into(), grad(&g, &center, "center")?));
    out.push(("implicit.d/dorigins".into(), grad(&g, &o, "origins")?));
    out.push(("implicit.d/ddirections".into(), grad(&g, &d, "directions")?));

    // Sphere tracing on the same rays over a fixed range.
    let r = rays.len();
    let near = Tensor::full(0.5f64, r, &Device::Cpu)?
        .to_dtype(dtype)?
        .to_device(dev)?;
    let far = Tensor::full(4.5f64, r, &Device::Cpu)?
        .to_dtype(dtype)?
        .to_device(dev)?;
    let range = Intersection::new(near, far)?;
    let st = sphere_trace(&sdf, &rays, &range, &SphereTraceConfig::default())?;
    out.push(("sphere_trace.depth".into(), depth_tol(&st.depth)));
    out.push((
        "sphere_trace.status".into(),
        Out::Eq(format!("{:?}", st.status)),
    ));

    mlp_dvr(&mut out, dev, dtype, "mlp.head_on", 0.15, [12, 10], None)?;
    mlp_dvr(
        &mut out,
        dev,
        dtype,
        "mlp.grazing",
        0.8,
        [24, 20],
        Some(1e-2),
    )?;
    Ok(out)
}

/// The SDF network of `mlp_case` (a sphere of radius 0.5 at initialisation) seen by a
/// camera with vertical field of view `fov_y` from distance 2.5: march, implicit surface
/// and the gradients of the depths into the weights.
///
/// With `fov_y = 0.15` every ray meets the surface at a steep angle (cosine ≥ 0.87) and
/// the gradients are compared at the usual tolerance. With a wide view some rays meet it
/// at a shallow angle (cosine down to 0.11); there the implicit gradient
/// `−(∂f/∂θ)/(∇f·w)` amplifies the difference of the two marches' f32 depths (a few
/// 1e-6, within the march tolerance) by up to `1/grazing_eps = 1e3`, so the f32 gradient
/// tolerance is `grad_tol_f32`. (An H100 gave 2.5e-5 for this 24×20 view but up to 4e-3
/// for a 32×24 one; f64 stays within 1e-10.)
fn mlp_dvr(
    out: &mut Outs,
    dev: &Device,
    dtype: DType,
    label: &str,
    fov_y: f64,
    [width, height]: [usize; 2],
    grad_tol_f32: Option<f64>,
) -> Result<()> {
    let depth_tol = |t: &Tensor| Out::Abs(t.clone(), 1e-5, 1e-10);
    let k = Intrinsics::from_fov_y(width, height, fov_y)?;
    let cam = Camera::look_at(
        k,
        DVec3::new(0.3, 0.2, 2.5),
        DVec3::new(0.01, 0.02, 0.0),
        DVec3::Y,
        Convention::OpenGl,
    )?;
    let rays = cam.rays(dev, dtype)?;
    let o = Var::from_tensor(rays.origins())?;
    let d = Var::from_tensor(rays.directions())?;
    let rays = Rays::new(o.as_tensor().clone(), d.as_tensor().clone())?;
    let r = rays.len();
    let near = Tensor::full(0.5f64, r, &Device::Cpu)?
        .to_dtype(dtype)?
        .to_device(dev)?;
    let far = Tensor::full(4.5f64, r, &Device::Cpu)?
        .to_dtype(dtype)?
        .to_device(dev)?;
    let (cfg, _) = mlp_configs()?;
    let vm = VarMap::new();
    let net = build_seeded(&vm, dtype, dev, 42, |vb| mlp(&cfg, vb))?;
    let range = Intersection::new(near, far)?;
    let hits = march(&net, &rays, &range, &MarchConfig::default())?;
    out.push((format!("{label}.march.depth"), depth_tol(&hits.depth)));
    out.push((
        format!("{label}.march.status"),
        Out::Eq(format!("{:?}", hits.status)),
    ));
    let surf = implicit_surface(&net, &rays, &hits, &ImplicitConfig::default())?;
    let g = surf.depth.sum_all()?.backward()?;
    out.push((format!("{label}.implicit.depth"), depth_tol(&surf.depth)));
    out.push((
        format!("{label}.implicit.guarded"),
        Out::T(surf.guarded.clone()),
    ));
    let gn = surf.gradient.sqr()?.sum(1)?.sqrt()?;
    let wn = d.as_tensor().index_select(&surf.indices, 0)?;
    let cos = ((&surf.gradient * &wn)?.sum(1)? / (gn * wn.sqr()?.sum(1)?.sqrt()?)?)?
        .abs()?
        .min(0)?;
    out.push((
        format!("{label}.implicit.min_cosine"),
        Out::Abs(cos, 1e-4, 1e-10),
    ));
    out.push((
        format!("{label}.implicit.gradient"),
        Out::T(surf.gradient.clone()),
    ));
    for (name, var) in sorted_vars(&vm) {
        let what = format!("{label}.implicit.d(depth)/d{name}");
        let gr = match (grad(&g, &var, &name)?, grad_tol_f32) {
            (Out::T(t), Some(tol)) => Out::Rel(t, tol, 1e-10),
            (o, _) => o,
        };
        out.push((what, gr));
    }
    Ok(())
}

// --- meshes ---------------------------------------------------------------------------

fn mesh_outs(out: &mut Outs, label: &str, mesh: &neural_fields::mesh::Mesh) {
    out.push((
        format!("{label}.vertices"),
        Out::Host(mesh.vertices.iter().flatten().copied().collect()),
    ));
    out.push((
        format!("{label}.faces"),
        Out::Eq(format!("{:?}", mesh.faces)),
    ));
    out.push((
        format!("{label}.watertight"),
        Out::Eq(format!(
            "{}",
            !mesh.faces.is_empty() && mesh.edge_report() == (0, 0, 0)
        )),
    ));
}

fn mesh_case(dev: &Device, dtype: DType) -> Result<Outs> {
    let mut out: Outs = Vec::new();
    let torus = Torus::new([0.0, 0.05, 0.0], 0.3, 0.1, dev, dtype)?.occupancy(10.0);
    let m = mise(
        &torus,
        &MiseConfig {
            resolution0: 8,
            upsampling_steps: 2,
            device: dev.clone(),
            dtype,
            ..MiseConfig::new(32, 2, &Device::Cpu, DType::F32)
        },
    )?;
    mesh_outs(&mut out, "mise.torus", &m.mesh);
    out.push((
        "mise.torus.evaluations".into(),
        Out::Eq(format!("{} {:?}", m.evaluations, m.active_per_level)),
    ));
    out.push((
        "mise.torus.grid".into(),
        Out::Host(m.grid.values.iter().map(|&v| f64::from(v)).collect()),
    ));

    let sdf = Torus::new([0.0, 0.05, 0.0], 0.3, 0.1, dev, dtype)?.sdf();
    let grid = Grid::sample(&sdf, [21, 19, 17], [-0.55; 3], [0.55; 3], 1000, dev, dtype)?;
    out.push((
        "grid.torus.values".into(),
        Out::Host(grid.values.iter().map(|&v| f64::from(v)).collect()),
    ));
    mesh_outs(
        &mut out,
        "grid.torus.marching_cubes",
        &marching_cubes(&grid, 0.0, Inside::Negative)?,
    );

    let (cfg, _) = mlp_configs()?;
    let vm = VarMap::new();
    let net = build_seeded(&vm, dtype, dev, 42, |vb| mlp(&cfg, vb))?;
    let m = mise(
        &net,
        &MiseConfig {
            resolution0: 8,
            upsampling_steps: 1,
            device: dev.clone(),
            dtype,
            ..MiseConfig::new(32, 2, &Device::Cpu, DType::F32)
        },
    )?;
    mesh_outs(&mut out, "mise.mlp", &m.mesh);
    out.push((
        "mise.mlp.evaluations".into(),
        Out::Eq(format!("{} {:?}", m.evaluations, m.active_per_level)),
    ));
    Ok(out)
}

#[test]
fn cuda_volume_composite_and_render_weights() {
    check("composite", composite_case);
}

#[test]
fn cuda_volume_sampling() {
    check("sampling", sampling_case);
}

#[test]
fn cuda_mlp_value_grad_and_normal_loss_gradients() {
    check("mlp", mlp_case);
}

#[test]
fn cuda_encodings() {
    check("encoding", encoding_case);
}

#[test]
fn cuda_camera_rays_and_intersections() {
    check("camera", camera_case);
}

#[test]
fn cuda_analytic_fields() {
    check("field", field_case);
}

#[test]
fn cuda_dvr_march_and_implicit_surface() {
    check("dvr", dvr_case);
}

#[test]
fn cuda_mise_and_marching_cubes() {
    check("mesh", mesh_case);
}
