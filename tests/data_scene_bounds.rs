//! Scene bounds from the data (`Dataset::visual_hull`): the box of the silhouettes'
//! visual hull contains the object's box and is within a few cells of it.
#![cfg(feature = "data")]

use neural_fields::camera::{Camera, Convention, Intrinsics};
use neural_fields::data::{Background, Dataset, Image, View};
use neural_fields::glam::DVec3;

/// `n` cameras on a ring of radius 2.2 at heights alternating ±0.6 around the origin,
/// each with an RGBA image of `size`² whose alpha is the silhouette of the ball
/// (`centre`, `radius`) — or no alpha at all when `alpha` is false.
fn ball_dataset(n: usize, size: usize, centre: DVec3, radius: f64, alpha: bool) -> Dataset {
    let eyes: Vec<DVec3> = (0..n)
        .map(|i| {
            let a = i as f64 * std::f64::consts::TAU / n as f64;
            DVec3::new(
                2.2 * a.cos(),
                2.2 * a.sin(),
                if i % 2 == 0 { 0.6 } else { -0.6 },
            )
        })
        .collect();
    ellipsoid_dataset(&eyes, size, centre, DVec3::splat(radius), alpha)
}

/// Cameras at `eyes` looking at the origin (vertical field of view 0.7 rad), each with
/// an image of `size`² whose alpha (when `alpha`) is the silhouette of the ellipsoid
/// about `centre` with semi-axes `axes`.
fn ellipsoid_dataset(
    eyes: &[DVec3],
    size: usize,
    centre: DVec3,
    axes: DVec3,
    alpha: bool,
) -> Dataset {
    let k = Intrinsics::from_fov_y(size, size, 0.7).expect("intrinsics");
    let views = eyes
        .iter()
        .enumerate()
        .map(|(i, &eye)| {
            let cam =
                Camera::look_at(k, eye, DVec3::ZERO, DVec3::Z, Convention::OpenCv).expect("camera");
            let pose = cam.cam_to_world();
            // The ray eye + t·d in the ellipsoid's unit-sphere coordinates.
            let o = (eye - centre) / axes;
            let channels = if alpha { 4 } else { 3 };
            let mut px = Vec::with_capacity(size * size * channels);
            for v in 0..size {
                for u in 0..size {
                    let d = DVec3::new(
                        (u as f64 + 0.5 - k.cx) / k.fx,
                        (v as f64 + 0.5 - k.cy) / k.fy,
                        1.0,
                    );
                    let d = (pose.matrix3 * d) / axes;
                    let (b, c) = (o.dot(d), o.length_squared() - 1.0);
                    let inside = b < 0.0 && b * b >= d.length_squared() * c;
                    px.extend_from_slice(&[128, 128, 128]);
                    if alpha {
                        px.push(if inside { 255 } else { 0 });
                    }
                }
            }
            let image = Image::new(size, size, channels, px).expect("image");
            View::new(cam, image, None, format!("v{i}")).expect("view")
        })
        .collect();
    Dataset::new(views, Background::Color([1.0; 3]), None).expect("dataset")
}

#[test]
fn the_hull_box_of_a_ball_contains_it_and_is_within_three_cells_of_it() {
    let (centre, radius) = (DVec3::new(0.12, -0.05, 0.2), 0.3);
    let data = ball_dataset(24, 80, centre, radius, true);
    let b = data.visual_hull(0.0).expect("valid margin").expect("masks");
    let (lo, hi) = (centre - radius, centre + radius);
    // The second pass cuts a box about 0.7 wide into 48 cells of about 0.015.
    for a in 0..3 {
        assert!(
            b[a] <= lo[a] + 1e-9 && b[a + 3] >= hi[a] - 1e-9,
            "{b:?} must contain the ball"
        );
        assert!(
            lo[a] - b[a] < 0.06 && b[a + 3] - hi[a] < 0.06,
            "{b:?} too loose around the ball"
        );
    }
    // The margin grows every side by margin × the largest side.
    let m = data.visual_hull(0.1).expect("valid").expect("masks");
    let side = (0..3).map(|a| b[a + 3] - b[a]).fold(0.0, f64::max);
    for a in 0..3 {
        assert!((b[a] - m[a] - 0.1 * side).abs() < 1e-12);
        assert!((m[a + 3] - b[a + 3] - 0.1 * side).abs() < 1e-12);
    }
}

#[test]
fn no_masks_no_hull_and_a_bad_margin_is_refused() {
    let data = ball_dataset(6, 32, DVec3::ZERO, 0.3, false);
    assert_eq!(data.visual_hull(0.05).expect("valid margin"), None);
    let masked = ball_dataset(6, 32, DVec3::ZERO, 0.3, true);
    for bad in [f64::NAN, -0.1, f64::INFINITY] {
        let e = masked.visual_hull(bad).expect_err("bad margin").to_string();
        assert!(e.contains("margin"), "{e}");
    }
}

#[test]
fn silhouettes_that_are_all_background_carve_everything() {
    // A ball far outside every view: no foreground pixel anywhere.
    let data = ball_dataset(8, 32, DVec3::new(40.0, 0.0, 0.0), 0.3, true);
    assert_eq!(data.visual_hull(0.05).expect("valid margin"), None);
}

#[test]
fn the_committed_scene_hull_is_inside_its_unit_ball() {
    let train = neural_fields::data::load(
        "examples/data/wuson".as_ref(),
        &neural_fields::data::LoadConfig::default(),
    )
    .expect("committed dataset");
    let b = train.visual_hull(0.0).expect("valid").expect("alpha");
    // render_dataset.py scales the mesh into the unit ball (largest vertex distance 1).
    for a in 0..3 {
        assert!(b[a] > -1.06 && b[a + 3] < 1.06, "{b:?}");
        assert!(
            b[a + 3] - b[a] > 0.3,
            "{b:?}: the object has extent on every axis"
        );
    }
}

/// Three views from one side, all above the object: the camera centres' own box misses
/// the object entirely (the first carving region was once that box, and the hull of the
/// committed scene's three sparse views landed 5 units above it).
#[test]
fn three_views_from_one_side_still_bound_the_object() {
    let (centre, radius) = (DVec3::new(0.05, 0.1, -0.1), 0.3);
    let all = ball_dataset(24, 80, centre, radius, true);
    let views: Vec<View> = [0, 2, 4].iter().map(|&i| all.views()[i].clone()).collect();
    let data = Dataset::new(views, Background::Color([1.0; 3]), None).expect("dataset");
    let b = data.visual_hull(0.0).expect("valid").expect("masks");
    let (lo, hi) = (centre - radius, centre + radius);
    for a in 0..3 {
        assert!(
            b[a] <= lo[a] + 1e-9 && b[a + 3] >= hi[a] - 1e-9,
            "{b:?} must contain the ball"
        );
        // A narrow baseline (60°) leaves the hull long along the views, not unbounded.
        assert!(b[a + 3] - b[a] < 4.4, "{b:?}: within the cameras' reach");
    }
}

/// `Dataset::scene_box` of a layout without stated bounds is the silhouettes' hull + 5 %
/// where the views have alpha, else the given cube (what the examples take without
/// `--aabb`).
#[test]
fn scene_box_without_stated_bounds_is_the_hull_else_the_cube() {
    let masked = ball_dataset(12, 48, DVec3::new(0.1, 0.0, -0.1), 0.3, true);
    let hull = masked
        .visual_hull(0.05)
        .expect("valid margin")
        .expect("masks");
    assert_eq!(masked.scene_box(1.5), hull);
    assert!(hull.iter().all(|v| v.abs() < 0.6), "{hull:?}");
    let plain = ball_dataset(12, 48, DVec3::ZERO, 0.3, false);
    assert_eq!(plain.scene_box(1.5), [-1.5, -1.5, -1.5, 1.5, 1.5, 1.5]);
    // Silhouettes without any foreground: no hull, the cube.
    let empty = ball_dataset(8, 32, DVec3::new(40.0, 0.0, 0.0), 0.3, true);
    assert_eq!(empty.scene_box(1.5), [-1.5, -1.5, -1.5, 1.5, 1.5, 1.5]);
}

/// An object that fills the near views' frames, seen only from above, once left its hull
/// reaching far below it (z from −5.8 under a disc 0.4 thick): the near views' frames do
/// not reach that column, and the far views see it behind the object. Its silhouettes
/// in the low near views are cut by the frame's sides but do not touch the bottom edge,
/// so the object does not lie beyond that edge, and those views carve the column.
#[test]
fn an_object_that_fills_the_frame_is_bounded_below() {
    let (centre, axes) = (DVec3::ZERO, DVec3::new(2.0, 2.0, 0.4));
    // Camera `i` of `n` around the z axis at `radius` and elevation `e`, the ring turned
    // by `turn`.
    let around = |n: usize, i: usize, radius: f64, e: f64, turn: f64| {
        let a = i as f64 * std::f64::consts::TAU / n as f64 + turn;
        radius * DVec3::new(e.cos() * a.cos(), e.cos() * a.sin(), e.sin())
    };
    // 24 near views at elevations 0.3 and 0.9 rad (the disc wider than every frame),
    // 4 far views at 1.0 rad that hold it whole.
    let near = (0..24).map(|i| around(24, i, 4.0, if i % 2 == 0 { 0.3 } else { 0.9 }, 0.0));
    let eyes: Vec<DVec3> = near
        .chain((0..4).map(|i| around(4, i, 9.0, 1.0, 0.4)))
        .collect();
    let data = ellipsoid_dataset(&eyes, 64, centre, axes, true);
    let b = data.visual_hull(0.0).expect("valid").expect("masks");
    for a in 0..3 {
        assert!(
            b[a] <= centre[a] - axes[a] + 1e-9 && b[a + 3] >= centre[a] + axes[a] - 1e-9,
            "{b:?} must contain the disc"
        );
    }
    assert!(b[2] > -2.5, "{b:?}: the column under the disc is carved");
}
