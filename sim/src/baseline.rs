//! A hand-written reactive driver (no learning): steer towards the side with more room, slow
//! down when the way ahead closes. It gives demos and tests a sensible non-random trajectory and
//! is a floor that learned policies should beat on EQS/EES. It is not from the paper.

/// The smallest range within ±0.3 rad of the heading, and the turn command towards the side
/// with more room (hard over when the way ahead closes to 2 m).
fn front_and_turn(ranges_m: &[f32], beam_angles_rad: &[f64], max_range_m: f64) -> (f64, f32) {
    let mut left = 0.0f64;
    let mut right = 0.0f64;
    let mut front = max_range_m;
    for (r, a) in ranges_m.iter().zip(beam_angles_rad) {
        let r = *r as f64;
        if a.abs() < 0.3 {
            front = front.min(r);
        }
        if *a > 0.0 {
            left += r * a.sin();
        } else {
            right -= r * a.sin();
        }
    }
    let turn = ((left - right) / (left + right).max(1e-6)).clamp(-1.0, 1.0);
    let turn = if front < 2.0 { turn.signum() } else { turn };
    (front, turn as f32)
}

/// Speed command that is full with 3 m of room ahead and stops at 0.6 m.
fn approach_speed(front_m: f64) -> f32 {
    (2.0 * ((front_m - 0.6) / 2.4).clamp(0.0, 1.0) - 1.0) as f32
}

/// Action in [−1, 1]² from measured ranges (metres) at beam angles relative to the heading.
pub fn wander(ranges_m: &[f32], beam_angles_rad: &[f64], max_range_m: f64) -> [f32; 2] {
    let (front, turn) = front_and_turn(ranges_m, beam_angles_rad, max_range_m);
    [approach_speed(front), turn]
}

/// The same steering as [`wander`] at a set speed, `speed_fraction` of v_max (slowing only when
/// the way ahead closes to 1.5 m): a scripted driver at the paper's speeds, whose per-step reward
/// shows what a world pays for driving (`sim/tests/paper_worlds.rs`).
pub fn cruise(ranges_m: &[f32], beam_angles_rad: &[f64], max_range_m: f64, speed_fraction: f64) -> [f32; 2] {
    let (front, turn) = front_and_turn(ranges_m, beam_angles_rad, max_range_m);
    let wanted = 2.0 * speed_fraction.clamp(0.0, 1.0) - 1.0;
    let speed = if front < 1.5 { f64::from(approach_speed(front)).min(wanted) } else { wanted };
    // Half the steering while the way ahead is open: less weaving, less ω² penalty.
    let turn = if front > 3.0 { 0.5 * turn } else { turn };
    [speed as f32, turn]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn turns_towards_open_side_and_slows_for_walls() {
        let angles = [-1.0, 0.0, 1.0];
        // Open on the left (positive angles).
        let a = wander(&[1.0, 12.0, 12.0], &angles, 12.0);
        assert!(a[1] > 0.0 && a[0] == 1.0);
        // Wall 0.5 m ahead: stop, turn hard.
        let a = wander(&[3.0, 0.5, 1.0], &angles, 12.0);
        assert_eq!(a, [-1.0, -1.0]);
    }
}
