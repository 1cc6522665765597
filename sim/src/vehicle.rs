//! Kinematic bicycle model of the XTENTH-CAR (paper eqs. 13–16):
//!
//! ```text
//!   β = atan(l_r / (l_f + l_r) · tan δ)
//!   ẋ = v cos(ψ + β)     ẏ = v sin(ψ + β)     ψ̇ = v / l_r · sin β
//! ```
//!
//! The agent commands (v, ω); steering follows from δ = atan(ω L / v), clipped to ±δ_max.
//! Controls are held for a step (zero-order hold), and with v and δ constant the equations
//! have a closed-form solution — a circle of radius l_r / sin β (a line when β = 0) — so we
//! integrate exactly: the pose after a step does not depend on how the step is cut. Sub-steps
//! exist only for collision checks (no obstacle thinner than `max_substep_m` is jumped).

use crate::config::VehicleConfig;

/// Pose of the centre of mass.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Pose {
    pub x_m: f64,
    pub y_m: f64,
    pub heading_rad: f64,
}

/// Physical command derived from a normalised action.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Command {
    /// Commanded linear speed v.
    pub v_mps: f64,
    /// Commanded angular velocity ω (what the reward penalises).
    pub omega_radps: f64,
    /// Steering angle δ actually applied, after the limit.
    pub steer_rad: f64,
}

impl VehicleConfig {
    /// Maps a ∈ [−1, 1]² (clipped) to (v, ω) and the steering angle that realises ω.
    #[inline]
    pub fn command(&self, a_speed: f32, a_turn: f32) -> Command {
        let a1 = (a_speed as f64).clamp(-1.0, 1.0);
        let a2 = (a_turn as f64).clamp(-1.0, 1.0);
        let v = self.v_max_mps * (a1 + 1.0) / 2.0;
        let omega = self.omega_max_radps * a2;
        // atan2 handles v = 0 (steer to the limit; the car does not move anyway).
        let steer = (omega * self.wheelbase_m).atan2(v).clamp(-self.max_steer_rad, self.max_steer_rad);
        Command { v_mps: v, omega_radps: omega, steer_rad: steer }
    }

    /// Distance from the centre of mass to the footprint's corners (m; the default car's
    /// 0.313 m): the car fits wherever the centre is this far from every surface, whatever its
    /// heading.
    pub fn circumradius_m(&self) -> f64 {
        (self.length_m / 2.0).hypot(self.width_m / 2.0)
    }

    /// Slip angle β for steering δ (eq. 16).
    #[inline]
    pub fn slip_rad(&self, steer_rad: f64) -> f64 {
        (self.lr_m / self.wheelbase_m * steer_rad.tan()).atan()
    }

    /// Pose after `t_s` seconds at constant (v, δ), exact solution of eqs. 13–15.
    #[inline]
    pub fn advance(&self, p: Pose, v_mps: f64, steer_rad: f64, t_s: f64) -> Pose {
        let beta = self.slip_rad(steer_rad);
        let yaw_rate = v_mps / self.lr_m * beta.sin();
        let phi0 = p.heading_rad + beta;
        let dpsi = yaw_rate * t_s;
        let (dx, dy) = if dpsi.abs() < 1e-9 {
            // Straight line (limit of the arc; also avoids 0/0).
            let (s, c) = phi0.sin_cos();
            (v_mps * t_s * c, v_mps * t_s * s)
        } else {
            let r = v_mps / yaw_rate; // signed radius of the centre-of-mass path
            let phi1 = phi0 + dpsi;
            (r * (phi1.sin() - phi0.sin()), -r * (phi1.cos() - phi0.cos()))
        };
        Pose { x_m: p.x_m + dx, y_m: p.y_m + dy, heading_rad: wrap_angle(p.heading_rad + dpsi) }
    }

    /// Number of sub-steps for a step at speed `v_mps`.
    #[inline]
    pub fn substeps(&self, v_mps: f64) -> u32 {
        ((v_mps * self.dt_s / self.max_substep_m).ceil() as u32).max(1)
    }

    /// Turning radius of the centre of mass at steering δ (∞ for δ = 0).
    pub fn turning_radius_m(&self, steer_rad: f64) -> f64 {
        self.lr_m / self.slip_rad(steer_rad).sin().abs()
    }

    /// The tightest circle the centre of mass drives, at the steering limit (m; the default
    /// car's 0.774 m). The car cannot reverse, so a passage narrower than this circle and its
    /// footprint is one it cannot turn round in.
    pub fn min_turning_radius_m(&self) -> f64 {
        self.turning_radius_m(self.max_steer_rad)
    }
}

/// Wraps to (−π, π].
#[inline]
pub fn wrap_angle(a: f64) -> f64 {
    let t = std::f64::consts::TAU;
    let mut a = a.rem_euclid(t);
    if a > std::f64::consts::PI {
        a -= t;
    }
    a
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cfg() -> VehicleConfig {
        VehicleConfig::default()
    }

    #[test]
    fn action_maps_to_speed_and_turn_rate() {
        let c = cfg();
        let k = c.command(1.0, 0.0);
        assert_eq!((k.v_mps, k.omega_radps, k.steer_rad), (0.5, 0.0, 0.0));
        let k = c.command(-1.0, 1.0);
        assert_eq!((k.v_mps, k.omega_radps), (0.0, 0.6));
        assert_eq!(k.steer_rad, 0.40); // v = 0 → full lock, clipped
        // a = (0, 0.5): v = 0.25, ω = 0.3, δ = atan(0.3·0.32/0.25) = atan(0.384) = 0.36655 rad.
        let k = c.command(0.0, 0.5);
        assert!((k.steer_rad - 0.384f64.atan()).abs() < 1e-12);
        // Out-of-range actions are clipped.
        assert_eq!(c.command(7.0, -9.0).v_mps, 0.5);
        assert_eq!(c.command(7.0, -9.0).omega_radps, -0.6);
    }

    #[test]
    fn straight_driving_covers_v_times_t_along_the_heading() {
        let c = cfg();
        let p = Pose { x_m: 1.0, y_m: 2.0, heading_rad: std::f64::consts::FRAC_PI_6 };
        let q = c.advance(p, 0.5, 0.0, 10.0);
        // 5 m along 30°: (1 + 5 cos 30°, 2 + 5 sin 30°) = (5.330127, 4.5).
        assert!((q.x_m - (1.0 + 5.0 * 3f64.sqrt() / 2.0)).abs() < 1e-12);
        assert!((q.y_m - 4.5).abs() < 1e-12);
        assert_eq!(q.heading_rad, p.heading_rad);
    }

    #[test]
    fn constant_steering_traces_the_circle_the_equations_give() {
        let c = cfg();
        let delta = 0.3f64;
        // β = atan(0.5 tan 0.3) = atan(0.154668) = 0.153451; R = l_r / sin β = 0.16 / 0.152850 = 1.046777 m.
        let beta = (0.5 * delta.tan()).atan();
        let r_expected = 0.16 / beta.sin();
        assert!((c.turning_radius_m(delta) - r_expected).abs() < 1e-12);
        assert!((r_expected - 1.046777).abs() < 1e-5);
        // At the 0.40 rad limit: β = atan(0.5 tan 0.4) = 0.208329, R = 0.16 / sin β = 0.773598 m.
        assert!((c.min_turning_radius_m() - 0.773598).abs() < 1e-5, "{}", c.min_turning_radius_m());
        assert!((c.circumradius_m() - 0.275f64.hypot(0.15)).abs() < 1e-12);
        // Integrate in many small steps; every point lies on one circle of that radius, and a
        // full revolution (2πR / v seconds) returns to the start.
        let p0 = Pose { x_m: 0.0, y_m: 0.0, heading_rad: 0.0 };
        // Centre of the circle: left of the velocity direction ψ + β at distance R.
        let (cx, cy) = (-r_expected * beta.sin(), r_expected * beta.cos());
        let v = 0.5;
        let period = std::f64::consts::TAU * r_expected / v;
        let n = 1000;
        let mut p = p0;
        for _ in 0..n {
            p = c.advance(p, v, delta, period / n as f64);
            let r = (p.x_m - cx).hypot(p.y_m - cy);
            assert!((r - r_expected).abs() < 1e-9, "off the circle: {r}");
        }
        assert!(p.x_m.abs() < 1e-9 && p.y_m.abs() < 1e-9, "{p:?}");
    }

    #[test]
    fn result_does_not_depend_on_how_a_step_is_cut() {
        let c = cfg();
        let p = Pose { x_m: 0.3, y_m: -0.2, heading_rad: 1.0 };
        let one = c.advance(p, 0.4, -0.25, 0.1);
        let mut many = p;
        for _ in 0..10 {
            many = c.advance(many, 0.4, -0.25, 0.01);
        }
        assert!((one.x_m - many.x_m).abs() < 1e-12 && (one.y_m - many.y_m).abs() < 1e-12);
        assert!((one.heading_rad - many.heading_rad).abs() < 1e-12);
    }
}
