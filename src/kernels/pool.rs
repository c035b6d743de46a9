//! Buffers kept between a fused op's calls ([`BufferPool`]): a training step's large
//! activations and gradients, which, allocated afresh, are faulted in page by page on
//! every step.

use super::dispatch::Real;
use std::any::Any;
use std::sync::{Mutex, MutexGuard, PoisonError};

/// Buffers a [`BufferPool`] holds at most.
const HELD: usize = 64;

/// Buffers kept between a fused op's calls (each `Vec<f32>` or `Vec<f64>`, at most
/// [`HELD`]): the ONet decoder and the voxel and image encoders each own one and hand it to every
/// op they build (`FusedOnet`, `FusedConvStack`).
#[derive(Debug, Default)]
pub(crate) struct BufferPool(Mutex<Vec<Box<dyn Any + Send>>>);

impl BufferPool {
    fn lock(&self) -> MutexGuard<'_, Vec<Box<dyn Any + Send>>> {
        self.0.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// A buffer of `len` values: the smallest held one of capacity `≥ len`, its values
    /// those of its last use (every caller writes each value before reading it), or a
    /// new one of zeros.
    pub(crate) fn take<T: Real>(&self, len: usize) -> Vec<T> {
        let mut held = self.lock();
        let fit = held
            .iter()
            .enumerate()
            .filter_map(|(i, b)| {
                let c = b.downcast_ref::<Vec<T>>()?.capacity();
                (c >= len).then_some((c, i))
            })
            .min();
        match fit.map(|(_, i)| held.swap_remove(i).downcast::<Vec<T>>()) {
            Some(Ok(v)) => {
                let mut v = *v;
                v.resize(len, T::from_f64(0.0));
                v
            }
            _ => vec![T::from_f64(0.0); len],
        }
    }

    /// Returns `v` for a later [`BufferPool::take`] (dropped when [`HELD`] are held).
    pub(crate) fn give<T: Real>(&self, v: Vec<T>) {
        let mut held = self.lock();
        if held.len() < HELD {
            held.push(Box::new(v));
        }
    }
}
