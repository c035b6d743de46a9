//! Similarity alignment: of point sets ([`align_similarity`]), of a reconstruction's
//! cameras to the true ones by what they see ([`align_cameras`]), and the reprojection
//! error that measures the latter.

use super::Camera;
use crate::error::{Error, Result};
use crate::numerics::{levenberg_marquardt, LmConfig};
use glam::{DAffine3, DMat3, DQuat, DVec2, DVec3};

/// A similarity transform `y = s·R·x + t` (scale `s > 0`, rotation `R`, translation `t`),
/// the map between two reconstructions of the same scene that agree up to gauge: a
/// jointly refined set of cameras is determined only up to one (BARF, §4.1, aligns its
/// poses to the truth this way before measuring them). Its inverse, `x = R⁻¹(y − t)/s`,
/// is `Similarity { scale: 1/s, rotation: R⁻¹, translation: −R⁻¹t/s }`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Similarity {
    /// Scale `s > 0`.
    pub scale: f64,
    /// Rotation `R` (a unit quaternion).
    pub rotation: DQuat,
    /// Translation `t`.
    pub translation: DVec3,
}

impl Similarity {
    /// The identity: `s = 1`, `R = I`, `t = 0`.
    pub const IDENTITY: Self = Self {
        scale: 1.0,
        rotation: DQuat::IDENTITY,
        translation: DVec3::ZERO,
    };

    /// `x` moved by the similarity ([`Transformable`]): a point `p` to `s·R·p + t`; a
    /// camera-to-world pose (rotation `R_p`, centre `c`) to rotation `R·R_p`, centre
    /// `s·R·c + t` (a camera moved with the scene: its intrinsics are unchanged, its
    /// world-space depth scales by `s`).
    ///
    /// ```
    /// use neural_fields::camera::Similarity;
    /// use neural_fields::glam::{DAffine3, DQuat, DVec3};
    ///
    /// let s = Similarity { scale: 2.0, rotation: DQuat::from_rotation_z(0.5), translation: DVec3::X };
    /// let pose = DAffine3::from_translation(DVec3::Y);
    /// assert_eq!(s.apply(pose).translation, s.apply(DVec3::Y));
    /// # Ok::<(), neural_fields::Error>(())
    /// ```
    #[must_use]
    pub fn apply<T: Transformable>(&self, x: T) -> T {
        x.transformed(self)
    }
}

/// What a [`Similarity`] moves ([`Similarity::apply`]): points and camera-to-world poses.
pub trait Transformable {
    /// `self` moved by `s`.
    #[must_use]
    fn transformed(&self, s: &Similarity) -> Self;
}

impl Transformable for DVec3 {
    fn transformed(&self, s: &Similarity) -> Self {
        s.scale * (s.rotation * *self) + s.translation
    }
}

impl Transformable for DAffine3 {
    fn transformed(&self, s: &Similarity) -> Self {
        DAffine3::from_mat3_translation(
            DMat3::from_quat(s.rotation) * self.matrix3,
            self.translation.transformed(s),
        )
    }
}

/// The similarity `y ≈ s·R·x + t` that best maps the points `from` onto `to` in least
/// squares, `min Σᵢ |s·R·fromᵢ + t − toᵢ|²` over proper rotations `R` (Horn 1987: `R` is
/// the quaternion of the largest eigenvalue of a symmetric 4 × 4 matrix of the centred
/// cross-covariance; `s = Σ yᵢ·R xᵢ / Σ |xᵢ|²` on centred points; `t` from the centroids).
/// Used to align cameras refined jointly with a scene to the true cameras (their
/// centres as the points) before comparing poses or the scene.
///
/// The eigenvector is found by cyclic Jacobi rotations (at most 64 sweeps), so the cost
/// is `O(n)` for `n` points and there is no SVD.
///
/// ```
/// use glam::{DQuat, DVec3};
/// use neural_fields::camera::{align_similarity, Similarity};
///
/// let truth = Similarity {
///     scale: 2.0,
///     rotation: DQuat::from_rotation_z(0.3),
///     translation: DVec3::new(1.0, -2.0, 0.5),
/// };
/// let from = [DVec3::X, DVec3::Y, DVec3::Z, DVec3::ONE];
/// let to: Vec<DVec3> = from.iter().map(|&p| truth.apply(p)).collect();
/// let s = align_similarity(&from, &to)?;
/// assert!((s.scale - 2.0).abs() < 1e-12);
/// assert!(s.rotation.angle_between(truth.rotation) < 1e-9);
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// # Errors
/// [`Error::InvalidArgument`] naming `to` if its length differs from `from`'s; `from` if
/// it has fewer than 3 points, a non-finite coordinate, or points that do not span a
/// plane (the rotation about their line is then undetermined); `to` for a non-finite
/// coordinate or if all its points coincide (no scale).
pub fn align_similarity(from: &[DVec3], to: &[DVec3]) -> Result<Similarity> {
    if to.len() != from.len() {
        return Err(Error::invalid(
            "to",
            format!("{} points (as many as from)", from.len()),
            to.len().to_string(),
        ));
    }
    if from.len() < 3 {
        return Err(Error::invalid(
            "from",
            "at least 3 points",
            from.len().to_string(),
        ));
    }
    for (pts, name) in [(from, "from"), (to, "to")] {
        if let Some(p) = pts.iter().find(|p| !p.is_finite()) {
            return Err(Error::invalid(name, "finite points", format!("{p:?}")));
        }
    }
    let n = from.len() as f64;
    let mean = |p: &[DVec3]| p.iter().fold(DVec3::ZERO, |s, &q| s + q) / n;
    let (mx, my) = (mean(from), mean(to));
    // Centre and scale each set to unit RMS radius so the tests below are relative.
    let rms = |p: &[DVec3], m: DVec3| {
        (p.iter().map(|&q| (q - m).length_squared()).sum::<f64>() / n).sqrt()
    };
    let (rx, ry) = (rms(from, mx), rms(to, my));
    if !(rx > 0.0 && rx.is_finite()) {
        return Err(Error::invalid(
            "from",
            "points that do not all coincide",
            format!("RMS spread {rx}"),
        ));
    }
    if !(ry > 0.0 && ry.is_finite()) {
        return Err(Error::invalid(
            "to",
            "points that do not all coincide",
            format!("RMS spread {ry}"),
        ));
    }
    // Cross-covariance S_ab = Σ x_a y_b of the normalised, centred points.
    let mut s = [[0.0f64; 3]; 3];
    for (&x, &y) in from.iter().zip(to) {
        let (x, y) = (((x - mx) / rx).to_array(), ((y - my) / ry).to_array());
        for a in 0..3 {
            for b in 0..3 {
                s[a][b] += x[a] * y[b] / n;
            }
        }
    }
    let [[sxx, sxy, sxz], [syx, syy, syz], [szx, szy, szz]] = s;
    let mut m = [
        [sxx + syy + szz, syz - szy, szx - sxz, sxy - syx],
        [syz - szy, sxx - syy - szz, sxy + syx, szx + sxz],
        [szx - sxz, sxy + syx, -sxx + syy - szz, syz + szy],
        [sxy - syx, szx + sxz, syz + szy, -sxx - syy + szz],
    ];
    let (values, vectors) = symmetric_eigen4(&mut m);
    let mut order = [0usize, 1, 2, 3];
    order.sort_by(|&i, &j| values[j].total_cmp(&values[i]));
    // The two largest eigenvalues coincide exactly when the points lie on a line (or
    // the cross-covariance is otherwise rank-deficient in a way that leaves R free).
    if values[order[0]] - values[order[1]] <= 1e-9 {
        return Err(Error::invalid(
            "from",
            "points spanning a plane (a unique rotation)",
            format!("eigenvalue gap {:e}", values[order[0]] - values[order[1]]),
        ));
    }
    let q = vectors[order[0]];
    let rotation = DQuat::from_xyzw(q[1], q[2], q[3], q[0]).normalize();
    let (mut num, mut den) = (0.0, 0.0);
    for (&x, &y) in from.iter().zip(to) {
        num += (y - my).dot(rotation * (x - mx));
        den += (x - mx).length_squared();
    }
    let scale = num / den;
    if !(scale > 0.0 && scale.is_finite()) {
        return Err(Error::invalid(
            "to",
            "points related to from by a positive scale",
            format!("least-squares scale {scale}"),
        ));
    }
    Ok(Similarity {
        scale,
        rotation,
        translation: my - scale * (rotation * mx),
    })
}

/// The similarity `S` from the frame of the cameras `from` (a reconstruction's, with its
/// scene) to the frame of the cameras `to` (the reference) under which the cameras agree
/// best in **what they see**: the least-squares fit of the reprojections of the scene
/// `points` (in `from`'s frame),
///
/// `min_S Σᵢ Σₖ |π_toᵢ(S·yₖ) − π_fromᵢ(yₖ)|²` (pixels),
///
/// over every pair of camera `i` and point `yₖ` that `fromᵢ` sees in front of it and
/// inside its image (`π` the pinhole projection to pixel coordinates). A pinhole projection is unchanged when its
/// camera and the point move by one similarity, so each residual is the disagreement of
/// the reference camera `toᵢ` and the reconstruction's camera moved by `S` on the moved
/// point: a point of the scene lands on the same pixel in both.
///
/// Why not the centres ([`align_similarity`], BARF's protocol for comparing poses): a
/// camera refined from images is determined worst along the direction in which a shift
/// of its centre across the line of sight and the matching turn leave the scene's image
/// in place. A fit of the centres gives that direction full weight, so each camera's
/// error along it moves the whole fitted scene; this fit gives it the little weight the
/// images give it, and places the scene where the cameras' views put it. For a scene
/// learnt with refined cameras, compare the scene after this alignment and the poses
/// after the centres' one.
///
/// Solved by Levenberg–Marquardt ([`levenberg_marquardt`] with [`LmConfig::default`])
/// on a local chart `x ↦ e^σ·exp([ω]×)·(S(x) − m) + m + v` about the moved points'
/// centroid `m`, with central-difference Jacobians in f64 (7 parameters), from the
/// centres' fit, for at most 100 trial steps. The pairs are chosen once, at `S`'s start; a step that takes
/// one of them behind its reference camera is refused. Cost per iteration: `O(15·P)`
/// projections for `P` pairs. The cameras' intrinsics may differ between `from` and
/// `to`.
///
/// ```
/// use glam::{DQuat, DVec3};
/// use neural_fields::camera::{align_cameras, Camera, Convention, Intrinsics, Similarity};
///
/// let k = Intrinsics::from_fov_y(64, 64, 0.7)?;
/// let truth = Similarity {
///     scale: 1.5,
///     rotation: DQuat::from_rotation_y(0.4),
///     translation: DVec3::new(0.2, -0.1, 0.3),
/// };
/// let eyes = [(3.0, 0.0, 0.5), (0.0, 3.0, -0.5), (-3.0, 0.5, 0.0), (0.5, -3.0, 1.0)];
/// let mut from = Vec::new();
/// let mut to = Vec::new();
/// for (x, y, z) in eyes {
///     let c = Camera::look_at(k, DVec3::new(x, y, z), DVec3::ZERO, DVec3::Z, Convention::OpenCv)?;
///     to.push(Camera::new(k, truth.apply(c.cam_to_world()), Convention::OpenCv)?);
///     from.push(c);
/// }
/// let points = [DVec3::ZERO, DVec3::X * 0.3, DVec3::Y * 0.3, DVec3::Z * 0.3];
/// let s = align_cameras(&from, &to, &points)?;
/// assert!((s.scale - 1.5).abs() < 1e-9);
/// assert!(s.rotation.angle_between(truth.rotation) < 1e-9);
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// # Errors
/// [`Error::InvalidArgument`] naming `to` if its length differs from `from`'s; `from` if
/// the centres' fit that starts the solve fails (fewer than 3 cameras, or centres on one
/// line: [`align_similarity`]); `points` if it is empty, has a non-finite coordinate, or
/// no camera of `from` sees any of its points.
pub fn align_cameras(from: &[Camera], to: &[Camera], points: &[DVec3]) -> Result<Similarity> {
    check_views(from, to, points)?;
    let centres = |cams: &[Camera]| {
        cams.iter()
            .map(|c| c.cam_to_world().translation)
            .collect::<Vec<_>>()
    };
    let start = align_similarity(&centres(from), &centres(to))?;
    let pairs = seen_pairs(from, to, points, &start)?;
    // The residuals of `s`, or `None` when a pair's point falls behind its camera.
    let residuals = |s: &Similarity| -> Option<Vec<f64>> {
        let moved: Vec<DVec3> = points.iter().map(|&y| s.apply(y)).collect();
        let mut r = Vec::with_capacity(2 * pairs.len());
        for &(i, j, seen, _) in &pairs {
            let p = to[i].project(moved[j])?;
            r.push(p.x - seen.x);
            r.push(p.y - seen.y);
        }
        Some(r)
    };
    // The chart at `s`: 7 parameters (ω, v, σ) about the moved points' centroid.
    let centroid = |s: &Similarity| {
        points.iter().fold(DVec3::ZERO, |a, &y| a + s.apply(y)) / points.len() as f64
    };
    let chart = |s: &Similarity, step: &[f64; 7]| -> Similarity {
        let m = centroid(s);
        let turn = DQuat::from_scaled_axis(DVec3::new(step[0], step[1], step[2]));
        let grow = step[6].exp();
        Similarity {
            scale: grow * s.scale,
            rotation: (turn * s.rotation).normalize(),
            translation: grow * (turn * (s.translation - m))
                + m
                + DVec3::new(step[3], step[4], step[5]),
        }
    };
    // The residuals and their Jacobian by central differences: unit-free steps for ω and
    // σ, a fraction of the points' spread for v.
    let linearize = |s: &Similarity| -> Result<Linearization> {
        let Some(r) = residuals(s) else {
            return Ok(None);
        };
        let m = centroid(s);
        let spread = (points
            .iter()
            .map(|&y| (s.apply(y) - m).length_squared())
            .sum::<f64>()
            / points.len() as f64)
            .sqrt()
            .max(1e-300);
        let mut jac = vec![[0.0; 7]; r.len()];
        for a in 0..7 {
            let h = if (3..6).contains(&a) {
                1e-6 * spread
            } else {
                1e-6
            };
            let mut step = [0.0; 7];
            step[a] = h;
            let plus = residuals(&chart(s, &step));
            step[a] = -h;
            let minus = residuals(&chart(s, &step));
            let (Some(plus), Some(minus)) = (plus, minus) else {
                return Ok(None);
            };
            for (row, (p, q)) in jac.iter_mut().zip(plus.iter().zip(&minus)) {
                row[a] = (p - q) / (2.0 * h);
            }
        }
        Ok(Some((r, jac)))
    };
    let (s, _) = levenberg_marquardt(start, &LmConfig::default(), linearize, chart)?;
    Ok(s)
}

/// Residuals and their Jacobian rows w.r.t. [`align_cameras`]' chart, where defined.
type Linearization = Option<(Vec<f64>, Vec<[f64; 7]>)>;

/// The argument checks that [`align_cameras`] and [`reprojection_error`] share.
fn check_views(from: &[Camera], to: &[Camera], points: &[DVec3]) -> Result<()> {
    if to.len() != from.len() {
        return Err(Error::invalid(
            "to",
            format!("{} cameras (as many as from)", from.len()),
            to.len().to_string(),
        ));
    }
    if points.is_empty() {
        return Err(Error::invalid("points", "at least one point", "none"));
    }
    if let Some(p) = points.iter().find(|p| !p.is_finite()) {
        return Err(Error::invalid("points", "finite points", format!("{p:?}")));
    }
    Ok(())
}

/// The pairs of [`align_cameras`] and [`reprojection_error`]: camera `i` and point `k`
/// where `from[i]` sees `points[k]` in front of it and inside its image (edges
/// included) and `to[i]` sees `frame·points[k]` in front of it, with the pixels `from[i]`
/// and `to[i]` see them at.
///
/// # Errors
/// [`Error::InvalidArgument`] naming `points` when there is no such pair.
fn seen_pairs(
    from: &[Camera],
    to: &[Camera],
    points: &[DVec3],
    frame: &Similarity,
) -> Result<Vec<(usize, usize, DVec2, DVec2)>> {
    let moved: Vec<DVec3> = points.iter().map(|&y| frame.apply(y)).collect();
    let mut pairs = Vec::new();
    for (i, (f, t)) in from.iter().zip(to).enumerate() {
        let k = f.intrinsics();
        let inside = |p: DVec3| {
            (0.0..=k.width as f64).contains(&p.x) && (0.0..=k.height as f64).contains(&p.y)
        };
        for (j, (&y, &m)) in points.iter().zip(&moved).enumerate() {
            if let (Some(p), Some(q)) = (f.project(y).filter(|&p| inside(p)), t.project(m)) {
                pairs.push((i, j, p.truncate(), q.truncate()));
            }
        }
    }
    if pairs.is_empty() {
        return Err(Error::invalid(
            "points",
            "points that some camera of from sees (in front of it, inside its image)",
            format!("none of {} points", points.len()),
        ));
    }
    Ok(pairs)
}

/// The mean distance in pixels between where `from` sees `points` and where `to` sees
/// them moved by `frame`:
///
/// `(1/|P|) Σ_{(i,k)∈P} |π_toᵢ(S·yₖ) − π_fromᵢ(yₖ)|`,
///
/// over the pairs `P` of camera `i` and point `yₖ` that `fromᵢ` sees in front of it and
/// inside its image and `toᵢ` sees in front of it. [`align_cameras`] selects its pairs
/// the same way (at its starting similarity) and minimises their squared residuals, so
/// with `frame` its result this is that fit's residual, as a mean distance.
///
/// It measures a camera's error as a scene learnt with that camera feels it. Unlike the
/// rotation and centre errors after [`align_similarity`], it leaves out what the images do not show: a camera
/// orbited a little about the scene and turned to match sees nearly the same image and
/// scores nearly zero here. `points` are in `from`'s frame (for a reconstruction: points
/// of its surface), `frame` maps them into `to`'s (the identity when both are in one).
/// Plain f64 geometry, not differentiable. Cost: `O(|from|·|points|)` projections.
///
/// ```
/// use glam::DVec3;
/// use neural_fields::camera::{reprojection_error, Camera, Convention, Intrinsics, Similarity};
///
/// let k = Intrinsics::from_fov_y(64, 64, 0.7)?;
/// let eye = DVec3::new(0.0, -3.0, 0.0);
/// let cam = Camera::look_at(k, eye, DVec3::ZERO, DVec3::Z, Convention::OpenCv)?;
/// // The same camera shifted sideways by 0.03 (a hundredth of its distance).
/// let side = DVec3::X * 0.03;
/// let shifted = Camera::look_at(k, eye + side, side, DVec3::Z, Convention::OpenCv)?;
/// let points = [DVec3::ZERO, DVec3::new(0.2, 0.0, 0.1)];
/// let none = reprojection_error(&[cam], &[cam], &points, &Similarity::IDENTITY)?;
/// let some = reprojection_error(&[cam], &[shifted], &points, &Similarity::IDENTITY)?;
/// assert!(none < 1e-12);
/// // Every point seen a hundredth of the focal length (fy ≈ 87.7 px) off: about 0.88 px.
/// assert!((some - 0.01 * k.fy).abs() < 1e-9);
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// # Errors
/// [`Error::InvalidArgument`] naming `to` if its length differs from `from`'s; `points` if
/// it is empty, has a non-finite coordinate, or no pair is seen; `frame` if it is not
/// finite.
pub fn reprojection_error(
    from: &[Camera],
    to: &[Camera],
    points: &[DVec3],
    frame: &Similarity,
) -> Result<f64> {
    check_views(from, to, points)?;
    if !(frame.scale.is_finite() && frame.rotation.is_finite() && frame.translation.is_finite()) {
        return Err(Error::invalid(
            "frame",
            "a finite similarity",
            format!("{frame:?}"),
        ));
    }
    let pairs = seen_pairs(from, to, points, frame)?;
    let sum: f64 = pairs.iter().map(|(_, _, p, q)| (*q - *p).length()).sum();
    Ok(sum / pairs.len() as f64)
}

/// Eigenvalues and unit eigenvectors of the symmetric 4 × 4 matrix `m` (destroyed) by
/// cyclic Jacobi rotations; `vectors[k]` belongs to `values[k]`.
fn symmetric_eigen4(m: &mut [[f64; 4]; 4]) -> ([f64; 4], [[f64; 4]; 4]) {
    let mut v = [[0.0f64; 4]; 4];
    for (i, row) in v.iter_mut().enumerate() {
        row[i] = 1.0;
    }
    let scale: f64 = m.iter().flatten().map(|x| x * x).sum::<f64>().sqrt();
    for _sweep in 0..64 {
        let off: f64 = (0..4)
            .flat_map(|i| (0..4).filter(move |&j| j != i).map(move |j| (i, j)))
            .map(|(i, j)| m[i][j] * m[i][j])
            .sum::<f64>()
            .sqrt();
        if off <= 1e-15 * scale || off == 0.0 {
            break;
        }
        for p in 0..3 {
            for q in p + 1..4 {
                if m[p][q] == 0.0 {
                    continue;
                }
                // The rotation in the (p, q) plane that zeroes m[p][q].
                let theta = (m[q][q] - m[p][p]) / (2.0 * m[p][q]);
                // (signum(0) = 1: a rotation by π/4 when the diagonal entries are equal.)
                let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
                let c = 1.0 / (t * t + 1.0).sqrt();
                let s = t * c;
                for row in m.iter_mut() {
                    let (mkp, mkq) = (row[p], row[q]);
                    row[p] = c * mkp - s * mkq;
                    row[q] = s * mkp + c * mkq;
                }
                let (row_p, row_q) = (m[p], m[q]);
                for k in 0..4 {
                    m[p][k] = c * row_p[k] - s * row_q[k];
                    m[q][k] = s * row_p[k] + c * row_q[k];
                }
                for row in v.iter_mut() {
                    let (vp, vq) = (row[p], row[q]);
                    row[p] = c * vp - s * vq;
                    row[q] = s * vp + c * vq;
                }
            }
        }
    }
    let values = [m[0][0], m[1][1], m[2][2], m[3][3]];
    // Column k of v is the eigenvector of values[k].
    let mut vectors = [[0.0f64; 4]; 4];
    for (k, vec) in vectors.iter_mut().enumerate() {
        for (i, x) in vec.iter_mut().enumerate() {
            *x = v[i][k];
        }
    }
    (values, vectors)
}
