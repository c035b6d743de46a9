//! Reading `dvr::Hits` in the dvr tests (`Hits::count` is gone in 0.2).

use neural_fields::dvr::{Hits, RayStatus};

/// The number of rays of `hits` with status `status`.
pub fn count(hits: &Hits, status: RayStatus) -> usize {
    hits.status.iter().filter(|&&s| s == status).count()
}
