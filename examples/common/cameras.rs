//! Cameras of the examples: square pinhole images looking at the origin, z up.

use neural_fields::camera::{Camera, Convention, Intrinsics};
use neural_fields::glam::DVec3;

/// A `side × side` pinhole camera (vertical field of view `fov_y`, radians) at `eye`,
/// looking at the origin with +z up, in the OpenGL convention.
pub fn looking_at_origin(side: usize, fov_y: f64, eye: DVec3) -> neural_fields::Result<Camera> {
    let k = Intrinsics::from_fov_y(side, side, fov_y)?;
    Camera::look_at(k, eye, DVec3::ZERO, DVec3::Z, Convention::OpenGl)
}
