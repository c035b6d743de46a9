//! A torus that twists, stretches and moves: an analytic motion with closed-form
//! occupancy and correspondences at every time (the Occupancy Flow example and the
//! solver study of `error_vs_time` share it).
//!
//! At `t = 0` the torus lies in the `xy` plane (major radius `R`, minor radius `r`,
//! centred at the origin). The motion `Φ(p₀, t)`:
//! 1. rotates `(x, z)` about the `y` axis by `θ = K·t·y₀` (a twist: the ring bends out of
//!    its plane),
//! 2. stretches `y` by `s(t) = 1 + S·t`,
//! 3. translates by `t·b`.
//!
//! Its inverse undoes the steps in reverse order, and its velocity in Eulerian form is
//! `v(p, t) = (K y₀ (z − b_z t) + b_x, S y₀, −K y₀ (x − b_x t) + b_z)` with `y₀ = y / s(t)`.
#![allow(dead_code)] // each example uses a part

use candle_core::{Tensor, D};
use neural_fields::rng::SplitMix64;
use neural_fields::Result;

/// Major radius.
pub const R: f64 = 0.25;
/// Minor radius.
pub const TUBE: f64 = 0.12;
/// Twist rate (radians per unit of `y₀` and time).
pub const K: f64 = 2.5;
/// Stretch rate of `y`.
pub const S: f64 = 0.3;
/// Translation per unit of time.
pub const B: [f64; 3] = [0.12, 0.0, 0.05];

/// Whether `p` is inside the torus at time 0.
pub fn inside0(p: [f64; 3]) -> bool {
    let ring = (p[0] * p[0] + p[1] * p[1]).sqrt() - R;
    ring * ring + p[2] * p[2] < TUBE * TUBE
}

/// `Φ(p₀, t)`: where the point `p₀` of time 0 is at time `t`.
pub fn forward(p: [f64; 3], t: f64) -> [f64; 3] {
    let (sin, cos) = (K * t * p[1]).sin_cos();
    [
        cos * p[0] + sin * p[2] + B[0] * t,
        p[1] * (1.0 + S * t) + B[1] * t,
        -sin * p[0] + cos * p[2] + B[2] * t,
    ]
}

/// `Φ⁻¹(p, t)`: the point of time 0 that is at `p` at time `t`.
pub fn inverse(p: [f64; 3], t: f64) -> [f64; 3] {
    let q = [p[0] - B[0] * t, p[1] - B[1] * t, p[2] - B[2] * t];
    let y0 = q[1] / (1.0 + S * t);
    let (sin, cos) = (K * t * y0).sin_cos();
    [cos * q[0] - sin * q[2], y0, sin * q[0] + cos * q[2]]
}

/// Whether `p` is inside the moved torus at time `t`.
pub fn inside(p: [f64; 3], t: f64) -> bool {
    inside0(inverse(p, t))
}

/// `n` points uniform by area on the torus surface at time 0.
pub fn surface(n: usize, rng: &mut SplitMix64) -> Vec<[f64; 3]> {
    let mut out = Vec::with_capacity(n);
    while out.len() < n {
        let u = std::f64::consts::TAU * rng.uniform();
        let v = std::f64::consts::TAU * rng.uniform();
        // Area element ∝ R + r cos v: accept with that weight.
        if rng.uniform() * (R + TUBE) > R + TUBE * v.cos() {
            continue;
        }
        let ring = R + TUBE * v.cos();
        out.push([ring * u.cos(), ring * u.sin(), TUBE * v.sin()]);
    }
    out
}

/// The Eulerian velocity `v(p, t)` for `p: [N, 3]` (candle ops, any dtype).
pub fn velocity(p: &Tensor, t: f64) -> Result<Tensor> {
    let col = |i| p.narrow(D::Minus1, i, 1);
    let y0 = col(1)?.affine(1.0 / (1.0 + S * t), 0.0)?;
    let vx = (y0.clone() * col(2)?.affine(K, -K * B[2] * t)?)?.affine(1.0, B[0])?;
    let vy = y0.affine(S, B[1])?;
    let vz = (y0 * col(0)?.affine(-K, K * B[0] * t)?)?.affine(1.0, B[2])?;
    Ok(Tensor::cat(&[vx, vy, vz], D::Minus1)?)
}
