//! Scene bounds from the data: the box of the visual hull of the training silhouettes.

use super::dataset::{Dataset, View};
use crate::camera::{axes_centre, Camera};
use crate::error::{Error, Result};
use crate::glam::DVec3;

/// Cells per axis of each carving pass.
const CELLS: usize = 48;

/// A view's foreground (mask ≥ ½) as a summed-area table `[(h + 1)·(w + 1)]`, which of
/// the image's edges it touches, and whether it shows the whole object (some
/// foreground, none on the image's border).
struct Silhouette<'a> {
    view: &'a View,
    w: usize,
    h: usize,
    sum: Vec<u32>,
    /// Foreground in the first column, the last column, the first row, the last row.
    touches: [bool; 4],
    whole: bool,
}

impl<'a> Silhouette<'a> {
    fn new(view: &'a View) -> Self {
        let (w, h, _) = view.image().size();
        let mut sum = vec![0u32; (w + 1) * (h + 1)];
        for v in 0..h {
            let mut row = 0u32;
            for u in 0..w {
                row += u32::from(view.mask_value(u, v).is_some_and(|m| m >= 0.5));
                sum[(v + 1) * (w + 1) + u + 1] = sum[v * (w + 1) + u + 1] + row;
            }
        }
        let total = sum[(w + 1) * (h + 1) - 1];
        let s = |u: usize, v: usize| sum[v * (w + 1) + u];
        // Foreground pixels in columns u0..u1 of rows v0..v1.
        let rect = |u0: usize, u1: usize, v0: usize, v1: usize| {
            s(u1, v1) + s(u0, v0) - s(u0, v1) - s(u1, v0)
        };
        let touches = if w > 0 && h > 0 {
            [
                rect(0, 1, 0, h) > 0,
                rect(w - 1, w, 0, h) > 0,
                rect(0, w, 0, 1) > 0,
                rect(0, w, h - 1, h) > 0,
            ]
        } else {
            [false; 4]
        };
        let whole = total > 0 && !touches.contains(&true);
        Self {
            view,
            w,
            h,
            sum,
            touches,
            whole,
        }
    }

    /// Foreground pixels in the view.
    fn count(&self) -> u32 {
        self.sum[(self.w + 1) * (self.h + 1) - 1]
    }

    /// Whether this view shows the ball of radius `radius` about `p` to be empty: the
    /// ball is in front of the camera and its projected square holds no foreground pixel,
    /// where the square lies inside the image — or, for a view that shows the whole
    /// object, wherever the square meets the image (the object lies inside that view's
    /// frustum, so space outside it is empty) — or, for a view with some foreground, the
    /// square lies wholly beyond an image edge the foreground does not touch, within
    /// that edge's span (the object leaves the frame only across the edges its
    /// silhouette touches).
    fn carves(&self, p: DVec3, radius: f64) -> bool {
        let cam = self.view.camera();
        let Some(q) = cam.project(p) else {
            // Behind the camera: empty if this view holds the whole object in front of it.
            return self.whole && self.behind(p, radius);
        };
        if q.z <= radius {
            return false;
        }
        let k = cam.intrinsics();
        // The ball's image lies within r·f/(z − r) of the centre's, plus a pixel.
        let r = radius * k.fx.max(k.fy) / (q.z - radius) + 1.0;
        let (mut x0, mut x1, mut y0, mut y1) = (q.x - r, q.x + r, q.y - r, q.y + r);
        let inside = x0 >= 0.0 && y0 >= 0.0 && x1 <= self.w as f64 && y1 <= self.h as f64;
        if !inside {
            if !self.whole {
                return self.beyond_free_edge(x0, x1, y0, y1);
            }
            (x0, y0) = (x0.max(0.0), y0.max(0.0));
            (x1, y1) = (x1.min(self.w as f64), y1.min(self.h as f64));
            if x0 >= x1 || y0 >= y1 {
                return true; // entirely outside the frame
            }
        }
        // Pixels whose centres (u + ½, v + ½) fall in the square.
        let (u0, u1) = (
            (x0 - 0.5).ceil() as usize,
            ((x1 - 0.5).floor() as usize).min(self.w - 1),
        );
        let (v0, v1) = (
            (y0 - 0.5).ceil() as usize,
            ((y1 - 0.5).floor() as usize).min(self.h - 1),
        );
        if u0 > u1 || v0 > v1 {
            return false; // no pixel centre in the square: keep the cell
        }
        let s = |u: usize, v: usize| self.sum[v * (self.w + 1) + u];
        s(u1 + 1, v1 + 1) + s(u0, v0) == s(u0, v1 + 1) + s(u1 + 1, v0)
    }

    /// Whether the square `[x0, x1] × [y0, y1]` (pixels) lies wholly beyond an edge of
    /// the image that the foreground does not touch, within that edge's span; never for
    /// a view without foreground.
    fn beyond_free_edge(&self, x0: f64, x1: f64, y0: f64, y1: f64) -> bool {
        let (w, h) = (self.w as f64, self.h as f64);
        let [left, right, top, bottom] = self.touches;
        let (across, down) = (x0 >= 0.0 && x1 <= w, y0 >= 0.0 && y1 <= h);
        self.count() > 0
            && ((!left && x1 <= 0.0 && down)
                || (!right && x0 >= w && down)
                || (!top && y1 <= 0.0 && across)
                || (!bottom && y0 >= h && across))
    }

    /// Whether the whole ball about `p` lies behind the camera's image plane.
    fn behind(&self, p: DVec3, radius: f64) -> bool {
        let cam = self.view.camera();
        (p - cam.cam_to_world().translation).dot(cam.forward()) < -radius
    }
}

impl Dataset {
    /// The box `[x0, y0, z0, x1, y1, z1]` of the visual hull of the views' silhouettes
    /// (mask or alpha ≥ ½), grown by `margin` times its largest side on every side; `None`
    /// when no view has a mask or every cell is carved (no foreground anywhere).
    ///
    /// Space carving, twice: the cube the cameras look into (centred on the point closest
    /// to every optical axis, as far out as the farthest camera), then the box the first
    /// pass kept, each cut into 48³ cells. A
    /// cell is carved when some view sees the ball around it whole (in front of the camera
    /// and inside the image) and no foreground pixel in the ball's projected square; when
    /// a view whose silhouette touches no image edge (it holds the whole object) sees the
    /// ball outside its frame or behind it; or when the ball projects wholly beyond an
    /// image edge that the view's silhouette does not touch, within that edge's span (an
    /// object that fills the frame and is cut by its left and right edges is not below
    /// the bottom edge). A cell no view carves is kept. For an object whose parts outside
    /// a frame join its visible part across the edges its silhouette touches (not only
    /// around a corner of the frame), the test is conservative (a cell that holds any of
    /// the object is never carved), so the hull's box contains the object's box; it is
    /// within about two cells of the silhouettes' own hull. Host f64; O(48³ · views) per
    /// pass with one summed-area table per view.
    ///
    /// ```
    /// use neural_fields::data::{load, LoadConfig};
    /// let train = load("examples/data/wuson".as_ref(), &LoadConfig::default())?;
    /// let hull = train.visual_hull(0.0)?; // `Some`: the views have alpha
    /// // The mesh was scaled into the unit ball (examples/data/README.md): the hull's box
    /// // is far tighter than the ±1.5 cube of layouts that state no bounds.
    /// assert!(hull.is_some_and(|b| b[..3].iter().all(|&v| v > -1.06) && b[3..].iter().all(|&v| v < 1.06)));
    /// # Ok::<(), neural_fields::Error>(())
    /// ```
    ///
    /// # Errors
    /// `margin` when not finite and ≥ 0.
    pub fn visual_hull(&self, margin: f64) -> Result<Option<[f64; 6]>> {
        if !(margin.is_finite() && margin >= 0.0) {
            return Err(Error::invalid(
                "margin",
                "finite and ≥ 0",
                format!("{margin}"),
            ));
        }
        let masked: Vec<Silhouette<'_>> = self
            .views()
            .iter()
            .filter(|v| v.has_mask())
            .map(Silhouette::new)
            .collect();
        if masked.iter().all(|s| s.count() == 0) {
            return Ok(None);
        }
        let (centre, half) = look_at_region(self.views());
        let mut region = Some((centre - half, centre + half));
        for _ in 0..2 {
            let Some((lo, hi)) = region else {
                return Ok(None);
            };
            region = carve(&masked, lo, hi);
        }
        Ok(region.map(|(lo, hi)| {
            let grow = margin * (hi - lo).max_element();
            let (lo, hi) = (lo - grow, hi + grow);
            [lo.x, lo.y, lo.z, hi.x, hi.y, hi.z]
        }))
    }
}

/// The cube the cameras look into: centred on the point closest, in least squares, to
/// every optical axis (the centroid of the camera centres when the axes are parallel),
/// with the largest distance of a camera from it as its half-side.
fn look_at_region(views: &[View]) -> (DVec3, f64) {
    let cameras: Vec<Camera> = views.iter().map(|v| *v.camera()).collect();
    let centres = cameras.iter().map(|c| c.cam_to_world().translation);
    let mean = centres.clone().sum::<DVec3>() / cameras.len().max(1) as f64;
    let centre = axes_centre(&cameras)
        .ok()
        .filter(|c| c.is_finite())
        .unwrap_or(mean);
    let half = centres.map(|c| (c - centre).length()).fold(1e-9, f64::max);
    (centre, half)
}

/// The box of the cells of `[lo, hi]` (48³) that no silhouette carves, `None` if all are.
fn carve(views: &[Silhouette<'_>], lo: DVec3, hi: DVec3) -> Option<(DVec3, DVec3)> {
    let cell = (hi - lo) / CELLS as f64;
    let radius = cell.length() / 2.0;
    let (mut klo, mut khi) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
    for i in 0..CELLS {
        for j in 0..CELLS {
            for k in 0..CELLS {
                let a = lo + cell * DVec3::new(i as f64, j as f64, k as f64);
                let centre = a + cell / 2.0;
                if !views.iter().any(|s| s.carves(centre, radius)) {
                    (klo, khi) = (klo.min(a), khi.max(a + cell));
                }
            }
        }
    }
    (klo.x <= khi.x).then_some((klo, khi))
}
