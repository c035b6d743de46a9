//! Training points for occupancy networks: uniform in the padded cube, near the
//! surface, and labelled against a real mesh with the generalised winding number.
//!
//! The generalised winding number (Jacobson et al. 2013) of a point `p` w.r.t. a
//! triangle soup is `w(p) = (1/4π) Σ_f Ω_f(p)`, the sum of the signed solid angles
//! subtended by the faces; `Ω` of a triangle with corners `a, b, c` relative to `p`
//! (Van Oosterom & Strackee 1983) is
//! `2 atan2(a·(b × c), |a||b||c| + (a·b)|c| + (b·c)|a| + (c·a)|b|)`.
//! For a closed oriented surface `w` is 1 inside and 0 outside; for a surface with small
//! holes, duplicated or unshared vertices (triangle soups such as `Wuson.ply`) it stays
//! close to those values away from the defects, so `|w| > ½` is a robust inside test
//! (taking `|w|` also makes it indifferent to the global orientation).

use super::mesh::{cross, dot, norm, sub, Mesh};
use crate::error::{check_scalar, Error, Result};
use crate::rng::SplitMix64;
use candle_core::{DType, Device, Tensor};
use rayon::prelude::*;

/// `n` points uniform in the cube `[−(1 + padding)/2, (1 + padding)/2]³` (ONet: padding
/// 0.1, the box `[−0.55, 0.55]³`), as a `[n, 3]` tensor of `dtype` on `device`.
///
/// # Errors
/// `n = 0`, a negative or non-finite padding.
pub fn uniform_in_padded_cube(
    n: usize,
    padding: f64,
    seed: u64,
    device: &Device,
    dtype: DType,
) -> Result<Tensor> {
    check_scalar(padding, "padding", false)?;
    if padding < 0.0 || n == 0 {
        return Err(Error::invalid(
            "padding",
            "n ≥ 1 and padding ≥ 0",
            format!("n = {n}, padding = {padding}"),
        ));
    }
    let h = 0.5 * (1.0 + padding);
    Ok(SplitMix64::new(seed).uniform_tensor(&[n, 3], -h, h, dtype, device)?)
}

/// `n` points near the surface: area-weighted surface samples displaced by isotropic
/// Gaussian noise `N(0, σ² I)` (ONet's optional near-surface sampling uses σ = 0.01 in
/// unit-cube units).
///
/// # Errors
/// Invalid mesh, non-positive `sigma`.
pub fn near_surface(mesh: &Mesh, n: usize, sigma: f64, seed: u64) -> Result<Vec<[f64; 3]>> {
    check_scalar(sigma, "sigma", true)?;
    let (pts, _) = mesh.sample_surface(n, seed)?;
    let mut rng = SplitMix64::new(seed ^ 0x5EED_5EED);
    Ok(pts
        .into_iter()
        .map(|p| {
            [
                p[0] + sigma * rng.normal(),
                p[1] + sigma * rng.normal(),
                p[2] + sigma * rng.normal(),
            ]
        })
        .collect())
}

/// Signed solid angle of triangle `(a, b, c)` seen from `p` (see the module docs).
fn solid_angle(p: [f64; 3], a: [f64; 3], b: [f64; 3], c: [f64; 3]) -> f64 {
    let (a, b, c) = (sub(a, p), sub(b, p), sub(c, p));
    let (la, lb, lc) = (norm(a), norm(b), norm(c));
    let num = dot(a, cross(b, c));
    let den = la * lb * lc + dot(a, b) * lc + dot(b, c) * la + dot(c, a) * lb;
    2.0 * num.atan2(den)
}

/// Generalised winding numbers `w(p)` of `points` w.r.t. the mesh's triangles (in
/// parallel over points; `O(points × faces)`).
///
/// # Errors
/// Invalid mesh.
pub fn winding_numbers(mesh: &Mesh, points: &[[f64; 3]]) -> Result<Vec<f64>> {
    mesh.validate()?;
    let tris: Vec<[[f64; 3]; 3]> = mesh
        .faces
        .iter()
        .map(|f| f.map(|k| mesh.vertices[k as usize]))
        .collect();
    Ok(points
        .par_iter()
        .map(|&p| {
            tris.iter()
                .map(|t| solid_angle(p, t[0], t[1], t[2]))
                .sum::<f64>()
                / (4.0 * std::f64::consts::PI)
        })
        .collect())
}

/// Inside test for real meshes: `|w(p)| > ½` (see the module docs).
///
/// # Errors
/// Invalid mesh.
pub fn inside_mesh(mesh: &Mesh, points: &[[f64; 3]]) -> Result<Vec<bool>> {
    Ok(winding_numbers(mesh, points)?
        .into_iter()
        .map(|w| w.abs() > 0.5)
        .collect())
}

/// Host points (e.g. from [`near_surface`]) as a `[n, 3]` tensor; re-exported helper.
///
/// # Errors
/// candle's.
pub fn to_tensor(points: &[[f64; 3]], device: &Device, dtype: DType) -> Result<Tensor> {
    super::mesh::points_tensor(points, device, dtype)
}

/// A tensor `[n, 3]` back to host points.
///
/// # Errors
/// Not `[n, 3]` floats; candle's.
pub fn from_tensor(points: &Tensor) -> Result<Vec<[f64; 3]>> {
    crate::error::check_points(points, "points")?;
    let v = points
        .to_dtype(DType::F64)?
        .to_device(&Device::Cpu)?
        .to_vec2::<f64>()?;
    Ok(v.into_iter().map(|r| [r[0], r[1], r[2]]).collect())
}
