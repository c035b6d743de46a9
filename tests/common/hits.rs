//! Reading `dvr::Hits` in the dvr tests (`Hits::count` is gone in 0.2).

use neural_fields::dvr::{Hits, RayStatus};

/// The number of rays of `hits` with status `status`.
pub fn count(hits: &Hits, status: RayStatus) -> usize {
    hits.status.iter().filter(|&&s| s == status).count()
}

/// A march accurate enough for finite differences of its depths in f64: 256 samples and
/// 40 Illinois secant steps, no grazing classification.
pub fn accurate_march() -> neural_fields::dvr::MarchConfig {
    neural_fields::dvr::MarchConfig {
        steps: 256,
        secant_steps: 40,
        chunk_points: 1 << 16,
        grazing_threshold: None,
        tolerance: 1.0,
        rule: neural_fields::dvr::SecantRule::Illinois,
    }
}
