//! Training points for occupancy networks: uniform in the padded cube, near the
//! surface, and labelled against a real mesh with the generalised winding number.

use crate::error::{check_scalar, Error, Result};
use crate::mesh::vector::{cross, dot, norm, sub};
use crate::mesh::Mesh;
use crate::rng::SplitMix64;
use candle_core::{DType, Device, Tensor};
use rayon::prelude::*;

/// `n` points uniform in the cube `[−(1 + padding)/2, (1 + padding)/2]³` (ONet: padding
/// 0.1, the box `[−0.55, 0.55]³`), as a `[n, 3]` tensor of `dtype` on `device`.
///
/// # Errors
/// `n = 0`, a negative or non-finite padding; naming `n` when its `3n` values (8 bytes
/// each) pass the allocation limit of 2³³ bytes (8 GiB), checked before anything is
/// allocated.
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
    crate::limits::check_bytes("n", &[n, 3], 8)?;
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

/// Signed solid angle of triangle `(a, b, c)` seen from `p` (see [`winding_numbers`]).
fn solid_angle(p: [f64; 3], a: [f64; 3], b: [f64; 3], c: [f64; 3]) -> f64 {
    let (a, b, c) = (sub(a, p), sub(b, p), sub(c, p));
    let (la, lb, lc) = (norm(a), norm(b), norm(c));
    let num = dot(a, cross(b, c));
    let den = la * lb * lc + dot(a, b) * lc + dot(b, c) * la + dot(c, a) * lb;
    2.0 * num.atan2(den)
}

/// The exact generalised winding numbers: every triangle's solid angle summed, in
/// parallel over points (the reference path of [`winding_numbers`]).
fn winding_numbers_exact(tris: &[[[f64; 3]; 3]], points: &[[f64; 3]]) -> Vec<f64> {
    points
        .par_iter()
        .map(|&p| {
            tris.iter()
                .map(|t| solid_angle(p, t[0], t[1], t[2]))
                .sum::<f64>()
                / (4.0 * std::f64::consts::PI)
        })
        .collect()
}

/// A node of the triangle hierarchy for the fast winding number: the faces
/// `order[lo..hi]`, their area-weighted centroid `c`, the sum of area-weighted normals
/// `Σ a n` and the radius of a ball around `c` containing them.
struct WnNode {
    lo: usize,
    hi: usize,
    centre: [f64; 3],
    dipole: [f64; 3],
    radius: f64,
    children: Option<(usize, usize)>,
}

const WN_LEAF: usize = 8;
/// Far-field acceptance: use the dipole when `‖p − c‖ > WN_BETA · radius`.
const WN_BETA: f64 = 2.5;

fn wn_build(
    tris: &[[[f64; 3]; 3]],
    order: &mut [usize],
    base: usize,
    nodes: &mut Vec<WnNode>,
) -> usize {
    let mut area_sum = 0.0;
    let mut centre = [0.0; 3];
    let mut dipole = [0.0; 3];
    for &f in order.iter() {
        let [a, b, c] = tris[f];
        let n = cross(sub(b, a), sub(c, a)); // 2·area·normal
        let area = 0.5 * norm(n);
        for k in 0..3 {
            centre[k] += area * (a[k] + b[k] + c[k]) / 3.0;
            dipole[k] += 0.5 * n[k];
        }
        area_sum += area;
    }
    if area_sum > 0.0 {
        centre = centre.map(|x| x / area_sum);
    } else {
        let [a, _, _] = tris[order[0]];
        centre = a;
    }
    let mut radius: f64 = 0.0;
    for &f in order.iter() {
        for v in tris[f] {
            radius = radius.max(norm(sub(v, centre)));
        }
    }
    let id = nodes.len();
    nodes.push(WnNode {
        lo: base,
        hi: base + order.len(),
        centre,
        dipole,
        radius,
        children: None,
    });
    if order.len() > WN_LEAF {
        let cen = |f: usize| {
            let [a, b, c] = tris[f];
            [
                (a[0] + b[0] + c[0]) / 3.0,
                (a[1] + b[1] + c[1]) / 3.0,
                (a[2] + b[2] + c[2]) / 3.0,
            ]
        };
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        for &f in order.iter() {
            let c = cen(f);
            for k in 0..3 {
                lo[k] = lo[k].min(c[k]);
                hi[k] = hi[k].max(c[k]);
            }
        }
        let axis = (0..3)
            .max_by(|&a, &b| (hi[a] - lo[a]).total_cmp(&(hi[b] - lo[b])))
            .unwrap_or(0); // invariant: 0..3 is not empty
        let mid = order.len() / 2;
        order.select_nth_unstable_by(mid, |&a, &b| cen(a)[axis].total_cmp(&cen(b)[axis]));
        let (left, right) = order.split_at_mut(mid);
        let l = wn_build(tris, left, base, nodes);
        let r = wn_build(tris, right, base + mid, nodes);
        nodes[id].children = Some((l, r));
    }
    id
}

/// Settings of [`winding_numbers`].
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct WindingConfig {
    /// Sum the solid angle of every triangle at every point (exact, `O(points × faces)`):
    /// the reference the hierarchical approximation is tested against. Default `false`.
    pub force_reference: bool,
}

/// Generalised winding numbers `w(p)` of `points` w.r.t. the mesh's triangles.
///
/// The generalised winding number (Jacobson et al. 2013) of a point `p` w.r.t. a
/// triangle soup is `w(p) = (1/4π) Σ_f Ω_f(p)`, the sum of the signed solid angles
/// subtended by the faces; `Ω` of a triangle with corners `a, b, c` relative to `p`
/// (Van Oosterom & Strackee 1983) is
/// `2 atan2(a·(b × c), |a||b||c| + (a·b)|c| + (b·c)|a| + (c·a)|b|)`.
/// For a closed oriented surface `w` is 1 inside and 0 outside; for a surface with small
/// holes, duplicated or unshared vertices (triangle soups such as `Wuson.ply`) it stays
/// close to those values away from the defects, so `|w| > ½` is a robust inside test
/// (taking `|w|` also makes it indifferent to the global orientation).
///
/// By default the fast hierarchical approximation runs (Barill et al. 2018, first
/// order): a binary tree over the triangles; a subtree whose bounding ball is far from
/// `p` (`‖p − c‖ > 2.5·radius`) contributes its dipole term
/// `(c − p)·Σ aᵢnᵢ / (4π‖c − p‖³)`, nearer ones are descended, leaves are summed
/// exactly. Errors are well below the ½ threshold away from the surface;
/// `O(points × log faces)` in practice. With [`WindingConfig::force_reference`] every
/// triangle is summed at every point (exact, `O(points × faces)`). Both run in parallel
/// over points. Host values: not differentiable.
///
/// # Errors
/// Invalid mesh; naming `points` when one is NaN or ±∞ (its winding number would be NaN,
/// or meaningless), before anything is summed.
pub fn winding_numbers(
    mesh: &Mesh,
    points: &[[f64; 3]],
    config: &WindingConfig,
) -> Result<Vec<f64>> {
    mesh.validate()?;
    if let Some(i) = points.iter().position(|p| !p.iter().all(|x| x.is_finite())) {
        return Err(Error::invalid(
            "points",
            "finite coordinates",
            format!("{:?} at index {i}", points[i]),
        ));
    }
    let tris: Vec<[[f64; 3]; 3]> = mesh
        .faces
        .iter()
        .map(|f| f.map(|k| mesh.vertices[k as usize]))
        .collect();
    if config.force_reference {
        return Ok(winding_numbers_exact(&tris, points));
    }
    let mut order: Vec<usize> = (0..tris.len()).collect();
    let mut nodes = Vec::with_capacity(2 * tris.len() / WN_LEAF + 2);
    wn_build(&tris, &mut order, 0, &mut nodes);
    let eval = |p: [f64; 3]| -> f64 {
        let mut stack = vec![0usize];
        let mut sum = 0.0;
        while let Some(id) = stack.pop() {
            let n = &nodes[id];
            let d = sub(n.centre, p);
            let dist = norm(d);
            if dist > WN_BETA * n.radius {
                sum += dot(d, n.dipole) / (dist * dist * dist);
                continue;
            }
            match n.children {
                Some((l, r)) => {
                    stack.push(l);
                    stack.push(r);
                }
                None => {
                    for &f in &order[n.lo..n.hi] {
                        let t = tris[f];
                        sum += solid_angle(p, t[0], t[1], t[2]);
                    }
                }
            }
        }
        sum / (4.0 * std::f64::consts::PI)
    };
    Ok(points.par_iter().map(|&p| eval(p)).collect())
}
