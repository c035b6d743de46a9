//! An analytic motion whose occupancy, correspondences and velocity are known in closed
//! form at every time: ground truth for Occupancy Flow's training, and the reference
//! against which the ODE solvers' error is measured.

use crate::error::{Error, Result};
use crate::rng::SplitMix64;
use candle_core::{Tensor, D};

/// A torus that twists, stretches and moves.
///
/// At `t = 0` the torus lies in the `xy` plane, centred at the origin (ring radius
/// `major`, tube radius `minor`). The motion `Φ(p₀, t)`:
/// 1. rotates `(x, z)` about the `y` axis by `θ = twist · t · y₀` (a twist: the ring bends
///    out of its plane),
/// 2. stretches `y` by `s(t) = 1 + stretch · t`,
/// 3. translates by `t · shift`.
///
/// Its inverse undoes the steps in reverse order (`y₀ = (y − t·shift_y)/s(t)` first), and
/// its velocity in Eulerian form is, with `b = shift`,
/// `v(p, t) = (twist·y₀·(z − b_z t) + b_x, stretch·y₀ + b_y, −twist·y₀·(x − b_x t) + b_z)`.
/// `Φ` is defined for `s(t) > 0`, i.e. `t > −1/stretch`.
///
/// ```
/// use neural_fields::flow::DeformingTorus;
/// let torus = DeformingTorus::default();
/// let p = [0.25, 0.0, 0.0]; // on the ring's centre line at t = 0
/// let moved = torus.carry(p, 0.0, 1.0);
/// assert!(torus.inside(moved, 1.0));
/// let back = torus.carry(moved, 1.0, 0.0);
/// assert!((0..3).all(|i| (back[i] - p[i]).abs() < 1e-12));
/// ```
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DeformingTorus {
    /// Ring radius at `t = 0` (default 0.25).
    pub major: f64,
    /// Tube radius at `t = 0` (default 0.12).
    pub minor: f64,
    /// Twist rate, radians per unit of `y₀` and of time (default 2.5).
    pub twist: f64,
    /// Stretch rate of `y` per unit of time (default 0.3).
    pub stretch: f64,
    /// Translation per unit of time (default `[0.12, 0, 0.05]`).
    pub shift: [f64; 3],
}

impl Default for DeformingTorus {
    fn default() -> Self {
        Self {
            major: 0.25,
            minor: 0.12,
            twist: 2.5,
            stretch: 0.3,
            shift: [0.12, 0.0, 0.05],
        }
    }
}

impl DeformingTorus {
    /// Where the point that is at `p` at time `from` is at time `to`: `Φ(Φ⁻¹(p, from), to)`
    /// (`carry(p, 0, t)` is `Φ(p, t)`, `carry(p, t, 0)` is `Φ⁻¹(p, t)`). Exact up to
    /// rounding; `p` in scene units.
    #[must_use]
    pub fn carry(&self, p: [f64; 3], from: f64, to: f64) -> [f64; 3] {
        self.forward(self.inverse(p, from), to)
    }

    /// Whether `p` is inside the torus at time `t` (its time-0 point `Φ⁻¹(p, t)` is
    /// within `minor` of the ring).
    #[must_use]
    pub fn inside(&self, p: [f64; 3], t: f64) -> bool {
        let q = self.inverse(p, t);
        let ring = (q[0] * q[0] + q[1] * q[1]).sqrt() - self.major;
        ring * ring + q[2] * q[2] < self.minor * self.minor
    }

    /// `n` points on the torus surface at time 0, uniform by area (rejection sampling by
    /// the area element `∝ major + minor·cos v`, which accepts at least half of the draws
    /// when `0 < minor ≤ major`), drawn from `rng`.
    ///
    /// # Errors
    /// Naming `self` unless `major` and `minor` are finite with `0 < minor ≤ major` (NaN
    /// or ±∞ radii are refused, so the rejection loop always ends); naming `n` when `n`
    /// points (24 bytes each) pass the allocation limit of 2³³ bytes (8 GiB), checked
    /// before anything is allocated.
    pub fn surface(&self, n: usize, rng: &mut SplitMix64) -> Result<Vec<[f64; 3]>> {
        let (big, small) = (self.major, self.minor);
        if !(big.is_finite() && small.is_finite() && 0.0 < small && small <= big) {
            return Err(Error::invalid(
                "self",
                "finite radii with 0 < minor ≤ major",
                format!("major {big}, minor {small}"),
            ));
        }
        crate::limits::check_bytes("n", &[n], 24)?;
        let mut out = Vec::with_capacity(n);
        while out.len() < n {
            let u = std::f64::consts::TAU * rng.uniform();
            let v = std::f64::consts::TAU * rng.uniform();
            if rng.uniform() * (big + small) > big + small * v.cos() {
                continue;
            }
            let ring = big + small * v.cos();
            out.push([ring * u.cos(), ring * u.sin(), small * v.sin()]);
        }
        Ok(out)
    }

    /// The Eulerian velocity `v(p, t) = ∂Φ/∂t` at `Φ⁻¹(p, t)`, for `p: [N, 3]` of any
    /// float dtype on any device → `[N, 3]` of the same; candle ops, so differentiable
    /// with respect to `p`. Ready for [`odeint`](super::odeint) as
    /// `|t, p| torus.velocity(p, t)`.
    ///
    /// # Errors
    /// Candle's errors, e.g. for `p` not of shape `[N, 3]`.
    pub fn velocity(&self, p: &Tensor, t: f64) -> Result<Tensor> {
        let (k, b) = (self.twist, self.shift);
        let col = |i| p.narrow(D::Minus1, i, 1);
        let y0 = col(1)?.affine(
            1.0 / (1.0 + self.stretch * t),
            -b[1] * t / (1.0 + self.stretch * t),
        )?;
        let vx = (y0.clone() * col(2)?.affine(k, -k * b[2] * t)?)?.affine(1.0, b[0])?;
        let vy = y0.affine(self.stretch, b[1])?;
        let vz = (y0 * col(0)?.affine(-k, k * b[0] * t)?)?.affine(1.0, b[2])?;
        Ok(Tensor::cat(&[vx, vy, vz], D::Minus1)?)
    }

    /// `Φ(p₀, t)`.
    fn forward(&self, p: [f64; 3], t: f64) -> [f64; 3] {
        let b = self.shift;
        let (sin, cos) = (self.twist * t * p[1]).sin_cos();
        [
            cos * p[0] + sin * p[2] + b[0] * t,
            p[1] * (1.0 + self.stretch * t) + b[1] * t,
            -sin * p[0] + cos * p[2] + b[2] * t,
        ]
    }

    /// `Φ⁻¹(p, t)`.
    fn inverse(&self, p: [f64; 3], t: f64) -> [f64; 3] {
        let b = self.shift;
        let q = [p[0] - b[0] * t, p[1] - b[1] * t, p[2] - b[2] * t];
        let y0 = q[1] / (1.0 + self.stretch * t);
        let (sin, cos) = (self.twist * t * y0).sin_cos();
        [cos * q[0] - sin * q[2], y0, sin * q[0] + cos * q[2]]
    }
}
