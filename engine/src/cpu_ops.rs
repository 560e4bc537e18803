//! Helpers shared by the engine's fused CPU ops (candle `CustomOp`s).

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
