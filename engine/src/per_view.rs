//! Work done once per view — rendering an image, caching a view's surface samples, decoding a
//! frame — run for a few views at once on the CPU.
//!
//! One view's work is parallel only in its big kernels (the hash encoding, matrix products);
//! between them candle's element-wise ops, the ray marcher and the bookkeeping run on one
//! thread, so a single view keeps two cores about 145 % busy. Two views at a time fill those
//! gaps. Each view's result depends on that view alone, so the outputs are the same, in the
//! same order, as one at a time. On a GPU the views run one at a time (its kernels already
//! fill it, and two views would double its memory).

use std::sync::atomic::{AtomicUsize, Ordering};

use candle_core::Device;
use rayon::prelude::*;

use crate::stages::StageControl;
use crate::{EngineError, Result};

/// Views in flight at once on the CPU: enough to overlap one view's serial stretches with the
/// other's parallel kernels, few enough that memory stays that of a couple of views.
const CPU_VIEWS_AT_ONCE: usize = 2;

/// `work(i)` for every view `i` in `0..n`, in order. Stops with [`EngineError::Cancelled`] when
/// `control` is cancelled (checked before each group of views), and calls `done(k)` each time
/// a view finishes (`k`: views finished so far), for progress reports.
pub fn per_view<T: Send>(
    n: usize,
    device: &Device,
    control: Option<&StageControl>,
    work: impl Fn(usize) -> Result<T> + Sync,
    done: impl Fn(usize) + Sync,
) -> Result<Vec<T>> {
    let at_once = if device.is_cpu() {
        CPU_VIEWS_AT_ONCE
    } else {
        1
    };
    let finished = AtomicUsize::new(0);
    let mut out = Vec::with_capacity(n);
    let views: Vec<usize> = (0..n).collect();
    for group in views.chunks(at_once) {
        if control.is_some_and(|c| c.is_cancelled()) {
            return Err(EngineError::Cancelled);
        }
        let results: Vec<Result<T>> = group
            .par_iter()
            .map(|&i| {
                let r = work(i);
                if r.is_ok() {
                    done(finished.fetch_add(1, Ordering::Relaxed) + 1);
                }
                r
            })
            .collect();
        for r in results {
            out.push(r?);
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn results_keep_the_views_order_and_every_view_is_reported() {
        let reported = AtomicUsize::new(0);
        let out = per_view(
            7,
            &Device::Cpu,
            None,
            |i| Ok(i * i),
            |k| {
                reported.fetch_max(k, Ordering::Relaxed);
            },
        )
        .unwrap();
        assert_eq!(out, vec![0, 1, 4, 9, 16, 25, 36]);
        assert_eq!(reported.load(Ordering::Relaxed), 7);
    }

    #[test]
    fn the_first_error_is_returned_and_cancellation_stops_before_the_next_views() {
        let err = per_view(
            5,
            &Device::Cpu,
            None,
            |i| match i {
                3 => Err(EngineError::config("view", "three")),
                _ => Ok(i),
            },
            |_| {},
        )
        .unwrap_err();
        assert!(err.to_string().contains("three"), "{err}");

        let control = StageControl::default();
        let flag = control.cancel_flag();
        let started = AtomicUsize::new(0);
        let err = per_view(
            10,
            &Device::Cpu,
            Some(&control),
            |i| {
                started.fetch_add(1, Ordering::Relaxed);
                if i == 0 {
                    flag.store(true, Ordering::Relaxed);
                }
                Ok(i)
            },
            |_| {},
        )
        .unwrap_err();
        assert!(matches!(err, EngineError::Cancelled), "{err}");
        // Only the first group ran.
        assert_eq!(started.load(Ordering::Relaxed), CPU_VIEWS_AT_ONCE);
    }
}
