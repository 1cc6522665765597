//! The rate limiter's arithmetic (see [`RateLimiterConfig`] for the rule). Pure state; the
//! table holds it under its lock and parks blocked callers on a condition variable.
//!
//! Invariant: `inserts` and `samples` only grow (rows ever inserted / ever sampled), so
//! diff = inserts × spi − samples moves up with inserts and down with samples; an insert
//! that is allowed never makes sampling impossible, and vice versa, as long as error_buffer
//! covers the largest batch (checked by `TableConfig::validate`).

use serde::Serialize;

use crate::config::RateLimiterConfig;

#[derive(Clone, Debug)]
pub struct RateLimiter {
    cfg: RateLimiterConfig,
    inserts: u64,
    samples: u64,
    /// Cumulative time callers spent blocked, nanoseconds.
    insert_blocked_ns: u64,
    sample_blocked_ns: u64,
}

/// What server info shows.
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct RateLimiterState {
    pub inserts: u64,
    pub samples: u64,
    pub min_size_to_sample: u64,
    pub samples_per_insert: Option<f64>,
    pub min_diff: f64,
    pub max_diff: f64,
    pub diff: f64,
    pub insert_blocked_s: f64,
    pub sample_blocked_s: f64,
}

impl RateLimiter {
    pub fn new(cfg: RateLimiterConfig) -> Self {
        RateLimiter { cfg, inserts: 0, samples: 0, insert_blocked_ns: 0, sample_blocked_ns: 0 }
    }

    /// Restores counters (after a restart).
    pub fn restore(&mut self, inserts: u64, samples: u64) {
        self.inserts = inserts;
        self.samples = samples;
    }

    fn bounds(&self) -> Option<(f64, f64, f64)> {
        self.cfg.samples_per_insert.map(|spi| {
            let centre = spi * self.cfg.min_size_to_sample as f64;
            (spi, centre - self.cfg.error_buffer, centre + self.cfg.error_buffer)
        })
    }

    fn diff(&self, spi: f64) -> f64 {
        self.inserts as f64 * spi - self.samples as f64
    }

    /// May a batch of rows be inserted now?
    pub fn can_insert(&self) -> bool {
        match self.bounds() {
            None => true,
            Some((spi, _, max)) => self.diff(spi) <= max,
        }
    }

    /// May a minibatch of `rows` be drawn from a table of `size` rows now?
    pub fn can_sample(&self, size: u64, rows: u64) -> bool {
        if size < self.cfg.min_size_to_sample.max(1) {
            return false;
        }
        match self.bounds() {
            None => true,
            Some((spi, min, _)) => self.diff(spi) - rows as f64 >= min,
        }
    }

    pub fn inserted(&mut self, rows: u64) {
        self.inserts += rows;
    }
    pub fn sampled(&mut self, rows: u64) {
        self.samples += rows;
    }
    pub fn insert_blocked(&mut self, ns: u64) {
        self.insert_blocked_ns += ns;
    }
    pub fn sample_blocked(&mut self, ns: u64) {
        self.sample_blocked_ns += ns;
    }
    pub fn counts(&self) -> (u64, u64) {
        (self.inserts, self.samples)
    }

    pub fn state(&self) -> RateLimiterState {
        let (min, max, diff) = match self.bounds() {
            Some((spi, min, max)) => (min, max, self.diff(spi)),
            None => (f64::NEG_INFINITY, f64::INFINITY, 0.0),
        };
        RateLimiterState {
            inserts: self.inserts,
            samples: self.samples,
            min_size_to_sample: self.cfg.min_size_to_sample,
            samples_per_insert: self.cfg.samples_per_insert,
            min_diff: min,
            max_diff: max,
            diff,
            insert_blocked_s: self.insert_blocked_ns as f64 * 1e-9,
            sample_blocked_s: self.sample_blocked_ns as f64 * 1e-9,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn limiter(min: u64, spi: Option<f64>, buf: f64) -> RateLimiter {
        RateLimiter::new(RateLimiterConfig { min_size_to_sample: min, samples_per_insert: spi, error_buffer: buf })
    }

    #[test]
    fn blocks_samples_until_min_size_reached() {
        let l = limiter(100, None, 0.0);
        assert!(!l.can_sample(99, 1));
        assert!(l.can_sample(100, 1));
        assert!(l.can_insert());
    }

    #[test]
    fn ratio_band_blocks_the_side_that_runs_ahead() {
        // spi 2, min size 10: centre 20, band [20 − 8, 20 + 8] = [12, 28].
        let mut l = limiter(10, Some(2.0), 8.0);
        l.inserted(10); // diff 20
        assert!(l.can_sample(10, 8)); // 20 − 8 = 12 ≥ 12
        assert!(!l.can_sample(10, 9)); // would fall below the band
        l.sampled(8); // diff 12
        assert!(!l.can_sample(10, 1));
        l.inserted(8); // diff 28
        assert!(l.can_insert()); // 28 ≤ 28
        l.inserted(1); // diff 30
        assert!(!l.can_insert(), "inserts wait for the learner");
        l.sampled(4); // diff 26
        assert!(l.can_insert());
        let s = l.state();
        assert_eq!((s.inserts, s.samples, s.diff, s.min_diff, s.max_diff), (19, 12, 26.0, 12.0, 28.0));
    }
}
