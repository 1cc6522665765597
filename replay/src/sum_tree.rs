//! A sum tree over a fixed number of slots: set a slot's weight and draw a slot with
//! probability weight / total, both in O(log n). The prioritised sampler's core (Schaul et al.
//! 2016, appendix B.2.1); with all weights 1 it is also the uniform sampler, so removing an
//! item (max_times_sampled) is the same O(log n) write for both.
//!
//! ```text
//!   nodes[1] = total          nodes[i] = nodes[2i] + nodes[2i+1]
//!   leaves at nodes[size + slot], size = next power of two ≥ capacity
//! ```

#[derive(Clone, Debug)]
pub struct SumTree {
    size: usize,
    nodes: Vec<f64>,
}

impl SumTree {
    pub fn new(capacity: usize) -> Self {
        let size = capacity.max(1).next_power_of_two();
        SumTree { size, nodes: vec![0.0; 2 * size] }
    }

    pub fn total(&self) -> f64 {
        self.nodes[1]
    }

    pub fn get(&self, slot: usize) -> f64 {
        self.nodes[self.size + slot]
    }

    /// Sets a slot's weight (≥ 0, finite). O(log n).
    pub fn set(&mut self, slot: usize, weight: f64) {
        debug_assert!(weight >= 0.0 && weight.is_finite());
        let mut i = self.size + slot;
        let delta = weight - self.nodes[i];
        if delta == 0.0 {
            return;
        }
        self.nodes[i] = weight;
        // Recompute sums on the way up instead of adding `delta`: no drift from rounding.
        while i > 1 {
            i /= 2;
            self.nodes[i] = self.nodes[2 * i] + self.nodes[2 * i + 1];
        }
    }

    /// Sets slots `start..end` to `weight` (≥ 0, finite) and recomputes their ancestors level
    /// by level: O((end − start) + log n) instead of O((end − start) · log n) for one `set` per
    /// slot, with the same result (every sum is recomputed from its children). Does nothing
    /// when every slot already has that weight. `end` ≤ capacity.
    pub fn set_range(&mut self, start: usize, end: usize, weight: f64) {
        debug_assert!(weight >= 0.0 && weight.is_finite());
        debug_assert!(start <= end && end <= self.size);
        let leaves = &mut self.nodes[self.size + start..self.size + end];
        if leaves.iter().all(|&w| w == weight) {
            return;
        }
        leaves.fill(weight);
        let (mut lo, mut hi) = (self.size + start, self.size + end - 1);
        while lo > 1 {
            lo /= 2;
            hi /= 2;
            for i in lo..=hi {
                self.nodes[i] = self.nodes[2 * i] + self.nodes[2 * i + 1];
            }
        }
    }

    /// The slot whose cumulative-weight interval holds `u` (0 ≤ u < total). Never returns a
    /// zero-weight slot while the total is positive.
    pub fn find(&self, mut u: f64) -> usize {
        let mut i = 1;
        while i < self.size {
            let left = self.nodes[2 * i];
            // Go right when u is past the left mass, or when the left subtree is empty (guards
            // against u == total after rounding).
            if u >= left && self.nodes[2 * i + 1] > 0.0 || left <= 0.0 {
                u -= left;
                i = 2 * i + 1;
            } else {
                i *= 2;
            }
        }
        i - self.size
    }

    /// Bytes held.
    pub fn memory_bytes(&self) -> usize {
        self.nodes.len() * std::mem::size_of::<f64>()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn totals_follow_updates_and_find_walks_the_cumulative_weights() {
        let mut t = SumTree::new(5);
        for (s, w) in [1.0, 2.0, 0.0, 3.0, 4.0].into_iter().enumerate() {
            t.set(s, w);
        }
        assert_eq!(t.total(), 10.0);
        // Cumulative: [0,1) → 0, [1,3) → 1, slot 2 empty, [3,6) → 3, [6,10) → 4.
        assert_eq!(t.find(0.0), 0);
        assert_eq!(t.find(0.99), 0);
        assert_eq!(t.find(1.0), 1);
        assert_eq!(t.find(2.99), 1);
        assert_eq!(t.find(3.0), 3);
        assert_eq!(t.find(9.99), 4);
        assert_eq!(t.find(10.0), 4, "u at the total stays on a non-empty slot");
        t.set(4, 0.0);
        assert_eq!(t.total(), 6.0);
        assert_eq!(t.find(5.99), 3);
    }

    #[test]
    fn range_updates_give_exactly_the_tree_of_single_updates() {
        let mut one = SumTree::new(37);
        let mut range = SumTree::new(37);
        for (start, end, w) in [(0, 37, 1.0), (5, 9, 0.25), (30, 37, 3.5), (0, 1, 0.0), (12, 12, 9.0), (8, 33, 1.0 / 3.0)] {
            for slot in start..end {
                one.set(slot, w);
            }
            range.set_range(start, end, w);
            assert_eq!(one.nodes, range.nodes, "after {start}..{end} = {w}");
        }
    }

    #[test]
    fn zero_weight_slots_are_never_found() {
        let mut t = SumTree::new(8);
        t.set(7, 1.0);
        for k in 0..100 {
            assert_eq!(t.find(k as f64 / 100.0), 7);
        }
    }
}
