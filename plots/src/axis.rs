//! Axis ranges and tick values on a 1-2-5 × 10^k grid, and their labels. plotters draws the
//! axes; these choose where they start and end (both ends on ticks) and how numbers read.

use std::ops::Range;

use plotters::coord::ranged1d::{DefaultFormatting, KeyPointHint, Ranged};
use plotters::coord::types::RangedCoordf64;

/// An axis from `lo` to `hi` with ticks every `step` (1-2-5 × 10^k), both ends on ticks.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Axis {
    pub lo: f64,
    pub hi: f64,
    pub step: f64,
}

impl Axis {
    /// At most `target` + 2 intervals covering [min, max], the finest 1-2-5 step that allows it;
    /// a degenerate range is widened, and values beyond ±1e300 are cut there.
    pub fn nice(min: f64, max: f64, target: f64) -> Axis {
        let (mut min, mut max) = (min.clamp(-1e300, 1e300), max.clamp(-1e300, 1e300));
        if max.partial_cmp(&min) != Some(std::cmp::Ordering::Greater) {
            let pad = if min.abs() > 1.0 { min.abs() * 0.1 } else { 1.0 };
            (min, max) = (min - pad, min + pad);
        }
        let mut step = nice_step((max - min) / (2.0 * target));
        for _ in 0..64 {
            if (max / step).ceil() - (min / step).floor() <= target + 2.0 {
                break;
            }
            step = nice_step(step * 1.5);
        }
        let lo = (min / step).floor() * step;
        let mut hi = (max / step).ceil() * step;
        if hi <= lo {
            hi = lo + step;
        }
        Axis { lo, hi, step }
    }

    /// The same axis with a step of at least `min` (whole episodes on an episode axis), both
    /// ends still on ticks.
    pub fn min_step(self, min: f64) -> Axis {
        if self.step >= min {
            return self;
        }
        Axis { lo: (self.lo / min).floor() * min, hi: ((self.hi / min).ceil() * min).max((self.lo / min).floor() * min + min), step: min }
    }

    /// Ticks every `step` within [lo, hi] (a finer grid than [`Axis::nice`]'s own; e.g. metres
    /// on a map whose edges are not on the grid).
    pub fn within(lo: f64, hi: f64, step: f64) -> Axis {
        Axis { lo, hi, step }
    }

    /// The tick values, `lo` and `hi` included when they are on the grid.
    pub fn ticks(&self) -> Vec<f64> {
        let first = (self.lo / self.step - 1e-9).ceil();
        let last = (self.hi / self.step + 1e-9).floor();
        let n = last - first;
        if !(n.is_finite() && (0.0..=100.0).contains(&n)) {
            return vec![self.lo, self.hi];
        }
        (0..=n as usize).map(|k| (first + k as f64) * self.step).collect()
    }

    /// The label of tick value `v`: as many decimals as the step needs, no "−0".
    pub fn label(&self, v: f64) -> String {
        minus(self.plain_label(v))
    }

    fn plain_label(&self, v: f64) -> String {
        if v == 0.0 {
            let decimals = (-self.step.log10().floor()).clamp(0.0, 6.0) as usize;
            return if self.step >= 1e-6 && self.lo.abs().max(self.hi.abs()) < 1e6 { format!("{:.decimals$}", 0.0) } else { "0".into() };
        }
        if self.lo.abs().max(self.hi.abs()) >= 1e6 || self.step < 1e-6 {
            return format!("{v:e}");
        }
        let decimals = (-self.step.log10().floor()).clamp(0.0, 6.0) as usize;
        let s = format!("{v:.decimals$}");
        if s.trim_start_matches('-').chars().all(|c| c == '0' || c == '.') { s.trim_start_matches('-').to_string() } else { s }
    }
}

/// The axis as a plotters coordinate whose key points (ticks and grid lines) are exactly
/// [`Axis::ticks`]; values map as on any f64 axis from `lo` to `hi`.
pub(crate) struct Ticked {
    range: RangedCoordf64,
    ticks: Vec<f64>,
}

impl Ticked {
    pub fn new(a: &Axis) -> Ticked {
        Ticked { range: (a.lo..a.hi).into(), ticks: a.ticks() }
    }
}

impl Ranged for Ticked {
    // Labels come from the charts' formatters (`Axis::label`).
    type FormatOption = DefaultFormatting;
    type ValueType = f64;

    fn map(&self, value: &f64, limit: (i32, i32)) -> i32 {
        self.range.map(value, limit)
    }

    fn key_points<H: KeyPointHint>(&self, _hint: H) -> Vec<f64> {
        self.ticks.clone()
    }

    fn range(&self) -> Range<f64> {
        self.range.range()
    }
}

/// The 1-2-5 × 10^k value nearest above `raw`.
pub(crate) fn nice_step(raw: f64) -> f64 {
    if !(raw.is_finite() && raw > 0.0) {
        return 1.0;
    }
    let mag = 10f64.powf(raw.log10().floor());
    let norm = raw / mag;
    let m = if norm <= 1.0 {
        1.0
    } else if norm <= 2.0 {
        2.0
    } else if norm <= 5.0 {
        5.0
    } else {
        10.0
    };
    m * mag
}

/// A typographic minus sign (U+2212) for a leading hyphen.
fn minus(s: String) -> String {
    match s.strip_prefix('-') {
        Some(rest) => format!("\u{2212}{rest}"),
        None => s,
    }
}

/// Short form of a value for labels: integers without decimals, otherwise 4 significant digits.
pub(crate) fn fmt_value(v: f64) -> String {
    minus(plain_value(v))
}

fn plain_value(v: f64) -> String {
    if v.abs() >= 1e6 {
        format!("{v:.3e}")
    } else if v.fract() == 0.0 {
        format!("{v:.0}")
    } else {
        let decimals = (3 - v.abs().max(1e-9).log10().floor() as i32).clamp(0, 6) as usize;
        let s = format!("{v:.decimals$}");
        s.trim_end_matches('0').trim_end_matches('.').to_string()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nice_axes_use_1_2_5_steps() {
        let a = Axis::nice(0.0, 1000.0, 6.0);
        assert_eq!((a.lo, a.hi, a.step), (0.0, 1000.0, 200.0));
        let a = Axis::nice(-37.0, 312.0, 5.0);
        assert_eq!((a.lo, a.hi, a.step), (-100.0, 400.0, 100.0));
        let a = Axis::nice(0.0, 1020.0, 5.0);
        assert_eq!((a.lo, a.hi, a.step), (0.0, 1200.0, 200.0));
        let a = Axis::nice(0.0, 0.9, 5.0);
        assert_eq!(a.step, 0.2);
        assert_eq!(a.label(0.4 + 0.2), "0.6");
        let a = Axis::nice(5.0, 5.0, 5.0);
        assert!(a.lo < 5.0 && a.hi > 5.0);
        let a = Axis::nice(-f64::MAX, f64::MAX, 5.0);
        assert!(a.lo.is_finite() && a.hi.is_finite() && a.ticks().len() >= 2);
    }

    #[test]
    fn ticks_stay_within_the_axis() {
        assert_eq!(Axis::nice(0.0, 1000.0, 6.0).ticks(), vec![0.0, 200.0, 400.0, 600.0, 800.0, 1000.0]);
        // A map from −12.5 m to 12.5 m with a tick every 5 m.
        assert_eq!(Axis::within(-12.5, 12.5, 5.0).ticks(), vec![-10.0, -5.0, 0.0, 5.0, 10.0]);
        assert_eq!(Axis::within(-10.0, 10.0, 5.0).ticks(), vec![-10.0, -5.0, 0.0, 5.0, 10.0]);
        assert_eq!(Axis::within(0.0, 1.0, 0.5).label(-0.0), "0.0", "no minus zero");
        assert_eq!(Axis::within(-10.0, 10.0, 5.0).label(-0.0), "0");
        assert_eq!(Axis::nice(-1e300, 1e300, 5.0).label(0.0), "0", "not 0e0");
        // Episodes: whole numbers only.
        let a = Axis::nice(0.0, 2.0, 6.0).min_step(1.0);
        assert_eq!((a.lo, a.hi, a.step), (0.0, 2.0, 1.0));
    }

    #[test]
    fn values_print_short() {
        assert_eq!(fmt_value(320.0), "320");
        assert_eq!(fmt_value(312.456), "312.5");
        assert_eq!(fmt_value(-0.5), "\u{2212}0.5", "a minus sign, not a hyphen");
        assert_eq!(Axis::within(-10.0, 10.0, 5.0).label(-5.0), "\u{2212}5");
    }
}
