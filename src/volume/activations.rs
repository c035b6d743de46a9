//! Density activations (placeholder).
