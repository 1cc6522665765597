//! The paper's order-W moving average (MATLAB's Episode Manager "average window", W = 50): the
//! one implementation behind the training-curve pictures (`mapless-plots`), the convergence
//! rule (`mapless`'s `protocol::convergence_episode`), and, its newest entry alone
//! ([`trailing_mean`]), the stop rule, progress line and summary of `mapless train`.

/// Order-`window` trailing moving average (first window-1 points average what exists).
///
/// Entry i is the mean of the finite values among `values[i+1-window ..= i]` (fewer at the
/// start); NaN where that range holds no finite value. A `window` of 0 is treated as 1 (the
/// values themselves, non-finite ones as NaN). O(n) for any window: a running sum, recomputed
/// exactly every `window` entries so rounding cannot drift. Entries from `window - 1` on are the
/// full-window averages.
pub fn moving_average(values: &[f64], window: usize) -> Vec<f64> {
    let w = window.max(1);
    let mut out = Vec::with_capacity(values.len());
    let (mut sum, mut count) = (0.0f64, 0usize);
    for (i, &v) in values.iter().enumerate() {
        if v.is_finite() {
            sum += v;
            count += 1;
        }
        if i >= w {
            let old = values[i - w];
            if old.is_finite() {
                sum -= old;
                count -= 1;
            }
        }
        if (i + 1) % w == 0 {
            let (s, c) = values[i + 1 - w..=i].iter().filter(|x| x.is_finite()).fold((0.0, 0), |(s, c), x| (s + x, c + 1));
            sum = s;
            count = c;
        }
        out.push(if count > 0 { sum / count as f64 } else { f64::NAN });
    }
    out
}

/// The newest entry of [`moving_average`] (the order-`window` average now) without the whole
/// series: the mean of the finite values among the last `window` of `values`; NaN when those
/// hold no finite value (or there are none). A `window` of 0 is treated as 1. O(window): reads
/// `values` from the back.
pub fn trailing_mean(values: impl DoubleEndedIterator<Item = f64>, window: usize) -> f64 {
    let (sum, count) = values.rev().take(window.max(1)).filter(|v| v.is_finite()).fold((0.0f64, 0usize), |(s, c), v| (s + v, c + 1));
    if count > 0 { sum / count as f64 } else { f64::NAN }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: &[f64], b: &[f64]) -> bool {
        a.len() == b.len() && a.iter().zip(b).all(|(x, y)| (x.is_nan() && y.is_nan()) || (x - y).abs() < 1e-9)
    }

    #[test]
    fn moving_average_matches_hand_computed_values() {
        let v = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0];
        // Warm-up: 1, (1+2)/2, then full windows (1+2+3)/3, (2+3+4)/3 …
        assert!(close(&moving_average(&v, 3), &[1.0, 1.5, 2.0, 3.0, 4.0, 5.0]));
        assert!(close(&moving_average(&v, 1), &v), "window 1 is the values themselves");
        assert!(close(&moving_average(&v, 0), &v), "window 0 is taken as 1");
        assert!(close(&moving_average(&v, 10), &[1.0, 1.5, 2.0, 2.5, 3.0, 3.5]), "window longer than the data: running mean");
        assert!(close(&moving_average(&[10.0, 0.0, 20.0, -10.0], 2), &[10.0, 5.0, 10.0, 5.0]));
        assert!(moving_average(&[], 50).is_empty());
        // Non-finite values are skipped; a window without finite values gives NaN.
        assert!(close(&moving_average(&[1.0, f64::NAN, 3.0, 5.0], 2), &[1.0, 1.0, 3.0, 4.0]));
        assert!(close(&moving_average(&[f64::NAN, f64::INFINITY, 2.0], 2), &[f64::NAN, f64::NAN, 2.0]));
        // A non-finite value leaves the average once it leaves the window.
        assert!(close(&moving_average(&[f64::NAN, 2.0, 4.0, 6.0], 2), &[f64::NAN, 2.0, 3.0, 5.0]));
    }

    #[test]
    fn trailing_mean_is_the_newest_entry_of_the_moving_average() {
        let series: [&[f64]; 6] = [&[1.0, 2.0, 3.0, 4.0, 5.0, 6.0], &[10.0, 0.0, 20.0, -10.0], &[1.0, f64::NAN, 3.0, 5.0], &[f64::NAN, f64::INFINITY, 2.0], &[f64::NAN, 2.0, 4.0, 6.0], &[7.0]];
        for v in series {
            for w in [0, 1, 2, 3, 10] {
                let newest = moving_average(v, w).last().copied().unwrap();
                assert!(close(&[trailing_mean(v.iter().copied(), w)], &[newest]), "{v:?}, window {w}");
            }
        }
        // By hand: the last three of six; fewer values than the window; none at all.
        assert_eq!(trailing_mean([1.0, 2.0, 3.0, 4.0, 5.0, 6.0].into_iter(), 3), 5.0);
        assert_eq!(trailing_mean([2.0, 4.0].into_iter(), 50), 3.0);
        assert!(trailing_mean(std::iter::empty(), 50).is_nan());
        // Non-finite values are skipped; a window of them alone gives NaN.
        assert_eq!(trailing_mean([1.0, 3.0, f64::NAN].into_iter(), 2), 3.0);
        assert!(trailing_mean([1.0, f64::NAN, f64::INFINITY].into_iter(), 2).is_nan());
    }

    #[test]
    fn moving_average_of_a_long_series_does_not_drift() {
        let v: Vec<f64> = (0..100_000).map(|i| 1e6 + ((i * 7919) % 1000) as f64 * 0.001).collect();
        let w = 50;
        let fast = moving_average(&v, w);
        for i in [0usize, 1, 48, 49, 50, 12_345, 99_998, 99_999] {
            let lo = (i + 1).saturating_sub(w);
            let direct = v[lo..=i].iter().sum::<f64>() / (i + 1 - lo) as f64;
            assert!((fast[i] - direct).abs() < 1e-6, "entry {i}: {} vs {direct}", fast[i]);
        }
    }
}
