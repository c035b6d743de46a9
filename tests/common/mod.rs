//! Helpers shared by the integration tests: tensor extraction, seeded parameters and
//! central finite differences with kink detection.
#![allow(dead_code)]

pub mod counting;
#[cfg(feature = "data")]
pub mod datasets;
#[cfg(feature = "dvr")]
pub mod hits;
pub mod host;
#[cfg(feature = "volume")]
pub mod intervals;
pub mod stiff;

use candle_core::{DType, Device, Tensor, Var};
use candle_nn::VarMap;
#[allow(unused_imports)] // not every test binary uses it
pub use host::v64;
use neural_fields::rng::SplitMix64;

/// A tensor of i.i.d. `N(mean, std²)` numbers drawn from `rng` (`SplitMix64::normal`),
/// with the given shape, dtype and device.
pub fn normal_tensor(
    rng: &mut SplitMix64,
    shape: &[usize],
    mean: f64,
    std: f64,
    dtype: DType,
    device: &Device,
) -> candle_core::Result<Tensor> {
    let n = shape.iter().product();
    let v: Vec<f64> = (0..n).map(|_| mean + std * rng.normal()).collect();
    Tensor::from_vec(v, shape, &Device::Cpu)?
        .to_dtype(dtype)?
        .to_device(device)
}

/// A `[rows, cols]` tensor of uniform numbers in `[lo, hi)`.
pub fn uniform(
    rng: &mut SplitMix64,
    rows: usize,
    cols: usize,
    lo: f64,
    hi: f64,
    dtype: DType,
) -> Tensor {
    rng.uniform_tensor(&[rows, cols], lo, hi, dtype, &Device::Cpu)
        .unwrap()
}

/// Overwrites every variable of `varmap` with seeded normal values: weights `[out, in]`
/// with std `gain·√(2/in)`, biases with std 0.3. Deterministic in `seed`.
pub fn reseed(varmap: &VarMap, seed: u64, gain: f64) {
    let data = varmap.data().lock().unwrap();
    let mut names: Vec<&String> = data.keys().collect();
    names.sort();
    let mut rng = SplitMix64::new(seed);
    for name in names {
        let var = &data[name];
        let dims = var.dims().to_vec();
        let std = if dims.len() == 2 {
            gain * (2.0 / dims[1] as f64).sqrt()
        } else {
            0.3
        };
        let t = normal_tensor(&mut rng, &dims, 0.0, std, var.dtype(), var.device()).unwrap();
        var.set(&t).unwrap();
    }
}

/// Central difference of a scalar function along one coordinate, Richardson-extrapolated
/// (`(4·D(h/2) − D(h))/3`, error O(h⁴)), with two smoothness checks that return `None`
/// when the stencil crossed a kink (e.g. a ReLU boundary), where finite differences say
/// nothing about the derivative:
/// 1. the one-sided differences disagree by more than `1e-3·(|D(h)| + scale)` (a large
///    slope jump anywhere in `[x − h, x + h]`);
/// 2. the extrapolations from `(h, h/2)` and from `(h/2, h/4)` disagree by more than
///    `1e-8·(|D| + scale)` plus their round-off. For a smooth function both are exact
///    to O(h⁴); a kink at offset `a` from `x` with slope jump `δ` separates them by
///    `(7/6)·δ·|a|/h`, so a small jump that passes check 1 is still caught (the CI
///    failure `relu_kink_inside_the_stencil` in tests/mlp.rs: a 2e-4 relative error).
///
/// Neither check sees a kink much closer to `x` than `h` (check 2 sees `(7/6)·δ·|a|/h` of
/// its `δ/2` bias): [`central_diff_bound`]'s error bar covers those.
pub fn central_diff(f: &mut dyn FnMut(f64) -> f64, x: f64, h: f64, scale: f64) -> Option<f64> {
    central_diff_bound(f, x, h, scale).map(|(d, _)| d)
}

/// [`central_diff`] with the estimate's own error bar: `|coarse − fine|` (the two
/// extrapolations' disagreement, which bounds the O(h⁴) term) plus the scaled second
/// differences' `C(k) = (f(x+k) − 2f(x) + f(x−k))/k` departures from proportionality,
/// `|C(h/2) − C(h)/2| + |C(h/4) − C(h/2)/2|` (O(h³) for a smooth function; a kink at
/// `|a| ≪ h` with slope jump `δ` gives about `δ`, and with the first term they bound its
/// bias wherever it lies in the stencil: the worst case over the offset needs half of
/// them), plus the round-off of the seven evaluations. The failure this pins:
/// `fused_loss_gradients_match_finite_differences` in tests/nerf_color_loss.rs at seed
/// 7934692064343667385, a kink about 1e-7 from `x` that gave a 1.4e-5 relative error
/// against a bar of 4e-9. A gradient far below the loss's
/// magnitude is resolved no better than that bar, so a comparison at an absolute floor
/// smaller than it adds the bar (the CI failure `texture_decoder_gradients_match_finite_
/// differences`: a 4.09e-9 gradient of a loss of 1.8 beside a ReLU kink at 5e-5, where
/// the h = 1e-4 stencil read 3.89e-9 and passed both checks).
pub fn central_diff_bound(
    f: &mut dyn FnMut(f64) -> f64,
    x: f64,
    h: f64,
    scale: f64,
) -> Option<(f64, f64)> {
    let f0 = f(x);
    let fp = f(x + h);
    let fm = f(x - h);
    let fwd = (fp - f0) / h;
    let bwd = (f0 - fm) / h;
    let d_h = (fp - fm) / (2.0 * h);
    if (fwd - bwd).abs() > 1e-3 * (d_h.abs() + scale) {
        return None;
    }
    let (fp2, fm2) = (f(x + h / 2.0), f(x - h / 2.0));
    let (fp4, fm4) = (f(x + h / 4.0), f(x - h / 4.0));
    let d_half = (fp2 - fm2) / h;
    let d_quarter = (fp4 - fm4) / (h / 2.0);
    let coarse = (4.0 * d_half - d_h) / 3.0;
    let fine = (4.0 * d_quarter - d_half) / 3.0;
    let magnitude = [f0, fp, fm, fp2, fm2, fp4, fm4]
        .iter()
        .fold(0.0f64, |m, v| m.max(v.abs()));
    let roundoff = 64.0 * f64::EPSILON * magnitude / h;
    if (coarse - fine).abs() > 1e-8 * (coarse.abs() + scale) + roundoff {
        return None;
    }
    let c = (fp - 2.0 * f0 + fm) / h;
    let c_half = (fp2 - 2.0 * f0 + fm2) / (h / 2.0);
    let c_quarter = (fp4 - 2.0 * f0 + fm4) / (h / 4.0);
    let unscaled = (c_half - c / 2.0).abs() + (c_quarter - c_half / 2.0).abs();
    Some((coarse, (coarse - fine).abs() + unscaled + roundoff))
}

/// Sets entry `index` of the flattened values of `var` to `x` (in the variable's dtype,
/// on its device): the finite-difference tests' perturbation.
pub fn set_entry(var: &Var, index: usize, x: f64) {
    let mut v = v64(var.as_tensor());
    v[index] = x;
    let t = Tensor::from_vec(v, var.dims(), var.device())
        .unwrap()
        .to_dtype(var.dtype())
        .unwrap();
    var.set(&t).unwrap();
}

/// The tally of a test that checks backpropagated gradients against finite differences:
/// entries checked, and entries skipped where the stencil crossed a kink.
#[derive(Default)]
pub struct FdTally {
    pub checked: usize,
    pub skipped: usize,
}

impl FdTally {
    /// Asserts `|backprop − fd| ≤ tol` (`fd = None`: skipped at a kink); `what` names the
    /// entry in the failure message.
    pub fn check(&mut self, backprop: f64, fd: Option<f64>, tol: f64, what: &dyn Fn() -> String) {
        match fd {
            Some(fd) => {
                self.checked += 1;
                assert!(
                    (backprop - fd).abs() <= tol,
                    "{}: backprop {backprop} vs finite difference {fd}",
                    what()
                );
            }
            None => self.skipped += 1,
        }
    }
}

/// `|a − b| ≤ tol·max(|a|, |b|, floor)`.
pub fn close(a: f64, b: f64, tol: f64, floor: f64) -> bool {
    (a - b).abs() <= tol * a.abs().max(b.abs()).max(floor)
}

/// The variables of `varmap` in name order.
pub fn sorted_vars(varmap: &VarMap) -> Vec<Var> {
    let data = varmap.data().lock().unwrap();
    let mut names: Vec<&String> = data.keys().collect();
    names.sort();
    names.into_iter().map(|k| data[k].clone()).collect()
}

/// Each part of `fused` within `tol` of the same part of `reference`, relative to the
/// part's largest entry (at least 1e-3).
pub fn assert_parts_close(fused: &[Vec<f64>], reference: &[Vec<f64>], tol: f64, what: &str) {
    assert_eq!(fused.len(), reference.len(), "{what}: parts");
    for (k, (x, y)) in fused.iter().zip(reference).enumerate() {
        assert_eq!(x.len(), y.len(), "{what}: part {k}");
        let scale = y.iter().fold(1e-3f64, |m, v| m.max(v.abs()));
        for (i, (&u, &v)) in x.iter().zip(y).enumerate() {
            assert!(
                (u - v).abs() <= tol * scale,
                "{what}: part {k}[{i}]: fused {u} vs reference {v}"
            );
        }
    }
}

/// Debian's assimp-testmodels (`apt-get install assimp-testmodels`), or `None` with a
/// line saying the tests on real meshes skip.
pub fn assimp_models() -> Option<&'static std::path::Path> {
    let p = std::path::Path::new("/usr/share/assimp/models");
    if p.is_dir() {
        Some(p)
    } else {
        println!(
            "SKIPPED: {} is absent (apt-get install assimp-testmodels)",
            p.display()
        );
        None
    }
}

/// The ray `(origin, direction)` of `camera` through the continuous pixel coordinate
/// `pixel`, in f64 on the host (through [`neural_fields::camera::Camera::rays_for_pixels`]).
pub fn camera_ray(
    camera: &neural_fields::camera::Camera,
    pixel: glam::DVec2,
) -> (glam::DVec3, glam::DVec3) {
    let px = candle_core::Tensor::new(&[[pixel.x, pixel.y]], &candle_core::Device::Cpu).unwrap();
    let rays = camera.rays_for_pixels(&px).unwrap();
    let row = |t: &candle_core::Tensor| {
        let v = t.to_vec2::<f64>().unwrap();
        glam::DVec3::new(v[0][0], v[0][1], v[0][2])
    };
    (row(rays.origins()), row(rays.directions()))
}
