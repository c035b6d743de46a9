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
use neural_fields::occupancy::{
    marching_cubes, mise, onet_decoder, Grid, MiseConfig, NormMode, OnetConfig,
};
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

// --- fused kernels ----------------------------------------------------------------------
//
// The crate's CUDA kernels against its CPU kernels on the same inputs, at a relative
// 1e-5 (f32) / 1e-10 (f64); the stiff inputs are the ones the CPU kernels' own tests
// sweep. (Run the binary a second time with `NEURAL_FIELDS_CUDA_KERNELS=0` and the same
// cases compare the candle-op reference paths on CUDA with the CPU kernels.)

/// Whether the CUDA kernels run (`NEURAL_FIELDS_CUDA_KERNELS` is not `0`); else the
/// CUDA side of every case is the candle-op reference path.
fn kernels_on() -> bool {
    std::env::var("NEURAL_FIELDS_CUDA_KERNELS").map_or(true, |v| v != "0")
}

/// A kernel output: relative 1e-5 (f32) / 1e-10 (f64); the reference paths' 1e-4 in f32
/// when the kernels are off.
fn k(t: Tensor) -> Out {
    Out::Rel(t, if kernels_on() { 1e-5 } else { 1e-4 }, 1e-10)
}

/// Whether a call failed, as a comparable output.
fn failed<T>(r: Result<T>) -> Out {
    Out::Eq(if r.is_err() { "Err" } else { "Ok" }.into())
}

fn kernels_case(dev: &Device, dtype: DType) -> Result<Outs> {
    let mut rng = SplitMix64::new(71);
    let cpu = Device::Cpu;
    let mut out: Outs = Vec::new();

    // Activations over ordinary and extreme arguments (both sides of every clamp).
    let mut xs: Vec<f64> = (0..200).map(|i| -10.0 + 0.1 * i as f64).collect();
    xs.extend([
        -1e4, -800.0, -100.0, -15.5, -15.0, 15.0, 15.5, 80.0, 87.9, 88.0, 88.5, 700.0, 708.9,
        709.0, 709.5, 1e4, 0.0, -0.0, 1e-30, -1e-30,
    ]);
    let x = Var::from_tensor(
        &Tensor::new(xs.as_slice(), &cpu)?
            .to_dtype(dtype)?
            .to_device(dev)?,
    )?;
    for (label, y) in [
        ("softplus_b1", neural_fields::numerics::softplus(&x, 1.0)?),
        (
            "softplus_b100",
            neural_fields::numerics::softplus(&x, 100.0)?,
        ),
        ("trunc_exp", neural_fields::numerics::trunc_exp(&x)?),
    ] {
        let mut up = SplitMix64::new(3);
        let g = probe(&y, &mut up)?.backward()?;
        out.push((label.to_string(), k(y)));
        out.push((format!("{label}.d/dx"), grad(&g, &x, "x")?));
    }
    let empty = Tensor::zeros(0, dtype, dev)?;
    out.push((
        "trunc_exp.empty".into(),
        Out::Eq(format!(
            "{:?}",
            neural_fields::numerics::trunc_exp(&empty)?.dims()
        )),
    ));

    // Encodings on large arguments (|2ᵏπx| up to 2⁹·π·300) and an empty batch.
    let xe = Var::from_tensor(&uniform(&mut rng, &[64, 3], -300.0, 300.0, dtype, dev)?)?;
    let freq = FrequencyEncoding::new(3, 10)?;
    let y = freq.forward(&xe)?;
    let g = probe(&y, &mut SplitMix64::new(4))?.backward()?;
    out.push(("frequency.large".into(), k(y)));
    out.push(("frequency.large.d/dx".into(), grad(&g, &xe, "x")?));
    let none = Tensor::zeros((0, 3), dtype, dev)?;
    out.push((
        "frequency.empty".into(),
        Out::Eq(format!("{:?}", freq.forward(&none)?.dims())),
    ));
    let var = Var::from_tensor(&uniform(&mut rng, &[64, 3], 0.0, 4.0, dtype, dev)?)?;
    let ipe = integrated_pe(&xe, &var, 0, 16)?;
    let g = probe(&ipe, &mut SplitMix64::new(5))?.backward()?;
    out.push(("integrated_pe.large".into(), k(ipe)));
    out.push(("integrated_pe.d/dmeans".into(), grad(&g, &xe, "means")?));
    out.push((
        "integrated_pe.d/dvariances".into(),
        grad(&g, &var, "variances")?,
    ));

    // Compositing with constant intervals (the op forms δ and t per ray), with and
    // without non-unit directions, batched and packed, opaque last or not; densities
    // from 0 to 1e30 and zero-length intervals.
    let (r, s) = (33, 37);
    let mut sig_h = v64(&rng
        .uniform_tensor(&[r, s], -2.0, 8.0, DType::F64, &cpu)?
        .relu()?);
    for (i, v) in [1e30, 1e-30, 5e3, 0.0, 1e6].iter().enumerate() {
        sig_h[i * 7 + 3] = *v;
    }
    let sig = Var::from_tensor(
        &Tensor::from_vec(sig_h, (r, s), &cpu)?
            .to_dtype(dtype)?
            .to_device(dev)?,
    )?;
    let mut del_h = v64(&rng.uniform_tensor(&[r, s], 0.0, 0.1, DType::F64, &cpu)?);
    del_h[5] = 0.0;
    del_h[s + 2] = 0.0;
    let (st_h, en_h) = common::intervals::starts_ends(&del_h, &vec![s; r]);
    let host = |v: Vec<f64>| -> Result<Tensor> {
        Ok(Tensor::from_vec(v, (r, s), &cpu)?
            .affine(1.0, 2.0)?
            .to_dtype(dtype)?
            .to_device(dev)?)
    };
    let iv = Intervals::new(host(st_h)?, host(en_h)?, Layout::Batched)?;
    let col = Var::from_tensor(&uniform(&mut rng, &[r, s, 3], 0.0, 1.0, dtype, dev)?)?;
    let dirs_h = uniform(&mut rng, &[r, 3], 0.3, 1.1, dtype, dev)?;
    let rays = Rays::new(Tensor::zeros((r, 3), dtype, dev)?, dirs_h.clone())?;
    let dirs = Var::from_tensor(&dirs_h)?;
    let rays_var = Rays::new(Tensor::zeros((r, 3), dtype, dev)?, dirs.as_tensor().clone())?;
    for opaque_last in [false, true] {
        let cfg = CompositeConfig {
            opaque_last,
            ..CompositeConfig::default()
        };
        for (label, rays) in [
            ("unit", None),
            ("norms", Some(&rays)),
            ("direction_graph", Some(&rays_var)),
        ] {
            let label = format!("composite.constant.{label}.opaque_last={opaque_last}");
            let res = composite(&sig, &col, &iv, rays, &cfg)?;
            let mut up = SplitMix64::new(8);
            let loss = ((probe(&res.color, &mut up)? + probe(&res.opacity, &mut up)?)?
                + probe(&res.depth, &mut up)?)?;
            let g = loss.backward()?;
            out.push((format!("{label}.color"), k(res.color)));
            out.push((format!("{label}.opacity"), k(res.opacity)));
            out.push((format!("{label}.depth"), k(res.depth)));
            out.push((format!("{label}.d/dsigmas"), grad(&g, &sig, "sigmas")?));
            out.push((format!("{label}.d/dcolors"), grad(&g, &col, "colors")?));
            if rays.is_some_and(|r| r.directions().track_op()) {
                out.push((
                    format!("{label}.d/ddirections"),
                    grad(&g, &dirs, "directions")?,
                ));
            }
        }
    }
    // Packed with empty rays: every third ray keeps no sample.
    let keep: Vec<u8> = (0..r * s)
        .map(|i| u8::from((i / s) % 3 != 0 && i % 2 == 0))
        .collect();
    let mask = Tensor::from_vec(keep, (r, s), &cpu)?.to_device(dev)?;
    let (kept, idx) = iv.retain(&mask)?;
    let ps = Var::from_tensor(&sig.as_tensor().flatten_all()?.index_select(&idx, 0)?)?;
    let pc = Var::from_tensor(&col.as_tensor().reshape((r * s, 3))?.index_select(&idx, 0)?)?;
    let res = composite(
        &ps,
        &pc,
        &kept,
        None,
        &CompositeConfig {
            opaque_last: true,
            ..CompositeConfig::default()
        },
    )?;
    let mut up = SplitMix64::new(9);
    let g = ((probe(&res.color, &mut up)? + probe(&res.opacity, &mut up)?)?
        + probe(&res.depth, &mut up)?)?
    .backward()?;
    out.push(("composite.packed.color".into(), k(res.color)));
    out.push(("composite.packed.opacity".into(), k(res.opacity)));
    out.push(("composite.packed.depth".into(), k(res.depth)));
    out.push((
        "composite.packed.d/dsigmas".into(),
        grad(&g, &ps, "sigmas")?,
    ));
    out.push((
        "composite.packed.d/dcolors".into(),
        grad(&g, &pc, "colors")?,
    ));
    // A batch whose rays all miss the grid's box: no interval on the CPU, one
    // zero-length interval on CUDA (candle cannot allocate an empty result there); the
    // composite is the background either way. The NeRF example on a tight box stopped
    // with CUDA_ERROR_INVALID_VALUE on such batches.
    let grid = neural_fields::volume::OccupancyGrid::new(neural_fields::volume::GridConfig {
        resolution: 8,
        ..Default::default()
    })?;
    let host = |v: &[[f64; 3]]| -> Result<Tensor> {
        Ok(Tensor::from_vec(v.concat(), (v.len(), 3), &cpu)?
            .to_dtype(dtype)?
            .to_device(dev)?)
    };
    let away = Rays::new(
        host(&[[0.0, 0.0, 5.0], [0.0, 0.0, -5.0]])?,
        host(&[[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]])?,
    )?;
    let mut field = |p: &Tensor| -> Result<Tensor> { Ok(p.sum(1)?.ones_like()?) };
    let march = neural_fields::volume::GridMarchConfig::default();
    let miss = grid.sample(&away, &march, Some(&mut field))?.intervals;
    let n = miss.starts.dim(0)?;
    out.push((
        "empty_batch.samples at most 1".into(),
        Out::Eq((n <= 1).to_string()),
    ));
    let res = composite(
        &Tensor::ones(n, dtype, dev)?,
        &Tensor::ones((n, 3), dtype, dev)?,
        &miss,
        Some(&away),
        &CompositeConfig {
            background: Some(host(&[[0.2, 0.4, 0.6]])?.squeeze(0)?),
            ..CompositeConfig::default()
        },
    )?;
    out.push(("empty_batch.color".into(), k(res.color)));
    out.push(("empty_batch.opacity".into(), k(res.opacity)));
    // A NaN or negative density is refused on both devices.
    for (label, bad) in [
        ("nan", f64::NAN),
        ("negative", -1.0),
        ("inf", f64::INFINITY),
    ] {
        let mut h = v64(sig.as_tensor());
        h[17] = bad;
        let b = Tensor::from_vec(h, (r, s), &cpu)?
            .to_dtype(dtype)?
            .to_device(dev)?;
        out.push((
            format!("composite.refuses_{label}_density"),
            failed(composite(
                &b,
                col.as_tensor(),
                &iv,
                None,
                &CompositeConfig::default(),
            )),
        ));
    }
    Ok(out)
}

/// NeRF's colour loss: the fused loss op on both devices (on CUDA its kernels and cuBLAS
/// products), at the defaults and with a skip connection, a softplus density, no view
/// dependence and an opaque last interval on packed samples; and the composed path
/// (`force_reference`) on both. The loss, the mean opacity and every parameter gradient.
fn nerf_loss_case(dev: &Device, dtype: DType) -> Result<Outs> {
    use neural_fields::volume::{nerf, DensityActivation, NerfConfig};
    let mut rng = SplitMix64::new(81);
    let r = 64;
    let shift = |t: Tensor, z: f64| -> Result<Tensor> {
        let o = Tensor::new(&[0.0, 0.0, z], &Device::Cpu)?
            .to_dtype(dtype)?
            .to_device(dev)?;
        Ok(t.broadcast_add(&o.unsqueeze(0)?)?)
    };
    let origins = shift(uniform(&mut rng, &[r, 3], -0.2, 0.2, dtype, dev)?, -3.0)?;
    let dirs = shift(uniform(&mut rng, &[r, 3], -0.3, 0.3, dtype, dev)?, 1.0)?;
    let rays = Rays::new(origins, dirs)?;
    let full = |v: f64| -> Result<Tensor> {
        Ok(Tensor::full(v, r, &Device::Cpu)?
            .to_dtype(dtype)?
            .to_device(dev)?)
    };
    let iv = stratified(&full(2.0)?, &full(4.5)?, 48, Jitter::None, 0)?;
    // Packed: a ray-dependent number of the batched samples (some rays keep none).
    let keep: Vec<u8> = (0..r * 48)
        .map(|i| u8::from((i % 48) < (i / 48) % 7 * 7))
        .collect();
    let mask = Tensor::from_vec(keep, (r, 48), &Device::Cpu)?.to_device(dev)?;
    let (packed, _) = iv.retain(&mask)?;
    let target = uniform(&mut rng, &[r, 3], 0.0, 1.0, dtype, dev)?;
    let variant = NerfConfig {
        skips: vec![2],
        density: DensityActivation::Softplus { shift: -0.5 },
        direction_encoding: None,
        ..NerfConfig::default()
    };
    let reference = NerfConfig {
        force_reference: true,
        ..NerfConfig::default()
    };
    let mut out: Outs = Vec::new();
    for (label, config, intervals, opaque_last) in [
        ("default", NerfConfig::default(), &iv, false),
        ("skip_softplus_packed", variant, &packed, true),
        ("composed", reference, &iv, false),
    ] {
        let vm = VarMap::new();
        let net = build_seeded(&vm, dtype, dev, 5, |vb| nerf(&config, vb))?;
        let cfg = CompositeConfig {
            opaque_last,
            ..CompositeConfig::default()
        };
        let res = net.color_loss(&rays, intervals, &target, &cfg)?;
        let g = res.loss.backward()?;
        out.push((
            format!("{label}.loss"),
            Out::Rel(res.loss.clone(), 1e-5, 1e-10),
        ));
        out.push((
            format!("{label}.opacity_mean"),
            Out::Host(vec![res.opacity_mean]),
        ));
        for (name, var) in sorted_vars(&vm) {
            out.push((
                format!("{label}.d/d{name}"),
                Out::Rel(grad_t(&g, &var, &name)?, 1e-4, 1e-9),
            ));
        }
    }
    Ok(out)
}

/// The hash grid, `grid_sample` and scatter-max: values and the gradients of every
/// differentiable input, on points that include the box's faces and points outside it.
/// The crate's Adam on both devices: 10 steps over three variables (one without a
/// gradient at odd steps), gradients ordinary, zero, tiny (1e-30) and huge (1e18 f32 /
/// 1e30 f64), weight decay on, a learning-rate change at step 6.
fn adam_case(dev: &Device, dtype: DType) -> Result<Outs> {
    use candle_nn::{Optimizer, ParamsAdamW};
    let mut rng = SplitMix64::new(83);
    let vars: Vec<Var> = [(7usize, 3usize), (64, 64), (1, 1)]
        .iter()
        .map(|&(a, b)| {
            Ok(Var::from_tensor(&uniform(
                &mut rng,
                &[a, b],
                -1.0,
                1.0,
                dtype,
                dev,
            )?)?)
        })
        .collect::<Result<_>>()?;
    let params = ParamsAdamW {
        lr: 1e-2,
        weight_decay: 0.01,
        ..ParamsAdamW::default()
    };
    let mut opt = neural_fields::nn::Adam::new(vars.clone(), params)?;
    let big = if dtype == DType::F32 { 1e18 } else { 1e30 };
    for k in 0..10 {
        if k == 6 {
            opt.set_learning_rate(5e-3);
        }
        let mut terms = Vec::new();
        for (i, v) in vars.iter().enumerate() {
            if i == 2 && k % 2 == 1 {
                continue;
            }
            let n = v.elem_count();
            let g: Vec<f64> = (0..n)
                .map(|j| {
                    let u = 2.0 * rng.uniform() - 1.0;
                    match (j + k) % 5 {
                        0 if k >= 2 => 0.0,
                        1 if k >= 2 => u * 1e-30,
                        2 if k >= 4 => u * big,
                        _ => u,
                    }
                })
                .collect();
            let g = Tensor::from_vec(g, v.shape(), &Device::Cpu)?
                .to_dtype(dtype)?
                .to_device(dev)?;
            terms.push((v.as_tensor() * g)?.sum_all()?);
        }
        opt.step(&Tensor::stack(&terms, 0)?.sum_all()?.backward()?)?;
    }
    Ok(vars
        .iter()
        .enumerate()
        .map(|(i, v)| (format!("variable {i}"), k(v.as_tensor().clone())))
        .collect())
}

fn grid_kernels_case(dev: &Device, dtype: DType) -> Result<Outs> {
    use neural_fields::encoding::{
        cell_index, grid_sample, hash_grid, scatter, GridSampleConfig, HashGridConfig, Pooling,
        ScatterConfig,
    };
    let mut rng = SplitMix64::new(91);
    let cpu = Device::Cpu;
    let mut out: Outs = Vec::new();

    // Hash grid: dense coarse levels and hashed fine ones (tables of 2¹² rows).
    let config = HashGridConfig {
        levels: 8,
        log2_table_size: 12,
        finest_resolution: 256.0,
        init_scale: 0.5,
        ..HashGridConfig::default()
    };
    let vm = VarMap::new();
    let grid = build_seeded(&vm, dtype, dev, 3, |vb| hash_grid(&config, vb))?;
    let mut ph = v64(&rng.uniform_tensor(&[500, 3], -1.2, 1.2, DType::F64, &cpu)?);
    ph[..9].copy_from_slice(&[-1.0, -1.0, -1.0, 1.0, 1.0, 1.0, 0.0, 0.0, 0.0]);
    let p = Var::from_tensor(
        &Tensor::from_vec(ph, (500, 3), &cpu)?
            .to_dtype(dtype)?
            .to_device(dev)?,
    )?;
    let y = grid.forward(&p)?;
    let g = probe(&y, &mut SplitMix64::new(10))?.backward()?;
    out.push(("hash_grid".into(), k(y)));
    for (name, var) in sorted_vars(&vm) {
        out.push((format!("hash_grid.d/d{name}"), k(grad_t(&g, &var, &name)?)));
    }
    if let Some(gp) = g.get(&p) {
        // The reference path forms the weights u − ⌊u⌋ from u = t·N in f32 (N up to 256:
        // 8 bits fewer), and the position gradient scales them by N: 5e-3 in f32 there.
        let tol = if kernels_on() { 1e-4 } else { 5e-3 };
        out.push((
            "hash_grid.d/dpoints".into(),
            Out::Rel(gp.clone(), tol, 1e-9),
        ));
    }

    // The deterministic table gradient (fixed point on CUDA): the CPU's gradient within
    // the kernels' tolerance, and the same bits when run again. 20 000 points, so that
    // many atomics meet on the coarse levels' entries.
    let det = HashGridConfig {
        deterministic: true,
        ..config.clone()
    };
    let vm = VarMap::new();
    let grid = build_seeded(&vm, dtype, dev, 3, |vb| hash_grid(&det, vb))?;
    let pts = uniform(&mut rng, &[20_000, 3], -1.0, 1.0, dtype, dev)?;
    let table_grad = || -> Result<Tensor> {
        let y = grid.forward(&pts)?;
        let g = probe(&y, &mut SplitMix64::new(13))?.backward()?;
        let (name, var) = sorted_vars(&vm)
            .into_iter()
            .next()
            .ok_or_else(|| candle_core::Error::Msg("no hash table".into()))?;
        Ok(grad_t(&g, &var, &name)?.to_dtype(DType::F64)?)
    };
    let (first, second) = (table_grad()?, table_grad()?);
    let same = (first.to_device(&cpu)?.flatten_all()?.to_vec1::<f64>()?)
        .iter()
        .zip(second.to_device(&cpu)?.flatten_all()?.to_vec1::<f64>()?)
        .all(|(a, b)| a.to_bits() == b.to_bits());
    out.push((
        "hash_grid.deterministic.d/dtable".into(),
        k(first.to_dtype(dtype)?),
    ));
    out.push((
        "hash_grid.deterministic.repeats bit for bit".into(),
        Out::Eq(same.to_string()),
    ));

    // grid_sample on planes and volumes, coordinates inside, on and outside [0, 1].
    for (label, shape, k_dim) in [
        ("planes", vec![2usize, 5, 9, 7], 2usize),
        ("volume", vec![2, 4, 6, 5, 7], 3),
    ] {
        let f = Var::from_tensor(&uniform(&mut rng, &shape, -1.0, 1.0, dtype, dev)?)?;
        let c = Var::from_tensor(&uniform(&mut rng, &[2, 300, k_dim], -0.1, 1.1, dtype, dev)?)?;
        let y = grid_sample(&f, &c, &GridSampleConfig::default())?;
        let g = probe(&y, &mut SplitMix64::new(11))?.backward()?;
        out.push((format!("grid_sample.{label}"), k(y)));
        out.push((
            format!("grid_sample.{label}.d/dfeatures"),
            k(grad_t(&g, &f, "features")?),
        ));
        if let Some(gc) = g.get(&c) {
            out.push((
                format!("grid_sample.{label}.d/dcoords"),
                Out::Rel(gc.clone(), 1e-4, 1e-9),
            ));
        }
    }

    // Scatter-max of point features into a 4³ grid (empty cells included).
    let coords = uniform(&mut rng, &[2, 200, 3], 0.0, 1.0, dtype, dev)?;
    let index = cell_index(&coords, 4)?;
    // Multiples of 1/4 in [−1, 1]: many ties within a cell (the lowest point wins).
    let values = (uniform(&mut rng, &[2, 200, 6], -1.0, 1.0, dtype, dev)? * 4.0)?.round()?;
    let values = Var::from_tensor(&(values / 4.0)?)?;
    let max = ScatterConfig {
        pooling: Pooling::Max,
        force_reference: false,
    };
    let y = scatter(&values, &index, 64, &max)?;
    let g = probe(&y, &mut SplitMix64::new(12))?.backward()?;
    out.push(("scatter_max".into(), k(y)));
    out.push((
        "scatter_max.d/dvalues".into(),
        k(grad_t(&g, &values, "values")?),
    ));
    Ok(out)
}

/// The gradient tensor of `var` in `grads`.
/// The ONet decoder's training pass: on the CPU its conditional batch norms run as the
/// fused op, on CUDA as candle's ops. Logits, the gradients of every variable, the points
/// and the codes, and (through inference-mode logits) the running statistics, with one
/// code per shape over groups that straddle the CPU op's row tiles. Tolerance: the CPU op
/// keeps its statistics in f64, candle's ops in the dtype, so f32 is compared at 1e-3
/// (f64 at 1e-10) relative to the largest entry of the logits, and every gradient relative
/// to the largest gradient entry of all (a bias that feeds a normalisation has a gradient
/// that is zero up to round-off).
fn onet_case(dev: &Device, dtype: DType) -> Result<Outs> {
    let config = OnetConfig {
        hidden: 32,
        blocks: 2,
        code_dim: 8,
        ..OnetConfig::default()
    };
    let vm = VarMap::new();
    let net = build_seeded(&vm, dtype, dev, 3, |vb| onet_decoder(&config, vb))?;
    let mut rng = SplitMix64::new(4);
    // Scales and shifts away from their (1, 0) start, so every code moves them.
    for (_, var) in sorted_vars(&vm) {
        let t = var.as_tensor();
        let noise = uniform(&mut rng, t.dims(), -0.5, 0.5, dtype, dev)?;
        var.set(&(t + noise)?)?;
    }
    let (b, q) = (3, 301);
    let points = Var::from_tensor(&uniform(&mut rng, &[b, q, 3], -0.5, 0.5, dtype, dev)?)?;
    let codes = Var::from_tensor(&uniform(&mut rng, &[b, 8], -1.0, 1.0, dtype, dev)?)?;
    net.set_mode(NormMode::Train);
    let logits = net.logits(&points, &codes)?;
    let grads = probe(&logits, &mut SplitMix64::new(7))?.backward()?;
    let largest = |t: &Tensor| -> Result<f64> {
        Ok(t.abs()?
            .flatten_all()?
            .max(0)?
            .to_dtype(DType::F64)?
            .to_scalar::<f64>()?)
    };
    let mut named: Vec<(String, Tensor)> = sorted_vars(&vm)
        .iter()
        .chain(
            [
                ("points".to_string(), points.clone()),
                ("codes".to_string(), codes.clone()),
            ]
            .iter(),
        )
        .map(|(name, var)| Ok((format!("d/d{name}"), grad_t(&grads, var, name)?)))
        .collect::<Result<_>>()?;
    // One scale for every gradient: the biases that feed a normalisation have gradients
    // that are zero up to round-off, compared against the largest gradient of all.
    let mut top = 0f64;
    for (_, g) in &named {
        top = top.max(largest(g)?);
    }
    let rel = |t: Tensor, scale: f64| -> Result<Out> {
        Ok(Out::Rel((t / scale.max(1e-30))?, 1e-3, 1e-10))
    };
    let scale = largest(&logits)?;
    let mut out: Outs = vec![("logits".into(), rel(logits, scale)?)];
    for (what, g) in named.drain(..) {
        out.push((what, rel(g, top)?));
    }
    net.set_mode(NormMode::Eval);
    let inference = net.logits(&points, &codes)?;
    let scale = largest(&inference)?;
    out.push((
        "inference logits (running statistics)".into(),
        rel(inference, scale)?,
    ));
    Ok(out)
}

fn grad_t(grads: &candle_core::backprop::GradStore, var: &Var, what: &str) -> Result<Tensor> {
    grads.get(var).cloned().ok_or_else(|| {
        candle_core::Error::Msg(format!("grads: expected a gradient for {what}, got none")).into()
    })
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

#[test]
fn cuda_fused_kernels_match_the_cpu_kernels() {
    check("kernels", kernels_case);
}

#[test]
fn cuda_nerf_color_loss_and_parameter_gradients() {
    check("nerf_loss", nerf_loss_case);
}

#[test]
fn cuda_adam_matches_the_cpu() {
    check("adam", adam_case);
}

#[test]
fn cuda_hash_grid_grid_sample_and_scatter_kernels() {
    check("grid_kernels", grid_kernels_case);
}

#[test]
fn cuda_onet_decoder_training_pass_matches_the_cpu_fused_norm() {
    check("onet", onet_case);
}
