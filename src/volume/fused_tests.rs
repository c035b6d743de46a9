//! Kernel builds against the reference path. The kernel build is chosen per call
//! ([`KernelBuild`], crate-private), so the tests that run every build in turn live
//! here, inside the crate (moved from `tests/volume_fused.rs`).

use super::{composite as fused_composite, FusedGeometry, KernelBuild};
use crate::rng::SplitMix64;
use crate::test_host::{extreme_inputs, v64};
use crate::volume::compositing::{composite_with, CompositeConfig};
use crate::volume::layout::{Intervals, Layout};
use crate::volume::reference;
use crate::Result;
use candle_core::backprop::GradStore;
use candle_core::{Device, Tensor, Var};

const BUILDS: [KernelBuild; 3] = [
    KernelBuild::Baseline,
    KernelBuild::Avx2Fma,
    KernelBuild::Avx512,
];

fn dev() -> Device {
    Device::Cpu
}

/// Random extreme inputs (`extreme_inputs`, shared with `tests/volume_fused.rs`) and
/// sample depths in [0, 10).
fn inputs(seed: u64, n: usize, c: usize) -> (Vec<f64>, Vec<f64>, Vec<f64>, Vec<f64>) {
    let (sig, del, col) = extreme_inputs(seed, n, c);
    let mut rng = SplitMix64::new(seed ^ 0x7e57);
    let tm = (0..n).map(|_| 10.0 * rng.uniform()).collect();
    (sig, del, col, tm)
}

fn loss_weights(seed: u64, c: usize) -> Vec<f64> {
    let mut rng = SplitMix64::new(seed ^ 0x5eed);
    (0..c + 2).map(|_| rng.normal()).collect()
}

fn batched(r: usize, s: usize, c: usize, seed: u64) -> Result<(Tensor, Tensor, Tensor, Tensor)> {
    let (sig, del, col, tm) = inputs(seed, r * s, c);
    Ok((
        Tensor::from_vec(sig, (r, s), &dev())?,
        Tensor::from_vec(col, (r, s, c), &dev())?,
        Tensor::from_vec(del, (r, s), &dev())?,
        Tensor::from_vec(tm, (r, s), &dev())?,
    ))
}

/// Outputs, then the gradients w.r.t. σ, δ and the values, on the host.
type Run = (Vec<f64>, Vec<f64>, Vec<f64>, Vec<f64>);

/// The gradient of `t` in `g`, or an error naming it.
fn grad<'a>(g: &'a GradStore, t: &Tensor) -> Result<&'a Tensor> {
    g.get(t)
        .ok_or_else(|| crate::Error::invalid("t", "a tensor of the graph", "no gradient"))
}

/// Σwv and Σw for 0–7 channels (the kernels specialised for 1–4 channels and the
/// general one, including no channels at all: opacity only) equal weights × values
/// from the reference path, values and gradients (σ, δ and the values), on every kernel
/// build the CPU has (baseline, AVX2 + FMA, AVX-512).
#[test]
fn every_channel_count_and_every_kernel_build_match_the_reference() -> Result<()> {
    for build in BUILDS {
        for k in 0..8 {
            let (sig, col, del, tm) = batched(3, 37, k, 7 + k as u64)?;
            let run = |fused: bool| -> Result<Run> {
                let (s, c, d) = (
                    Var::from_tensor(&sig)?,
                    Var::from_tensor(&col)?,
                    Var::from_tensor(&del)?,
                );
                let out = if fused {
                    let geometry = FusedGeometry::Tensors {
                        deltas: d.as_tensor(),
                        t_mids: &tm,
                    };
                    let (color, opacity, _) = fused_composite(
                        s.as_tensor(),
                        c.as_tensor(),
                        geometry,
                        &Layout::Batched,
                        false,
                        build,
                    )?;
                    let opacity = opacity.unsqueeze(1)?;
                    if k == 0 {
                        opacity
                    } else {
                        Tensor::cat(&[&color, &opacity], 1)?
                    }
                } else {
                    let w =
                        reference::weights(s.as_tensor(), d.as_tensor(), &Layout::Batched, false)?;
                    let opacity = w.weights.sum_keepdim(1)?;
                    if k == 0 {
                        opacity
                    } else {
                        let acc =
                            reference::accumulate(&w.weights, c.as_tensor(), &Layout::Batched)?;
                        Tensor::cat(&[&acc, &opacity], 1)?
                    }
                };
                let lw = Tensor::new(&loss_weights(k as u64, k)[..k + 1], &dev())?;
                let l = out.broadcast_mul(&lw)?.sum_all()?;
                let g = l.backward()?;
                let get = |v: &Var| -> Result<Vec<f64>> { Ok(v64(grad(&g, v.as_tensor())?)) };
                // With no channels candle drops the empty values from the reference graph.
                let gc = g.get(c.as_tensor()).map(v64).unwrap_or_default();
                Ok((v64(&out), get(&s)?, get(&d)?, gc))
            };
            let (fo, fs, fd, fc) = run(true)?;
            let (ro, rs, rd, rc) = run(false)?;
            // ∂L/∂xⱼ = Tⱼ₊₁uⱼ − Σ_{i>j} wᵢuᵢ cancels down from |u| ≤ Σ|loss weights|
            // (values in [0, 1]); ∂L/∂σ = δ·∂L/∂x and ∂L/∂δ = σ·∂L/∂x.
            let umax: f64 = loss_weights(k as u64, k)[..k + 1]
                .iter()
                .map(|w| w.abs())
                .sum();
            let (sv, dv) = (v64(&sig), v64(&del));
            let ss: Vec<f64> = dv.iter().map(|d| d * umax).collect();
            let sd: Vec<f64> = sv.iter().map(|s| s * umax).collect();
            let one = vec![1.0; fo.len().max(fc.len())];
            for (name, a, b, scale) in [
                ("out", &fo, &ro, &one),
                ("sigmas", &fs, &rs, &ss),
                ("deltas", &fd, &rd, &sd),
                ("values", &fc, &rc, &one),
            ] {
                assert_eq!(a.len(), b.len(), "k = {k}: {name}");
                for ((x, y), sc) in a.iter().zip(b.iter()).zip(scale.iter()) {
                    assert!(
                        (x - y).abs() <= 1e-10 * (sc + y.abs()),
                        "k = {k}, {build:?}: {name} {x} vs {y}"
                    );
                }
            }
        }
    }
    Ok(())
}

/// The scans run in blocks of 4 samples and fall back to one sample at a time in the
/// block where T drops below 1e-300 (and in the last S mod 4 samples). With the drop at
/// every position of 3 blocks and a tail (S = 13), every kernel build gives the
/// reference's colour, opacity and depth, and gradients equal to the reference's up to
/// the dropped weights (each below 1e-300), with exactly zero gradient past the drop.
/// The intervals are constant (`[k, k + 1]`), so the kernel forms δ and t in place.
#[test]
fn blocked_scan_stops_in_the_block_where_transmittance_falls_below_1e_300() -> Result<()> {
    let s = 13;
    let ks = Tensor::arange(0.0f64, s as f64, &dev())?.reshape((1, s))?;
    let intervals = Intervals::new(ks.clone(), (&ks + 1.0)?, Layout::Batched)?;
    for build in BUILDS {
        for drop_at in 0..s {
            // x = σδ = 0.3 before the drop, 700 at it (T falls by e^{-700} ≈ 1e-304),
            // 0.2 after it.
            let sig: Vec<f64> = (0..s)
                .map(|i| match i.cmp(&drop_at) {
                    std::cmp::Ordering::Less => 0.3,
                    std::cmp::Ordering::Equal => 700.0,
                    std::cmp::Ordering::Greater => 0.2,
                })
                .collect();
            let sig = Tensor::from_vec(sig, (1, s), &dev())?;
            let col = Tensor::from_vec(
                (0..s * 2)
                    .map(|i| 0.1 + 0.05 * i as f64)
                    .collect::<Vec<_>>(),
                (1, s, 2),
                &dev(),
            )?;
            let run = |fused: bool| -> Result<(Vec<f64>, Vec<f64>, Vec<f64>)> {
                let (sv, cv) = (Var::from_tensor(&sig)?, Var::from_tensor(&col)?);
                let config = CompositeConfig {
                    force_reference: !fused,
                    ..CompositeConfig::default()
                };
                let (color, opacity, depth) = composite_with(
                    sv.as_tensor(),
                    cv.as_tensor(),
                    &intervals,
                    None,
                    &config,
                    build,
                )?;
                let lw = [0.7, -1.3, 0.4, 0.9];
                let lc = color
                    .broadcast_mul(&Tensor::new(&[[lw[0], lw[1]]], &dev())?)?
                    .sum_all()?;
                let l = ((lc + (opacity.sum_all()? * lw[2])?)? + (depth.sum_all()? * lw[3])?)?;
                let g = l.backward()?;
                let vals = [v64(&color), v64(&opacity), v64(&depth)].concat();
                Ok((
                    vals,
                    v64(grad(&g, sv.as_tensor())?),
                    v64(grad(&g, cv.as_tensor())?),
                ))
            };
            let ((fv, fs, fc), (rv, rs, rc)) = (run(true)?, run(false)?);
            for (name, a, b) in [
                ("outputs", &fv, &rv),
                ("d/dsigma", &fs, &rs),
                ("d/dcolor", &fc, &rc),
            ] {
                for (x, y) in a.iter().zip(b.iter()) {
                    assert!(
                        x.is_finite() && (x - y).abs() <= 1e-13 * (1.0 + y.abs()) + 1e-290,
                        "{build:?}, drop at {drop_at}: {name} {x:e} vs {y:e}"
                    );
                }
            }
            assert!(
                fs[drop_at + 1..].iter().all(|g| *g == 0.0)
                    && fc[2 * (drop_at + 1)..].iter().all(|g| *g == 0.0),
                "{build:?}, drop at {drop_at}: gradient past the drop {fs:?}"
            );
        }
    }
    Ok(())
}
