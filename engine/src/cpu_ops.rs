//! Helpers shared by the engine's fused CPU ops (candle `CustomOp`s): contiguous views of
//! storage and a strided matrix product.

use candle_core::{Layout, WithDType};

/// The contiguous window of a CPU storage slice described by `layout`; `what` names the
/// operand in the error (e.g. "mlp: input").
pub fn contiguous_slice<'a, T: WithDType>(
    data: &'a [T],
    layout: &Layout,
    what: &str,
) -> candle_core::Result<&'a [T]> {
    match layout.contiguous_offsets() {
        Some((a, b)) => Ok(&data[a..b]),
        None => candle_core::bail!("{what} must be contiguous"),
    }
}

/// Row-major matrix view: data, row stride, column stride (non-negative).
pub type Mat<'a, T> = (&'a [T], isize, isize);

/// Whether a `rows × cols` matrix with strides `(rs, cs)` lies inside a slice of `len`.
fn fits(len: usize, rows: usize, cols: usize, rs: isize, cs: isize) -> bool {
    rows == 0
        || cols == 0
        || (rs >= 0 && cs >= 0 && ((rows - 1) * rs as usize + (cols - 1) * cs as usize) < len)
}

/// Which threads a product may use.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Threads {
    /// The rayon pool, when the product is large enough to pay for it.
    Pool,
    /// The calling thread alone: the caller is one task of a job already split over the pool.
    One,
}

/// dst[m, n] = (accumulate ? dst : 0) + a[m, k] · b[k, n]; `dst` is row-major with row
/// stride `dst.1` (≥ n), so a product can fill a band of a wider matrix.
#[allow(clippy::too_many_arguments)]
pub fn matmul<T: WithDType>(
    m: usize,
    n: usize,
    k: usize,
    dst: (&mut [T], usize),
    a: Mat<T>,
    b: Mat<T>,
    accumulate: bool,
    threads: Threads,
) {
    let (dst, dst_rs) = dst;
    assert!(
        dst_rs >= n
            && fits(dst.len(), m, n, dst_rs as isize, 1)
            && fits(a.0.len(), m, k, a.1, a.2)
            && fits(b.0.len(), k, n, b.1, b.2),
        "matmul: operands too small for {m}×{k} · {k}×{n}"
    );
    let parallelism = if threads == Threads::Pool && m * n * k > 1 << 16 {
        gemm::Parallelism::Rayon(rayon::current_num_threads())
    } else {
        gemm::Parallelism::None
    };
    // SAFETY: the assertion above checks that every strided extent lies inside its slice,
    // and `dst` is borrowed mutably, so it aliases neither operand.
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            dst.as_mut_ptr(),
            1,
            dst_rs as isize,
            accumulate,
            a.0.as_ptr(),
            a.2,
            a.1,
            b.0.as_ptr(),
            b.2,
            b.1,
            T::one(),
            T::one(),
            false,
            false,
            false,
            parallelism,
        )
    }
}
