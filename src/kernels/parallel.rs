//! CPU parallelism for kernels that run inside a candle autograd step.
//!
//! candle (0.11) runs its element-wise CPU ops on its own barrier pool, whose workers spin
//! for a while (25 000 iterations by default) after each op before parking. A kernel that
//! runs between candle ops on a second pool (rayon's global pool) competes with those
//! spinning workers for the same cores: on a 2-core machine this cost the fused
//! compositing step about a fifth of its time. Kernels called inside the forward or
//! backward of a step therefore run here, on candle's pool. (Work that runs outside the
//! step, such as mesh extraction, may keep using rayon.)

use std::sync::Mutex;

/// Runs `f(state, item)` for every item, in parallel on candle's CPU worker pool
/// ([`candle_core::utils::barrier_pool`]), with one `init()` state per claimed chunk of
/// items (scratch buffers). Returns after every item has been processed; a panic in `f`
/// is re-raised on the calling thread.
///
/// Items are handed out through per-item slots, each taken once, so every `&mut` inside
/// an item reaches exactly one call of `f` (no unsafe code).
pub(crate) fn for_each_init<I: Send, S>(
    items: Vec<I>,
    init: impl Fn() -> S + Sync,
    f: impl Fn(&mut S, I) + Sync,
) {
    let slots: Vec<Mutex<Option<I>>> = items.into_iter().map(|i| Mutex::new(Some(i))).collect();
    candle_core::utils::barrier_pool().execute_chunked(slots.len(), |range| {
        let mut state = init();
        for slot in &slots[range] {
            // The lock is released before `f` runs, so no panic can poison it; the item
            // is taken either way, since callers rely on every item being processed.
            let item = match slot.lock() {
                Ok(mut g) => g.take(),
                Err(p) => p.into_inner().take(),
            };
            if let Some(item) = item {
                f(&mut state, item);
            }
        }
    });
}

/// Work that [`wide`] runs: a closure, or a kernel's own type whose `run` is
/// `#[inline(always)]` (a closure cannot be marked so, and a large one is not inlined
/// into the function compiled for the wider instructions).
pub(crate) trait Wide {
    /// What the work returns.
    type Out;
    /// Does the work.
    fn run(self) -> Self::Out;
}

impl<R, F: FnOnce() -> R> Wide for F {
    type Out = R;
    #[inline(always)]
    fn run(self) -> R {
        self()
    }
}

/// Runs `w` inside a function compiled for AVX-512 (or AVX2 with FMA) where the CPU has
/// them, so that the loops of `w`, inlined there, are vectorised at that width (the
/// crate builds for baseline x86-64, SSE2). No floating-point contraction or
/// reassociation is enabled, so the results are the same bits as without.
#[inline]
pub(crate) fn wide<W: Wide>(w: W) -> W::Out {
    #[cfg(target_arch = "x86_64")]
    {
        #[target_feature(enable = "avx512f,avx512dq,avx512vl,avx512bw,fma")]
        fn avx512<W: Wide>(w: W) -> W::Out {
            w.run()
        }
        #[target_feature(enable = "avx2,fma")]
        fn avx2<W: Wide>(w: W) -> W::Out {
            w.run()
        }
        use std::arch::is_x86_feature_detected as has;
        if has!("avx512f")
            && has!("avx512dq")
            && has!("avx512vl")
            && has!("avx512bw")
            && has!("fma")
        {
            // SAFETY: the CPU has the features the function was compiled for.
            return unsafe { avx512(w) };
        }
        if has!("avx2") && has!("fma") {
            // SAFETY: as above.
            return unsafe { avx2(w) };
        }
    }
    w.run()
}
