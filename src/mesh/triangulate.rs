//! Polygon triangulation for the mesh readers: fans for convex polygons, ear clipping
//! for concave ones, both in the polygon's own plane.
//!
//! A polygon `p₀ … p_{k−1}` (k ≥ 3) is projected onto the plane of its Newell normal
//! `n = Σᵢ pᵢ × pᵢ₊₁` (twice the vector area), dropping the axis where `|n|` is largest,
//! and oriented so that it turns counter-clockwise seen along `n`. Then:
//!
//! - if every corner turns left (or goes straight), the fan `(0, i, i + 1)` is exact:
//!   `k − 2` triangles, `O(k)` work;
//! - otherwise ears are clipped (a corner that turns left and whose triangle holds no
//!   other corner), which triangulates every simple polygon in `O(k²)`. Concave polygons
//!   are limited to [`MAX_CONCAVE`] corners so that the work stays a constant times the
//!   file's size whatever the file holds;
//! - the triangles' areas projected along `n` must add up to the polygon's area `|n| / 2`
//!   (they do for every polygon that is simple in projection, planar or warped, and
//!   cannot for a self-intersecting one or one folded over itself): otherwise the
//!   polygon is refused.
//!
//! Triangles keep the polygon's winding, so faces stay oriented as the file had them.
//! Polygons with no area (all corners on a line, or repeated) are fanned: there is
//! nothing to orient, and the triangles are as degenerate as the polygon. A polygon
//! whose net area vanishes although its triangles would not (a symmetric bow tie) is
//! refused.

use super::vector::{cross, dot, sub};

/// The most corners a concave polygon may have (ear clipping is quadratic in them).
pub(crate) const MAX_CONCAVE: usize = 256;

/// Appends the triangles of `poly` (indices into `vertices`) to `out`.
///
/// # Errors
/// A message for the reader to wrap: fewer than three corners, an index past
/// `vertices`, a concave polygon with more than [`MAX_CONCAVE`] corners, or a
/// self-intersecting polygon.
pub(crate) fn triangulate(
    vertices: &[[f64; 3]],
    poly: &[u32],
    out: &mut Vec<[u32; 3]>,
) -> std::result::Result<(), String> {
    let k = poly.len();
    if k < 3 {
        return Err(format!("{k} vertices"));
    }
    if let Some(&bad) = poly.iter().find(|&&i| i as usize >= vertices.len()) {
        return Err(format!("index {bad} of {} vertices", vertices.len()));
    }
    if k == 3 {
        out.push([poly[0], poly[1], poly[2]]);
        return Ok(());
    }
    let p = |i: usize| vertices[poly[i] as usize];
    // Newell's normal, summed about the first corner (better conditioned far from 0).
    let o = p(0);
    let rel = |i: usize| sub(p(i), o);
    let mut n = [0.0f64; 3];
    for i in 0..k {
        let c = cross(rel(i), rel((i + 1) % k));
        n = [n[0] + c[0], n[1] + c[1], n[2] + c[2]];
    }
    let area2 = dot(n, n).sqrt();
    let fan = |out: &mut Vec<[u32; 3]>| {
        for i in 1..k - 1 {
            out.push([poly[0], poly[i], poly[i + 1]]);
        }
    };
    // The polygon's extent, to tell "no area" from rounding.
    let extent2 = (1..k).map(|i| dot(rel(i), rel(i))).fold(0.0, f64::max);
    if area2 <= 1e-12 * extent2 || !area2.is_finite() {
        // No net area: a polygon on a line (or repeated points), whose fan is as
        // degenerate as it is, or lobes that cancel (a bow tie), whose fan is not.
        let start = out.len();
        fan(out);
        let covered: f64 = out[start..]
            .iter()
            .map(|t| {
                let [a, b, c] = t.map(|i| vertices[i as usize]);
                dot(cross(sub(b, a), sub(c, a)), cross(sub(b, a), sub(c, a))).sqrt()
            })
            .sum();
        if covered > 1e-9 * extent2 {
            out.truncate(start);
            return Err(format!(
                "a self-intersecting polygon of {k} vertices (its lobes cancel: no net area)"
            ));
        }
        return Ok(());
    }
    // Drop the dominant axis; flip so that the projected polygon is counter-clockwise.
    let axis = (0..3)
        .max_by(|&a, &b| n[a].abs().total_cmp(&n[b].abs()))
        .unwrap_or(2);
    let (u, v) = ((axis + 1) % 3, (axis + 2) % 3);
    let sign = n[axis].signum();
    let q: Vec<[f64; 2]> = (0..k)
        .map(|i| {
            let r = rel(i);
            [r[u], sign * r[v]]
        })
        .collect();
    let turn = |a: [f64; 2], b: [f64; 2], c: [f64; 2]| {
        (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
    };
    // The turning number: a polygon that goes round its interior more than once (the
    // same convex ring listed twice) passes the convexity and area tests, since its
    // vector area counts every lap; it is refused here. Exact U-turns (the slits that
    // bridge a hole) have no defined turning sign and leave the check out.
    let mut turning = 0.0;
    let mut u_turn = false;
    for i in 0..k {
        let (a, b, c) = (q[(i + k - 1) % k], q[i], q[(i + 1) % k]);
        let (e, f) = ([b[0] - a[0], b[1] - a[1]], [c[0] - b[0], c[1] - b[1]]);
        let (x, y) = (e[0] * f[1] - e[1] * f[0], e[0] * f[0] + e[1] * f[1]);
        u_turn |= x == 0.0 && y < 0.0;
        turning += x.atan2(y);
    }
    let laps = (turning / std::f64::consts::TAU).round();
    if !u_turn && laps != 1.0 {
        return Err(format!(
            "a polygon of {k} vertices that winds {laps} times around its interior"
        ));
    }
    let convex = (0..k).all(|i| turn(q[(i + k - 1) % k], q[i], q[(i + 1) % k]) >= 0.0);
    let start = out.len();
    if convex {
        fan(out);
    } else {
        if k > MAX_CONCAVE {
            return Err(format!(
                "a concave polygon of {k} vertices (at most {MAX_CONCAVE} are triangulated)"
            ));
        }
        clip_ears(&q, poly, out, turn)?;
    }
    // Seen along the polygon's normal, the triangles of a polygon that is simple in
    // projection all turn its way and cover its area once; a self-intersecting or folded
    // polygon's triangles overlap or flip, so their unsigned areas add up to more.
    let mut covered = 0.0;
    for t in &out[start..] {
        let [a, b, c] = t.map(|i| vertices[i as usize]);
        covered += dot(cross(sub(b, a), sub(c, a)), n).abs() / area2;
    }
    if covered > area2 * (1.0 + 1e-7) {
        out.truncate(start);
        return Err(format!(
            "a self-intersecting or folded polygon of {k} vertices (its triangles cover \
             {:.6e}, its area is {:.6e})",
            covered / 2.0,
            area2 / 2.0
        ));
    }
    Ok(())
}

/// Ear clipping of the counter-clockwise projected polygon `q` (indices `poly`), in
/// `O(k²)`: ear flags are computed once and recomputed only for the two neighbours of a
/// clipped ear.
fn clip_ears(
    q: &[[f64; 2]],
    poly: &[u32],
    out: &mut Vec<[u32; 3]>,
    turn: impl Fn([f64; 2], [f64; 2], [f64; 2]) -> f64,
) -> std::result::Result<(), String> {
    let k = q.len();
    let mut prev: Vec<usize> = (0..k).map(|i| (i + k - 1) % k).collect();
    let mut next: Vec<usize> = (0..k).map(|i| (i + 1) % k).collect();
    let mut alive = vec![true; k];
    let is_ear = |i: usize, prev: &[usize], next: &[usize], alive: &[bool]| {
        let (a, b, c) = (prev[i], i, next[i]);
        if turn(q[a], q[b], q[c]) <= 0.0 {
            return false;
        }
        // No other corner strictly inside or on the open edges of the triangle (corners
        // equal to a, b or c, which repeated vertices produce, are not obstacles).
        (0..k).all(|j| {
            if !alive[j] || j == a || j == b || j == c {
                return true;
            }
            let p = q[j];
            if p == q[a] || p == q[b] || p == q[c] {
                return true;
            }
            !(turn(q[a], q[b], p) >= 0.0
                && turn(q[b], q[c], p) >= 0.0
                && turn(q[c], q[a], p) >= 0.0)
        })
    };
    let mut ear: Vec<bool> = (0..k).map(|i| is_ear(i, &prev, &next, &alive)).collect();
    let mut left = k;
    let mut i = 0;
    let mut misses = 0;
    while left > 3 {
        if alive[i] && ear[i] {
            let (a, c) = (prev[i], next[i]);
            out.push([poly[a], poly[i], poly[c]]);
            alive[i] = false;
            next[a] = c;
            prev[c] = a;
            left -= 1;
            ear[a] = is_ear(a, &prev, &next, &alive);
            ear[c] = is_ear(c, &prev, &next, &alive);
            i = c;
            misses = 0;
        } else {
            i = if alive[i] { next[i] } else { (i + 1) % k };
            misses += 1;
            if misses > 2 * k {
                return Err(format!(
                    "a self-intersecting polygon of {k} vertices (no ear left to clip with \
                     {left} vertices remaining)"
                ));
            }
        }
    }
    let a = (0..k).find(|&j| alive[j]).unwrap_or(0);
    out.push([poly[prev[a]], poly[a], poly[next[a]]]);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn area(vertices: &[[f64; 3]], tris: &[[u32; 3]]) -> f64 {
        tris.iter()
            .map(|t| {
                let [a, b, c] = t.map(|i| vertices[i as usize]);
                ((b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])) / 2.0
            })
            .sum()
    }

    #[test]
    fn an_l_shape_keeps_its_area_and_winding() -> Result<(), String> {
        // Counter-clockwise L of area 3, concave at corner 3.
        let v = [
            [0.0, 0.0, 0.0],
            [2.0, 0.0, 0.0],
            [2.0, 1.0, 0.0],
            [1.0, 1.0, 0.0],
            [1.0, 2.0, 0.0],
            [0.0, 2.0, 0.0],
        ];
        for rot in 0..6u32 {
            let poly: Vec<u32> = (0..6).map(|i| (i + rot) % 6).collect();
            let mut t = Vec::new();
            triangulate(&v, &poly, &mut t)?;
            assert_eq!(t.len(), 4);
            // Every triangle counter-clockwise, and together they cover the L once.
            assert!(t.iter().all(|tri| area(&v, &[*tri]) > 0.0), "{t:?}");
            assert!((area(&v, &t) - 3.0).abs() < 1e-12);
            // Reversed: every triangle clockwise, same area.
            let rev: Vec<u32> = poly.iter().rev().copied().collect();
            let mut t = Vec::new();
            triangulate(&v, &rev, &mut t)?;
            assert!((area(&v, &t) + 3.0).abs() < 1e-12);
        }
        Ok(())
    }

    #[test]
    fn a_bow_tie_is_refused() -> Result<(), String> {
        let v = [
            [0.0, 0.0, 0.0],
            [1.0, 1.0, 0.0],
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
        ];
        let mut t = Vec::new();
        let e = triangulate(&v, &[0, 1, 2, 3], &mut t).unwrap_err();
        assert!(e.contains("self-intersecting"), "{e}");
        assert!(t.is_empty());
        Ok(())
    }

    /// Pins a double cover: a convex ring listed twice (`f 1 2 3 4 5 1 2 3 4 5`) passed
    /// the convexity and area checks and was fanned into triangles covering it twice.
    #[test]
    fn a_ring_listed_twice_is_refused() -> Result<(), String> {
        let v: Vec<[f64; 3]> = (0..5)
            .map(|i| {
                let a = f64::from(i) / 5.0 * std::f64::consts::TAU;
                [a.cos(), a.sin(), 0.0]
            })
            .collect();
        let mut t = Vec::new();
        let e = triangulate(&v, &[0, 1, 2, 3, 4, 0, 1, 2, 3, 4], &mut t).unwrap_err();
        assert!(e.contains("winds 2 times"), "{e}");
        assert!(t.is_empty());
        triangulate(&v, &[0, 1, 2, 3, 4], &mut t)?;
        assert_eq!(t.len(), 3);
        Ok(())
    }

    #[test]
    fn collinear_and_huge_concave_polygons() -> Result<(), String> {
        let line = [
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [2.0, 0.0, 0.0],
            [3.0, 0.0, 0.0],
        ];
        let mut t = Vec::new();
        triangulate(&line, &[0, 1, 2, 3], &mut t)?;
        assert_eq!(t.len(), 2);
        // A star with more corners than MAX_CONCAVE is refused, not clipped.
        let k = MAX_CONCAVE + 2;
        let star: Vec<[f64; 3]> = (0..k)
            .map(|i| {
                let a = i as f64 / k as f64 * std::f64::consts::TAU;
                let r = if i % 2 == 0 { 1.0 } else { 0.5 };
                [r * a.cos(), r * a.sin(), 0.0]
            })
            .collect();
        let poly: Vec<u32> = (0..k as u32).collect();
        let e = triangulate(&star, &poly, &mut t).unwrap_err();
        assert!(e.contains("concave"), "{e}");
        Ok(())
    }
}
