//! Order statistics of maps and samples: median, mean and median summaries, used by every
//! stage that reports or thresholds a distribution.

use crate::grid::ScalarMap;
use serde::Serialize;

/// Mean and median of a map's finite values.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct MapSummary {
    /// Mean.
    pub mean: f64,
    /// Median (upper middle value for an even count).
    pub median: f64,
    /// Finite values counted.
    pub pixels: usize,
}

/// The upper median of `values` (the element at index len/2 in `cmp` order), reordering them;
/// `None` when empty.
pub(crate) fn median_by<T: Copy>(
    values: &mut [T],
    cmp: impl FnMut(&T, &T) -> std::cmp::Ordering,
) -> Option<T> {
    if values.is_empty() {
        return None;
    }
    let mid = values.len() / 2;
    Some(*values.select_nth_unstable_by(mid, cmp).1)
}

/// The finite values of `map`, ascending.
pub(crate) fn finite_sorted(map: &ScalarMap) -> Vec<f64> {
    let mut v: Vec<f64> = map
        .data()
        .iter()
        .filter(|v| v.is_finite())
        .map(|v| f64::from(*v))
        .collect();
    v.sort_by(f64::total_cmp);
    v
}

/// Mean and median of the finite values of `map` (NaN for both when there are none).
pub fn summarize(map: &ScalarMap) -> MapSummary {
    summarize_values(map.data().iter().copied())
}

/// [`summarize`] of values gathered in any order (e.g. band by band): mean and median of the
/// finite ones, summed in sorted order so that the result does not depend on the order.
pub fn summarize_values(values: impl IntoIterator<Item = f32>) -> MapSummary {
    let mut v: Vec<f64> = values
        .into_iter()
        .filter(|v| v.is_finite())
        .map(f64::from)
        .collect();
    v.sort_by(f64::total_cmp);
    if v.is_empty() {
        return MapSummary {
            mean: f64::NAN,
            median: f64::NAN,
            pixels: 0,
        };
    }
    MapSummary {
        mean: v.iter().sum::<f64>() / v.len() as f64,
        median: v[v.len() / 2],
        pixels: v.len(),
    }
}

/// The median of `values` (the mean of the two middle ones for an even count; NaN when there
/// are none), as benchmarks report repeated timings.
///
/// # Example
/// ```
/// use photostereo::stats::median;
/// assert_eq!(median(vec![3.0, 1.0, 2.0]), 2.0);
/// assert_eq!(median(vec![4.0, 1.0, 2.0, 3.0]), 2.5);
/// assert!(median(vec![]).is_nan());
/// ```
pub fn median(mut values: Vec<f64>) -> f64 {
    values.sort_by(f64::total_cmp);
    match values.len() {
        0 => f64::NAN,
        n if n % 2 == 1 => values[n / 2],
        n => (values[n / 2 - 1] + values[n / 2]) / 2.0,
    }
}

/// The `q` quantile of `values` by rank, the value at index ⌊(n − 1)·q⌋ in sorted order
/// (no interpolation), found by selection (the slice is reordered); `None` when empty.
///
/// ```
/// use photostereo::stats::quantile_in_place;
/// let mut v = [5.0f32, 1.0, 4.0, 2.0, 3.0];
/// assert_eq!(quantile_in_place(&mut v, 0.99), Some(4.0));
/// assert_eq!(quantile_in_place(&mut v, 1.0), Some(5.0));
/// assert_eq!(quantile_in_place(&mut [], 0.5), None);
/// ```
pub fn quantile_in_place(values: &mut [f32], q: f64) -> Option<f32> {
    if values.is_empty() {
        return None;
    }
    let k = ((values.len() - 1) as f64 * q) as usize;
    let (_, x, _) = values.select_nth_unstable_by(k.min(values.len() - 1), f32::total_cmp);
    Some(*x)
}
