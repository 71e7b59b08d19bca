//! What more than one bench needs. A folder, not `benches/support.rs`, so that cargo does not
//! take it for a bench of its own.

/// The nearest-rank `p`-quantile (0 ≤ p ≤ 1) of `values`, which it sorts in place.
///
/// # Panics
/// When `values` is empty.
pub fn percentile(values: &mut [f64], p: f64) -> f64 {
    values.sort_by(f64::total_cmp);
    values[((values.len() - 1) as f64 * p).round() as usize]
}
