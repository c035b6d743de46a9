//! A field wrapper that counts its evaluations, for the dvr tests.

use candle_core::Tensor;
use neural_fields::field::{ImplicitSurface, Inside};
use neural_fields::Result;
use std::cell::Cell;

/// Counts the points at which a field is evaluated (value and value_and_grad alike, with
/// or without ray indices), the calls, and the largest number of points in one call.
pub struct Counting<'a, F: ?Sized> {
    pub inner: &'a F,
    /// Total points over all calls.
    pub points: Cell<usize>,
    /// Number of calls.
    pub calls: Cell<usize>,
    /// The most points passed in a single call.
    pub max_call: Cell<usize>,
}

impl<'a, F: ImplicitSurface + ?Sized> Counting<'a, F> {
    pub fn new(inner: &'a F) -> Self {
        Self {
            inner,
            points: Cell::new(0),
            calls: Cell::new(0),
            max_call: Cell::new(0),
        }
    }

    fn note(&self, p: &Tensor) {
        let n = p.dim(0).unwrap();
        self.points.set(self.points.get() + n);
        self.calls.set(self.calls.get() + 1);
        self.max_call.set(self.max_call.get().max(n));
    }
}

impl<F: ImplicitSurface + ?Sized> ImplicitSurface for Counting<'_, F> {
    fn value(&self, points: &Tensor) -> Result<Tensor> {
        self.note(points);
        self.inner.value(points)
    }
    fn value_and_grad(&self, points: &Tensor) -> Result<(Tensor, Tensor)> {
        self.note(points);
        self.inner.value_and_grad(points)
    }
    // The ray forms forward to the inner field's (whose defaults call its own `value`,
    // not this wrapper's), so every evaluation is counted exactly once.
    fn value_on_rays(&self, points: &Tensor, rays: &Tensor) -> Result<Tensor> {
        self.note(points);
        self.inner.value_on_rays(points, rays)
    }
    fn value_and_grad_on_rays(&self, points: &Tensor, rays: &Tensor) -> Result<(Tensor, Tensor)> {
        self.note(points);
        self.inner.value_and_grad_on_rays(points, rays)
    }
    fn level(&self) -> f64 {
        self.inner.level()
    }
    fn inside(&self) -> Inside {
        self.inner.inside()
    }
}
