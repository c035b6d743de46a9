//! The ONet evaluation metrics: volumetric IoU, Chamfer-L1, normal consistency and
//! F-score, with nearest neighbours from a k-d tree.

use crate::camera::{align_similarity, Similarity};
use crate::error::{check_scalar, Error, Result};
use crate::mesh::vector::dot;
use crate::mesh::Mesh;
use glam::DVec3;
use rayon::prelude::*;

/// A static 3-D k-d tree over points for exact nearest-neighbour queries.
#[derive(Clone, Debug)]
pub struct KdTree {
    points: Vec<[f64; 3]>,
    /// Permutation of point indices; node `[lo, hi)` splits at `mid = (lo + hi)/2` on
    /// the axis of largest spread, stored in `axes`.
    order: Vec<u32>,
    axes: Vec<u8>,
}

const LEAF: usize = 8;

impl KdTree {
    /// Builds the tree (`O(n log n)`).
    ///
    /// # Errors
    /// No points, or a non-finite coordinate.
    pub fn new(points: &[[f64; 3]]) -> Result<Self> {
        if points.is_empty() {
            return Err(Error::invalid("points", "at least one point", "none"));
        }
        if let Some(i) = points.iter().position(|p| p.iter().any(|c| !c.is_finite())) {
            return Err(Error::invalid(
                "points",
                "finite coordinates",
                format!("point {i} = {:?}", points[i]),
            ));
        }
        let mut t = Self {
            points: points.to_vec(),
            order: (0..points.len() as u32).collect(),
            axes: vec![0; points.len()],
        };
        t.build(0, points.len());
        Ok(t)
    }

    fn build(&mut self, lo: usize, hi: usize) {
        if hi - lo <= LEAF {
            return;
        }
        let mut bmin = [f64::INFINITY; 3];
        let mut bmax = [f64::NEG_INFINITY; 3];
        for &i in &self.order[lo..hi] {
            let p = self.points[i as usize];
            for c in 0..3 {
                bmin[c] = bmin[c].min(p[c]);
                bmax[c] = bmax[c].max(p[c]);
            }
        }
        let axis = (0..3)
            .max_by(|&a, &b| (bmax[a] - bmin[a]).total_cmp(&(bmax[b] - bmin[b])))
            .unwrap_or(0); // invariant: 0..3 is not empty
        let mid = (lo + hi) / 2;
        let pts = &self.points;
        self.order[lo..hi].select_nth_unstable_by(mid - lo, |&a, &b| {
            pts[a as usize][axis].total_cmp(&pts[b as usize][axis])
        });
        self.axes[mid] = axis as u8;
        self.build(lo, mid);
        self.build(mid + 1, hi);
    }

    /// The index of the nearest point to `q` and its Euclidean distance; `None` when `q`
    /// has a NaN or ±∞ coordinate (no point is nearest to it: the search used to answer
    /// `(0, ∞)` as if point 0 were). The tree's own points are finite ([`KdTree::new`]).
    #[must_use]
    pub fn nearest(&self, q: [f64; 3]) -> Option<(usize, f64)> {
        if !q.iter().all(|x| x.is_finite()) {
            return None;
        }
        let mut best = (0usize, f64::INFINITY);
        self.search(q, 0, self.points.len(), &mut best);
        Some((best.0, best.1.sqrt()))
    }

    fn search(&self, q: [f64; 3], lo: usize, hi: usize, best: &mut (usize, f64)) {
        if hi - lo <= LEAF {
            for &i in &self.order[lo..hi] {
                let p = self.points[i as usize];
                let d = (p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2);
                if d < best.1 {
                    *best = (i as usize, d);
                }
            }
            return;
        }
        let mid = (lo + hi) / 2;
        let i = self.order[mid] as usize;
        let p = self.points[i];
        let d = (p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2);
        if d < best.1 {
            *best = (i, d);
        }
        let axis = self.axes[mid] as usize;
        let diff = q[axis] - p[axis];
        let (near, far) = if diff < 0.0 {
            ((lo, mid), (mid + 1, hi))
        } else {
            ((mid + 1, hi), (lo, mid))
        };
        self.search(q, near.0, near.1, best);
        if diff * diff < best.1 {
            self.search(q, far.0, far.1, best);
        }
    }
}

/// Nearest-neighbour distances from each of `queries` to `reference` (in parallel),
/// with the index of the neighbour.
///
/// # Errors
/// As [`KdTree::new`] on `reference`; naming `queries` for a NaN or ±∞ coordinate.
fn nearest_distances(queries: &[[f64; 3]], reference: &[[f64; 3]]) -> Result<Vec<(usize, f64)>> {
    let tree = KdTree::new(reference)?;
    queries
        .par_iter()
        .map(|&q| {
            tree.nearest(q)
                .ok_or_else(|| Error::invalid("queries", "finite coordinates", format!("{q:?}")))
        })
        .collect()
}

/// Surface-to-surface metrics between a prediction and a ground truth.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SurfaceMetrics {
    /// Mean distance from predicted samples to the ground truth.
    pub accuracy: f64,
    /// Mean distance from ground-truth samples to the prediction.
    pub completeness: f64,
    /// ½(accuracy + completeness) — multiply by 10 to compare with the ONet papers.
    pub chamfer_l1: f64,
    /// ½(mean |n·n'| both ways); `None` if normals were not given for both sets.
    pub normal_consistency: Option<f64>,
    /// F-score at the threshold: `2PR/(P + R)` with precision `P` the fraction of
    /// predicted samples within the threshold of the ground truth, recall `R` the reverse.
    pub f_score: f64,
}

/// Chamfer-L1, normal consistency and F-score between two point sets with optional
/// normals (one per point), with the conventions below.
///
/// # Conventions (Mescheder et al. 2019, and how to compare with the papers)
/// * Both meshes are normalised to the unit cube first ([`Mesh::normalize_unit_cube`]
///   on the ground truth, the same transform applied to the prediction).
/// * 100 000 points are sampled on each surface ([`Mesh::sample_surface`]);
///   **Chamfer-L1** = ½(accuracy + completeness), where accuracy is the mean Euclidean
///   distance from predicted samples to their nearest ground-truth sample and
///   completeness the reverse. The distances are not squared (the "L1" is the mean of
///   norms).
/// * **Normal consistency** = ½(mean |n_pred · n_gt(nn)| + mean |n_gt · n_pred(nn)|),
///   with the normals of the faces the samples lie on (absolute value: insensitive to
///   orientation).
/// * **IoU** on 100 000 points uniform in the padded box, occupancy = probability ≥ ½.
/// * **The papers print Chamfer-L1 × 10** (ONet Table 1: 0.215 means 0.0215 in unit-cube
///   units; ONet issues #20, #61, #89). This module returns the unscaled value.
///
/// # Errors
/// Empty or non-finite point sets, normals of the wrong length, a non-positive threshold;
/// naming `pred` when a metric overflows f64 (coordinates near 1e300).
pub fn surface_metrics(
    pred: &[[f64; 3]],
    pred_normals: Option<&[[f64; 3]]>,
    gt: &[[f64; 3]],
    gt_normals: Option<&[[f64; 3]]>,
    f_threshold: f64,
) -> Result<SurfaceMetrics> {
    check_scalar(f_threshold, "f_threshold", true)?;
    if pred_normals.is_some_and(|n| n.len() != pred.len()) {
        return Err(Error::invalid(
            "pred_normals",
            "one normal per point",
            "a different count",
        ));
    }
    if gt_normals.is_some_and(|n| n.len() != gt.len()) {
        return Err(Error::invalid(
            "gt_normals",
            "one normal per point",
            "a different count",
        ));
    }
    let to_gt = nearest_distances(pred, gt)?;
    let to_pred = nearest_distances(gt, pred)?;
    let mean = |v: &[(usize, f64)]| v.iter().map(|x| x.1).sum::<f64>() / v.len() as f64;
    let frac =
        |v: &[(usize, f64)]| v.iter().filter(|x| x.1 < f_threshold).count() as f64 / v.len() as f64;
    let (accuracy, completeness) = (mean(&to_gt), mean(&to_pred));
    let (p, r) = (frac(&to_gt), frac(&to_pred));
    let f_score = if p + r > 0.0 {
        2.0 * p * r / (p + r)
    } else {
        0.0
    };
    let normal_consistency = match (pred_normals, gt_normals) {
        (Some(pn), Some(gn)) => {
            let a = to_gt
                .iter()
                .enumerate()
                .map(|(i, &(j, _))| dot(pn[i], gn[j]).abs())
                .sum::<f64>()
                / pred.len() as f64;
            let b = to_pred
                .iter()
                .enumerate()
                .map(|(i, &(j, _))| dot(gn[i], pn[j]).abs())
                .sum::<f64>()
                / gt.len() as f64;
            Some(0.5 * (a + b))
        }
        _ => None,
    };
    let chamfer_l1 = 0.5 * (accuracy + completeness);
    // Finite inputs can still overflow here (coordinates near 1e300, or normals of such
    // length): a metric that f64 cannot represent is an error, not `inf` or NaN.
    let finite = [accuracy, completeness, chamfer_l1, f_score]
        .iter()
        .chain(normal_consistency.iter())
        .all(|x| x.is_finite());
    if !finite {
        return Err(Error::invalid(
            "pred",
            "point sets whose distances (and normal products) are finite in f64",
            format!(
                "accuracy {accuracy}, completeness {completeness}, normal consistency \
                 {normal_consistency:?}"
            ),
        ));
    }
    Ok(SurfaceMetrics {
        accuracy,
        completeness,
        chamfer_l1,
        normal_consistency,
        f_score,
    })
}

/// [`surface_metrics`] between two meshes from `n` area-weighted samples on each (seeded),
/// with face normals. ONet uses `n = 100 000` and F-score thresholds around 1% of the
/// unit cube.
///
/// # Errors
/// Invalid meshes, `n = 0`, a non-positive threshold.
pub fn mesh_metrics(
    pred: &Mesh,
    gt: &Mesh,
    n: usize,
    f_threshold: f64,
    seed: u64,
) -> Result<SurfaceMetrics> {
    if n == 0 {
        return Err(Error::invalid("n", "at least one sample", "0"));
    }
    let (pp, pn) = pred.sample_surface(n, seed)?;
    let (gp, gn) = gt.sample_surface(n, seed.wrapping_add(1))?;
    surface_metrics(&pp, Some(&pn), &gp, Some(&gn), f_threshold)
}

/// Chamfer-L1 of `pred` to `gt` after moving `pred` onto `gt` by the similarity that
/// iterative closest points finds: 30 rounds of [`align_similarity`] from 20 000 points
/// sampled on `pred` to their nearest of 20 000 points sampled on `gt`, from the identity.
/// Both meshes are then placed in `gt`'s unit cube ([`Mesh::normalize_unit_cube`] of
/// `gt`, the same map applied to `pred`: ONet's normalisation) and compared by
/// [`mesh_metrics`] with `n` samples on each (ONet: 100 000).
///
/// The shape's error apart from its placement: a scene learnt with refined cameras is
/// determined only up to a similarity. ICP is one-sided (every point of `pred` is
/// matched), so for a mesh that is already well placed the result can exceed the plain
/// Chamfer distance. Plain f64 geometry, not differentiable; cost `O(30·m log m)` for the
/// ICP with `m` = 20 000, then that of [`mesh_metrics`].
///
/// # Errors
/// Those of [`mesh_metrics`] (invalid or empty meshes, `n = 0`); [`Error::InvalidArgument`]
/// from [`align_similarity`] when `pred`'s samples are degenerate (on one line).
pub fn chamfer_icp(pred: &Mesh, gt: &Mesh, n: usize, seed: u64) -> Result<f64> {
    const ICP_POINTS: usize = 20_000;
    if n == 0 {
        return Err(Error::invalid("n", "at least one sample", "0"));
    }
    let (from, _) = pred.sample_surface(ICP_POINTS, seed)?;
    let (to, _) = gt.sample_surface(ICP_POINTS, seed ^ 1)?;
    let tree = KdTree::new(&to)?;
    let from: Vec<DVec3> = from.iter().map(|&p| DVec3::from_array(p)).collect();
    let mut frame = Similarity::IDENTITY;
    for _ in 0..30 {
        let targets = from
            .iter()
            .map(|&p| {
                let q = frame.apply(p).to_array();
                let (i, _) = tree.nearest(q).ok_or_else(|| {
                    Error::invalid(
                        "pred",
                        "an alignment to gt that stays finite",
                        format!("{q:?}"),
                    )
                })?;
                Ok(DVec3::from_array(to[i]))
            })
            .collect::<Result<Vec<DVec3>>>()?;
        frame = align_similarity(&from, &targets)?;
    }
    let mut gt = gt.clone();
    let (centre, scale) = gt.normalize_unit_cube()?;
    let mut moved = pred.clone();
    for v in &mut moved.vertices {
        let p = frame.apply(DVec3::from_array(*v)).to_array();
        *v = std::array::from_fn(|c| (p[c] - centre[c]) * scale);
    }
    if let Some(normals) = &mut moved.normals {
        for m in normals.iter_mut() {
            *m = (frame.rotation * DVec3::from_array(*m)).to_array();
        }
    }
    Ok(mesh_metrics(&moved, &gt, n, 0.01, seed)?.chamfer_l1)
}

/// Volumetric IoU `|A ∩ B| / |A ∪ B|` of two occupancy labelings of the same points
/// (1 when both are empty).
///
/// # Errors
/// Different lengths.
pub fn iou(a: &[bool], b: &[bool]) -> Result<f64> {
    if a.len() != b.len() {
        return Err(Error::invalid(
            "b",
            format!("{} labels (as many as a)", a.len()),
            format!("{}", b.len()),
        ));
    }
    let inter = a.iter().zip(b).filter(|(x, y)| **x && **y).count();
    let union = a.iter().zip(b).filter(|(x, y)| **x || **y).count();
    Ok(if union == 0 {
        1.0
    } else {
        inter as f64 / union as f64
    })
}
