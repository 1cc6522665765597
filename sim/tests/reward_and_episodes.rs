//! Rewards, episode ends, starts, determinism and the vectorised API, against hand-worked values.

use std::sync::Arc;

use mapless_sim::{Env, EnvConfig, Map, Pose, RewardConfig, VecEnv, VecStep, World};

fn world(map: &str, cfg: EnvConfig) -> Arc<World> {
    if map == "box" {
        return World::new(empty_box(), cfg).unwrap();
    }
    World::new(Map::builtin(map).unwrap(), cfg).unwrap()
}

/// An empty 25 m walled box (what env1 was before it got its interior walls): geometry with
/// hand-worked distances.
fn empty_box() -> Map {
    let text = "format: mapless-vector-map/v1\nname: box\nbounds: { min: [-12.5, -12.5], max: [12.5, 12.5] }\nboundary_walls: true\nobstacles: []\n";
    Map::from_vector_yaml(text, std::path::Path::new("box.yaml")).unwrap()
}

fn noiseless() -> EnvConfig {
    let mut c = EnvConfig::default();
    c.sensor.noise_std_m = 0.0;
    c
}

#[test]
fn exploration_reward_is_equation_1() {
    let r = RewardConfig::exploration();
    // R = 0.0075 r² + 1.5 v² − 0.6 ω²: r = 4, v = 0.5, ω = 0.3 → 0.12 + 0.375 − 0.054 = 0.441.
    assert!((r.reward(4.0, 0.5, 0.3) - 0.441).abs() < 1e-12);
    // Bands of eq. (2) do not apply to eq. (1).
    assert!((r.reward(0.5, 0.0, 0.0) - 0.001875).abs() < 1e-12);
}

#[test]
fn search_and_rescue_reward_is_equation_2() {
    let r = RewardConfig::search_and_rescue();
    // 2.0 < r = 2.2 < 2.5: eq. 1 (0.0363 + 0.375 − 0) + 2.0 = 2.4113.
    assert!((r.reward(2.2, 0.5, 0.0) - 2.4113).abs() < 1e-12);
    // r = 0.8 < 1.0: 0.0048 + 0.375 − 50 = −49.6202.
    assert!((r.reward(0.8, 0.5, 0.0) - (-49.6202)).abs() < 1e-12);
    // Band edges are strict: r = 2.0 and r = 1.0 get no bonus or penalty.
    assert!((r.reward(2.0, 0.0, 0.0) - 0.03).abs() < 1e-12);
    assert!((r.reward(1.0, 0.0, 0.0) - 0.0075).abs() < 1e-12);
    assert!(RewardConfig::preset("nope").is_err());
}

#[test]
fn observation_holds_both_scans_last_action_and_reward() {
    let w = world("box", noiseless());
    let mut env = Env::new(Arc::clone(&w), 1);
    let d = w.obs_dim();
    assert_eq!(d, 17);
    let mut obs = vec![0.0; d];
    // Centre of the box facing +x: the middle beam (0 rad) sees the wall at 12.5 m → beyond 12 m → max.
    env.reset_to(Pose { x_m: 0.0, y_m: 0.0, heading_rad: 0.0 }, &mut obs);
    assert_eq!(&obs[0..7], &obs[7..14], "at reset both scans are the first scan");
    assert_eq!(&obs[14..17], &[0.0, 0.0, 0.0]);
    assert_eq!(obs[3], 1.0); // 12 m (a miss) normalises to +1
    // Outer beams at ±3π/8 hit y = ±12.5 at 12.5 / sin(3π/8) = 13.53 m: also misses.
    let mut next = vec![0.0; d];
    // Full speed straight: v = 0.5, ω = 0.
    let o = env.step([1.0, 0.0], &mut next).unwrap();
    assert_eq!(&next[7..14], &obs[0..7], "previous scan moves to the second block");
    assert_eq!(next[14], 0.5);
    assert_eq!(next[15], 0.0);
    assert_eq!(next[16], o.reward);
    // Every beam reads 12 m (all walls ≥ 12.45 m away): R = 0.0075·144 + 1.5·0.25 = 1.455.
    assert!((o.reward - 1.455).abs() < 1e-6, "{}", o.reward);
    assert!(!o.terminal && !o.truncated);
}

#[test]
fn ranges_to_a_known_wall_match_the_geometry() {
    let w = world("box", noiseless());
    let mut env = Env::new(Arc::clone(&w), 1);
    let mut obs = vec![0.0; w.obs_dim()];
    // 4.5 m from the east wall (x = 12.5), facing it.
    env.reset_to(Pose { x_m: 8.0, y_m: 0.0, heading_rad: 0.0 }, &mut obs);
    let r = env.ranges_m();
    assert!((r[3] - 4.5).abs() < 1e-4, "{r:?}");
    // Beam k at angle θ_k = −3π/8 + kπ/8: distance to x = 12.5 is 4.5 / cos θ_k while ≤ 12.
    for (k, &rk) in r.iter().enumerate() {
        let theta = -3.0 * std::f64::consts::PI / 8.0 + k as f64 * std::f64::consts::PI / 8.0;
        let expect = (4.5 / theta.cos()).min(12.0);
        assert!((rk as f64 - expect).abs() < 1e-4, "beam {k}: {rk} vs {expect}");
    }
    // Normalised: 2·4.5/12 − 1 = −0.25.
    assert!((obs[3] + 0.25).abs() < 1e-5);
}

#[test]
fn driving_into_a_wall_is_terminal_not_truncated() {
    let w = world("box", noiseless());
    let mut env = Env::new(Arc::clone(&w), 3);
    let mut obs = vec![0.0; w.obs_dim()];
    // Nose 0.5 m from the east wall: centre at 12.5 − 0.275 − 0.5.
    env.reset_to(Pose { x_m: 11.725, y_m: 0.0, heading_rad: 0.0 }, &mut obs);
    let mut steps = 0;
    let outcome = loop {
        let o = env.step([1.0, 0.0], &mut obs).unwrap();
        steps += 1;
        if o.done() {
            break o;
        }
    };
    // 0.05 m per step: the nose reaches the wall during step 10.
    assert_eq!(steps, 10);
    assert!(outcome.terminal && !outcome.truncated);
}

#[test]
fn the_collision_term_is_paid_on_the_colliding_step_only() {
    // The same drive into the east wall, with eq. (1) and with eq. (1) plus `collision`.
    let drive = |collision: f64| {
        let mut cfg = noiseless();
        cfg.reward.collision = collision;
        let w = world("box", cfg);
        let mut env = Env::new(Arc::clone(&w), 3);
        let mut obs = vec![0.0; w.obs_dim()];
        env.reset_to(Pose { x_m: 11.725, y_m: 0.0, heading_rad: 0.0 }, &mut obs);
        let mut rewards = Vec::new();
        loop {
            let o = env.step([1.0, 0.0], &mut obs).unwrap();
            rewards.push(o.reward);
            if o.done() {
                assert!(o.terminal);
                return (rewards, obs[w.obs_dim() - 1]);
            }
        }
    };
    let (plain, _) = drive(0.0);
    let (penalised, last_obs_reward) = drive(-100.0);
    assert_eq!(plain.len(), 10);
    assert_eq!(&plain[..9], &penalised[..9], "no term before the collision");
    assert!((penalised[9] - (plain[9] - 100.0)).abs() < 1e-4, "{} vs {}", penalised[9], plain[9]);
    assert_eq!(last_obs_reward, penalised[9], "the observation's last reward includes it");
    // A bonus for colliding is refused.
    let mut cfg = noiseless();
    cfg.reward.collision = 1.0;
    assert!(cfg.validate().unwrap_err().to_string().contains("reward.collision"));
    cfg.reward.collision = f64::NAN;
    assert!(cfg.validate().is_err());
}

/// What [`drive_straight_then_lap`] records: per step, the reward, what the step added to the
/// EQS (> 0: it entered a new cell) and the observation after it (`observed[0]`: at the reset);
/// the cells visited and the EQS at the end.
struct Drive {
    rewards: Vec<f32>,
    gained: Vec<u64>,
    observed: Vec<Vec<f32>>,
    cells: u32,
    eqs: u64,
}

/// One drive in the empty box (5 m straight, then a full-lock circle back over its own track)
/// with the given novelty bonuses (per cell, per EQS point, the cap on the points one cell is
/// paid for, the share paid past the cap) and staleness horizon.
fn drive_straight_then_lap(novelty: (f64, f64, f64, f64), staleness_steps: u32) -> Drive {
    let mut cfg = noiseless();
    (cfg.reward.novelty, cfg.reward.novelty_eqs, cfg.reward.novelty_eqs_cap, cfg.reward.novelty_eqs_past_cap) = novelty;
    cfg.observation.staleness_steps = staleness_steps;
    let w = world("box", cfg);
    let mut env = Env::new(Arc::clone(&w), 5);
    let mut obs = vec![0.0; w.obs_dim()];
    env.reset_to(Pose { x_m: -6.0, y_m: 0.3, heading_rad: 0.0 }, &mut obs);
    let (mut rewards, mut new_cell, mut observed) = (Vec::new(), Vec::new(), vec![obs.clone()]);
    for k in 0..400 {
        let (cells, eqs) = (env.tracker().cells_visited(), env.tracker().eqs());
        let o = env.step(if k < 100 { [1.0, 0.0] } else { [1.0, 1.0] }, &mut obs).unwrap();
        assert!(!o.done());
        rewards.push(o.reward);
        let gained = env.tracker().eqs() - eqs;
        assert_eq!(gained > 0, env.tracker().cells_visited() > cells, "step {k}: a new cell adds to the EQS, an old one does not");
        new_cell.push(gained);
        observed.push(obs.clone());
    }
    Drive { rewards, gained: new_cell, observed, cells: env.tracker().cells_visited(), eqs: env.tracker().eqs() }
}

#[test]
fn the_novelty_term_is_paid_on_each_step_that_enters_a_new_cell_only() {
    // The same drive with eq. (1) and with eq. (1) plus `novelty` (per cell) and `novelty_eqs`
    // (per point of EQS), uncapped, capped (`novelty_eqs_cap`) and capped with a share paid
    // past the cap (`novelty_eqs_past_cap`).
    let Drive { rewards: plain, gained, cells, eqs, .. } = drive_straight_then_lap((0.0, 0.0, 0.0, 0.0), 0);
    let Drive { rewards: paid, gained: gained_too, observed, .. } = drive_straight_then_lap((10.0, 0.0, 0.0, 0.0), 0);
    let Drive { rewards: paid_eqs, gained: gained_also, observed: observed_eqs, .. } = drive_straight_then_lap((0.0, 2.0, 0.0, 0.0), 0);
    // Capped at 1.5 points a cell: ring 1 pays 1, every farther ring 1.5.
    let Drive { rewards: capped, gained: gained_capped, .. } = drive_straight_then_lap((0.0, 2.0, 1.5, 0.0), 0);
    // ... and with half of what lies past 1.5 points: ring 2 pays 1.75.
    let Drive { rewards: sloped, gained: gained_sloped, .. } = drive_straight_then_lap((0.0, 2.0, 1.5, 0.5), 0);
    assert!(gained == gained_too && gained == gained_also && gained == gained_capped && gained == gained_sloped, "the terms do not change the drive");
    // 5 m straight from x = −6 crosses cell edges at −4.5 and −2.5; the circle (0.76 m radius)
    // enters a few more and then only cells it has seen.
    let n_new = gained.iter().filter(|&&g| g > 0).count();
    assert_eq!(n_new as u32, cells - 1, "every cell but the start's is entered once");
    assert!(n_new >= 2 && !gained[300..].iter().any(|&g| g > 0), "{gained:?}");
    assert!(gained.iter().any(|&g| g > 1), "a cell beyond the first ring is entered: {gained:?}");
    for (k, (((p, q), q_eqs), g)) in plain.iter().zip(&paid).zip(&paid_eqs).zip(&gained).enumerate() {
        let want = if *g > 0 { p + 10.0 } else { *p };
        assert!((q - want).abs() < 1e-4, "step {k}: {q} against {want}");
        let want_eqs = p + 2.0 * *g as f32;
        assert!((q_eqs - want_eqs).abs() < 1e-4, "step {k}: {q_eqs} against {want_eqs}");
        let want_capped = p + 2.0 * (*g as f32).min(1.5);
        assert!((capped[k] - want_capped).abs() < 1e-4, "step {k}: {} against {want_capped} (capped)", capped[k]);
        let want_sloped = p + 2.0 * ((*g as f32).min(1.5) + 0.5 * (*g as f32 - 1.5).max(0.0));
        assert!((sloped[k] - want_sloped).abs() < 1e-4, "step {k}: {} against {want_sloped} (sloped)", sloped[k]);
        // The observation after step k carries its reward as R_{t−1}, the bonus included.
        assert_eq!((observed[k + 1][16], observed_eqs[k + 1][16]), (*q, *q_eqs), "step {k}");
    }
    // Per point of EQS: the episode's bonus is 2·(EQS − 1), the start's cell (ring 1) unpaid.
    let bonus: f64 = paid_eqs.iter().zip(&plain).map(|(q, p)| f64::from(q - p)).sum();
    assert!((bonus - 2.0 * (eqs - 1) as f64).abs() < 1e-3, "{bonus} against EQS {eqs}");
    // A price for exploring, or no number, is refused.
    for field in ["novelty", "novelty_eqs", "novelty_eqs_cap"] {
        for bad in [-1.0, f64::INFINITY] {
            let mut cfg = noiseless();
            let r = &mut cfg.reward;
            *(match field {
                "novelty" => &mut r.novelty,
                "novelty_eqs" => &mut r.novelty_eqs,
                _ => &mut r.novelty_eqs_cap,
            }) = bad;
            assert!(cfg.validate().unwrap_err().to_string().contains(&format!("reward.{field} ")), "{field} = {bad}");
        }
    }
    // A share past the cap outside [0, 1], or without a cap to be past, is refused.
    for (cap, share) in [(1.5, -0.1), (1.5, 1.5), (1.5, f64::NAN), (0.0, 0.5)] {
        let mut cfg = noiseless();
        (cfg.reward.novelty_eqs_cap, cfg.reward.novelty_eqs_past_cap) = (cap, share);
        assert!(cfg.validate().unwrap_err().to_string().contains("reward.novelty_eqs_past_cap "), "cap {cap}, share {share}");
    }
    let mut cfg = noiseless();
    (cfg.reward.novelty_eqs_cap, cfg.reward.novelty_eqs_past_cap) = (1.5, 1.0);
    cfg.validate().unwrap();
}

#[test]
fn the_staleness_counts_steps_since_the_last_new_cell_and_changes_nothing_else() {
    let Drive { rewards: rewards_without, gained, observed: without, .. } = drive_straight_then_lap((0.0, 0.0, 0.0, 0.0), 0);
    let Drive { rewards: rewards_with, gained: gained_too, observed: with, .. } = drive_straight_then_lap((0.0, 0.0, 0.0, 0.0), 50);
    assert_eq!((&gained, &rewards_without), (&gained_too, &rewards_with), "the value only observes");
    assert_eq!((without[0].len(), with[0].len()), (17, 18), "one value appended");
    let mut k_since = 0u32;
    for (t, (a, b)) in without.iter().zip(&with).enumerate() {
        assert_eq!(&b[..17], &a[..], "step {t}: the rest of the observation is as without it");
        if t > 0 {
            k_since = if gained[t - 1] > 0 { 0 } else { k_since + 1 };
        }
        assert_eq!(b[17], k_since.min(50) as f32 / 50.0, "step {t}");
    }
    // The lap over its own track (the last 100 steps enter nothing) saturates at 1.
    assert_eq!(with.last().unwrap()[17], 1.0);
    assert!(with.iter().any(|o| o[17] > 0.0 && o[17] < 1.0), "it passes through values between");
    // Its mirror image keeps it (the mirrored drive enters the same cells).
    let mut cfg = noiseless();
    cfg.observation.staleness_steps = 50;
    let mut mirrored = vec![0.0; 18];
    let last = with.last().unwrap();
    cfg.mirror_obs(last, &mut mirrored);
    assert_eq!((mirrored[17], mirrored[15]), (last[17], -last[15]));
}

#[test]
fn the_start_offset_points_at_the_start_in_the_cars_frame_and_changes_nothing_else() {
    // Straight ahead for 40 steps, then a hard left turn (a₂ = 1): the start falls behind, then
    // off to the side, at hand-worked bearings from the pose.
    let drive = |l: f64| {
        let mut cfg = noiseless();
        cfg.observation.start_offset_m = l;
        let w = world("box", cfg);
        let mut env = Env::new(Arc::clone(&w), 3);
        let mut obs = vec![0.0; w.obs_dim()];
        env.reset_to(Pose { x_m: -3.0, y_m: -2.0, heading_rad: 0.0 }, &mut obs);
        let mut seen = vec![(obs.clone(), env.pose(), 0.0f32)];
        for t in 0..80 {
            let o = env.step([1.0, if t < 40 { 0.0 } else { 1.0 }], &mut obs).unwrap();
            assert!(!o.done(), "step {t}: the box has room for the drive");
            seen.push((obs.clone(), env.pose(), o.reward));
        }
        seen
    };
    let (without, with) = (drive(0.0), drive(8.0));
    assert_eq!((without[0].0.len(), with[0].0.len()), (17, 19), "two values appended");
    for (t, ((a, pa, ra), (b, pb, rb))) in without.iter().zip(&with).enumerate() {
        assert_eq!((&b[..17], pb, rb), (&a[..], pa, ra), "step {t}: the drive, the rest of the observation and the reward are as without it");
        let (dx, dy) = (-3.0 - pb.x_m, -2.0 - pb.y_m);
        let d = dx.hypot(dy);
        let bearing = dy.atan2(dx) - pb.heading_rad;
        let want = if d > 0.0 { [(d / 8.0).tanh() * bearing.cos(), (d / 8.0).tanh() * bearing.sin()] } else { [0.0, 0.0] };
        assert!((b[17] as f64 - want[0]).abs() < 1e-5 && (b[18] as f64 - want[1]).abs() < 1e-5, "step {t}: {:?} is not {want:?}", &b[17..]);
    }
    // At the start it is 0; straight ahead the start lies straight behind (cos β = −1, sin β = 0).
    assert_eq!(&with[0].0[17..], &[0.0, 0.0]);
    let ahead = &with[40];
    assert!(ahead.0[17] < -0.2 && ahead.0[18].abs() < 1e-6, "{:?}", &ahead.0[17..]);
    // Turning left brings what lay behind to the left (sin β > 0).
    assert!(with[41..].iter().all(|(o, ..)| o[18] > 0.0) && with[80].0[18] > 0.1, "the start is not on the car's left: {:?}", &with[80].0[17..]);
    // Its mirror image: the bearing changes sign, the distance does not.
    let mut cfg = noiseless();
    cfg.observation.start_offset_m = 8.0;
    let mut mirrored = vec![0.0; 19];
    cfg.mirror_obs(&with[80].0, &mut mirrored);
    assert_eq!((mirrored[17], mirrored[18]), (with[80].0[17], -with[80].0[18]));
    for bad in [-1.0, f64::NAN, f64::INFINITY] {
        cfg.observation.start_offset_m = bad;
        assert!(cfg.validate().unwrap_err().to_string().contains("observation.start_offset_m"), "{bad}");
    }
}

#[test]
fn reaching_max_steps_is_truncated_not_terminal() {
    let mut cfg = noiseless();
    cfg.episode.max_steps = 25;
    let w = world("box", cfg);
    let mut env = Env::new(Arc::clone(&w), 4);
    let mut obs = vec![0.0; w.obs_dim()];
    env.reset_to(Pose { x_m: 0.0, y_m: 0.0, heading_rad: 0.0 }, &mut obs);
    for k in 1..=25 {
        // Standing still (v = 0) can never collide.
        let o = env.step([-1.0, 0.0], &mut obs).unwrap();
        assert_eq!(o.truncated, k == 25);
        assert!(!o.terminal);
    }
}

/// Long episodes (`episode.long_share`): that share of `reset`'s episodes runs to
/// `long_max_steps`, the rest to `max_steps`; a start placed by `reset_to` keeps `max_steps`.
#[test]
fn long_episodes_run_to_their_limit_in_their_share() {
    let limit_of = |env: &mut Env, obs: &mut [f32]| {
        // Standing still (v = 0) never collides: the episode ends on its limit.
        (1..=100u32).find(|_| env.step([-1.0, 0.0], obs).unwrap().truncated).unwrap_or(0)
    };
    let limits = |share: f64, n: usize| {
        let mut cfg = noiseless();
        (cfg.episode.max_steps, cfg.episode.long_max_steps, cfg.episode.long_share) = (5, 12, share);
        let w = world("box", cfg);
        let mut env = Env::new(Arc::clone(&w), 9);
        let mut obs = vec![0.0; w.obs_dim()];
        let mut seen = Vec::new();
        for _ in 0..n {
            env.reset(&mut obs).unwrap();
            seen.push(limit_of(&mut env, &mut obs));
        }
        env.reset_to(Pose { x_m: 0.0, y_m: 0.0, heading_rad: 0.0 }, &mut obs);
        (seen, limit_of(&mut env, &mut obs))
    };
    let (none, placed) = limits(0.0, 400);
    assert!(none.iter().all(|&l| l == 5) && placed == 5, "share 0: every episode runs to max_steps");
    let (all, placed) = limits(1.0, 400);
    assert!(all.iter().all(|&l| l == 12) && placed == 5, "share 1: every reset's episode is long, reset_to's is not");
    let (some, _) = limits(0.3, 2000);
    let long = some.iter().filter(|&&l| l == 12).count() as f64 / 2000.0;
    assert!(some.iter().all(|&l| l == 5 || l == 12));
    assert!((long - 0.3).abs() < 4.0 * (0.3f64 * 0.7 / 2000.0).sqrt(), "long share {long}");
    let mut bad = noiseless();
    bad.episode.long_share = 1.5;
    assert!(bad.validate().unwrap_err().to_string().contains("episode.long_share"));
    (bad.episode.long_share, bad.episode.long_max_steps) = (0.5, bad.episode.max_steps);
    assert!(bad.validate().unwrap_err().to_string().contains("episode.long_max_steps"));
    bad.episode.long_share = 0.0;
    bad.validate().expect("without long episodes their limit is not looked at");
}

#[test]
fn collision_on_the_last_step_is_terminal_only() {
    let mut cfg = noiseless();
    cfg.episode.max_steps = 10;
    let w = world("box", cfg);
    let mut env = Env::new(Arc::clone(&w), 5);
    let mut obs = vec![0.0; w.obs_dim()];
    env.reset_to(Pose { x_m: 11.725, y_m: 0.0, heading_rad: 0.0 }, &mut obs);
    let mut last = None;
    for _ in 0..10 {
        last = Some(env.step([1.0, 0.0], &mut obs).unwrap());
    }
    let o = last.unwrap();
    assert!(o.terminal && !o.truncated);
}

#[test]
fn random_starts_are_never_in_collision_and_keep_clearance() {
    for map in ["env1", "env2", "env3", "outdoor20"] {
        let w = world(map, EnvConfig::default());
        let mut env = Env::new(Arc::clone(&w), 11);
        let mut obs = vec![0.0; w.obs_dim()];
        for _ in 0..300 {
            env.reset(&mut obs).unwrap();
            let p = env.pose();
            assert!(w.map.is_free(p.x_m, p.y_m), "{map}: start {p:?} not in free space");
            assert!(!w.collide.footprint_collides(p.x_m, p.y_m, p.heading_rad, &w.footprint), "{map}: {p:?}");
            assert!(w.can_circle_from(p), "{map}: start {p:?} leaves no way on (episode.start_escapable)");
            // Footprint clearance ≥ 0.5 m: every point of the footprint's outline (where the
            // distance to outside obstacles is smallest) is ≥ 0.5 m from every surface.
            let (hl, hw) = (w.footprint.half_length_m, w.footprint.half_width_m);
            let (s, c) = p.heading_rad.sin_cos();
            for k in 0..200 {
                let f = k as f64 / 50.0;
                let (u, v) = match k / 50 {
                    0 => (-hl + 2.0 * hl * f, -hw),
                    1 => (hl, -hw + 2.0 * hw * (f - 1.0)),
                    2 => (hl - 2.0 * hl * (f - 2.0), hw),
                    _ => (-hl, hw - 2.0 * hw * (f - 3.0)),
                };
                let (x, y) = (p.x_m + c * u - s * v, p.y_m + s * u + c * v);
                let d = w.collide.distance_to_nearest(x, y);
                assert!(d >= 0.5 - 1e-5, "{map}: start {p:?}: outline point ({x:.3}, {y:.3}) only {d:.3} m from an obstacle");
            }
        }
    }
}

/// Hard starts (`episode.hard_start_share`): that share of starts faces a surface within
/// `hard_start_within_m`, every start is still valid and escapable, and the rest are uniform.
#[test]
fn hard_starts_face_a_surface_nearby_in_their_share_and_stay_escapable() {
    // Geometry in the empty box: 1.2 m from the south wall, facing it, sees it at 1.2 m; facing
    // along it, the ray 45° to the right meets it at 1.2·√2 = 1.70 m.
    let b = world("box", noiseless());
    let p = Pose { x_m: 0.0, y_m: -12.5 + 1.2, heading_rad: -std::f64::consts::FRAC_PI_2 };
    assert!(b.faces_surface_within(p, 1.5) && !b.faces_surface_within(p, 1.1));
    let along = Pose { heading_rad: 0.0, ..p };
    assert!(!b.faces_surface_within(along, 1.5) && b.faces_surface_within(along, 1.8));
    assert!(!b.faces_surface_within(Pose { heading_rad: std::f64::consts::FRAC_PI_2, ..p }, 1.5));

    let facing_share = |share: f64| {
        let mut cfg = EnvConfig::default();
        cfg.episode.start_clearance_m = 0.1;
        cfg.episode.hard_start_share = share;
        let w = world("env1", cfg);
        let mut env = Env::new(Arc::clone(&w), 3);
        let mut obs = vec![0.0; w.obs_dim()];
        let n = 2000;
        let mut facing = 0;
        for _ in 0..n {
            env.reset(&mut obs).unwrap();
            let p = env.pose();
            assert!(w.is_valid_start(p.x_m, p.y_m, 0.1) && w.can_circle_from(p), "share {share}: start {p:?}");
            facing += usize::from(w.faces_surface_within(p, 1.5));
        }
        facing as f64 / n as f64
    };
    let natural = facing_share(0.0);
    assert!(natural > 0.02 && natural < 0.4, "uniform starts facing a surface within 1.5 m: {natural}");
    assert_eq!(facing_share(1.0), 1.0);
    // Half hard: 0.5 + 0.5 × the uniform share, within four standard errors of 2,000 draws.
    let half = facing_share(0.5);
    let expect = 0.5 + 0.5 * natural;
    assert!((half - expect).abs() < 4.0 * (expect * (1.0 - expect) / 2000.0).sqrt(), "{half} vs {expect}");

    // A map with no hard start says so, naming the rule.
    let mut cfg = noiseless();
    cfg.episode.hard_start_share = 1.0;
    cfg.episode.hard_start_within_m = 0.2;
    cfg.episode.start_attempts = 2000;
    let err = Env::new(world("box", cfg), 1).reset(&mut vec![0.0; b.obs_dim()]).unwrap_err().to_string();
    assert!(err.contains("hard_start_share") && err.contains("0.2 m"), "{err}");
}

/// A start 0.83 m from a wall and facing it keeps the 0.5 m clearance (the centre needs 0.813 m)
/// but has no way on: the car has no reverse, and at full lock its outer front corner still
/// reaches 0.845 m ahead. `episode.start_escapable` keeps such starts out; 0.86 m is escapable.
#[test]
fn a_start_facing_a_wall_too_close_to_turn_is_refused_one_with_room_is_kept() {
    let w = world("box", noiseless());
    let mut obs = vec![0.0; w.obs_dim()];
    let trapped = Pose { x_m: 0.0, y_m: -12.5 + 0.83, heading_rad: -std::f64::consts::FRAC_PI_2 };
    assert!(w.can_circle_from(Pose { y_m: -12.5 + 0.86, ..trapped }));
    assert!(w.is_valid_start(trapped.x_m, trapped.y_m, 0.5), "the clearance rule alone accepts it");
    assert!(!w.can_circle_from(trapped));
    // No action held for the whole episode (speed × turn, a 9 × 9 lattice) avoids the wall.
    let mut env = Env::new(Arc::clone(&w), 5);
    for i in 0..9 {
        for j in 0..9 {
            let a = [-1.0 + 0.25 * i as f32, -1.0 + 0.25 * j as f32];
            env.reset_to(trapped, &mut obs);
            let mut crashed = false;
            for _ in 0..400 {
                let o = env.step(a, &mut obs).unwrap();
                if o.terminal {
                    crashed = true;
                    break;
                }
            }
            // Standing still (a₁ = −1) is the only way not to hit it.
            assert_eq!(crashed, i > 0, "action {a:?}");
        }
    }
    // The same spot facing along the wall, or away from it, has a way on.
    for heading in [0.0, std::f64::consts::FRAC_PI_2, std::f64::consts::PI] {
        assert!(w.can_circle_from(Pose { heading_rad: heading, ..trapped }), "heading {heading}");
    }
    // When no start can be found, the error names the rule only when it is on.
    let mut cfg = noiseless();
    cfg.episode.start_clearance_m = 30.0;
    let err = Env::new(world("box", cfg.clone()), 1).reset(&mut obs).unwrap_err().to_string();
    assert!(err.contains("start_escapable"), "{err}");
    cfg.episode.start_escapable = false;
    let err = Env::new(world("box", cfg), 1).reset(&mut obs).unwrap_err().to_string();
    assert!(!err.contains("start_escapable"), "{err}");
}

#[test]
fn same_seed_same_episode_different_seed_different_episode() {
    let run = |seed: u64| {
        let w = world("env2", EnvConfig::default());
        let mut v = VecEnv::new(w, 4, seed).unwrap();
        let mut out = VecStep::default();
        let mut trace = Vec::new();
        for t in 0..300 {
            let a: Vec<f32> = (0..8).map(|k| ((t * 7 + k * 3) % 11) as f32 / 5.0 - 1.0).collect();
            v.step(&a, &mut out).unwrap();
            trace.extend_from_slice(&out.next_obs);
            trace.extend_from_slice(&out.reward);
        }
        trace
    };
    let a = run(42);
    assert_eq!(a, run(42));
    assert_ne!(a, run(43));
}

#[test]
fn vec_env_resets_finished_vehicles_and_reports_their_episode() {
    let mut cfg = EnvConfig::default();
    cfg.episode.max_steps = 5;
    let w = world("box", cfg);
    let mut v = VecEnv::new(Arc::clone(&w), 3, 9).unwrap();
    let mut out = VecStep::default();
    let still = vec![-1.0f32, 0.0, -1.0, 0.0, -1.0, 0.0];
    for _ in 0..4 {
        v.step(&still, &mut out).unwrap();
        assert!(out.finished.is_empty());
    }
    let before: Vec<f32> = out.next_obs.clone();
    v.step(&still, &mut out).unwrap();
    assert_eq!(out.finished.len(), 3);
    for (i, s) in &out.finished {
        assert_eq!(s.steps, 5);
        assert!(s.truncated && !s.terminal);
        assert_eq!(v.envs()[*i].steps(), 0, "vehicle {i} was reset");
    }
    // After a reset the current observation is a fresh one (last action/reward zero), while
    // next_obs still holds the end of the finished episode.
    let d = w.obs_dim();
    assert_eq!(&v.obs()[d - 3..d], &[0.0, 0.0, 0.0]);
    assert_ne!(&out.next_obs[..], &before[..]);
}

#[test]
fn vec_env_rejects_bad_actions_without_moving_anyone() {
    let w = world("box", EnvConfig::default());
    let mut v = VecEnv::new(w, 2, 1).unwrap();
    let poses: Vec<Pose> = v.envs().iter().map(|e| e.pose()).collect();
    let mut out = VecStep::default();
    let e = v.step(&[1.0, 0.0, f32::NAN, 0.0], &mut out).unwrap_err().to_string();
    assert!(e.contains("vehicle 1"), "{e}");
    assert!(v.step(&[1.0, 0.0], &mut out).is_err(), "wrong length");
    let after: Vec<Pose> = v.envs().iter().map(|e| e.pose()).collect();
    assert_eq!(poses, after);
}

#[test]
fn outdoor_shade_time_accrues_under_canopies() {
    let w = world("outdoor20", noiseless());
    let mut env = Env::new(Arc::clone(&w), 2);
    let mut obs = vec![0.0; w.obs_dim()];
    // Under the canopy of the tree at (−1, 5), 1.2 m east of the trunk, standing still 10 steps.
    env.reset_to(Pose { x_m: 0.2, y_m: 5.0, heading_rad: 0.0 }, &mut obs);
    for _ in 0..10 {
        env.step([-1.0, 0.0], &mut obs).unwrap();
    }
    assert!((env.summary(None).shaded_time_s - 1.0).abs() < 1e-9);
}

#[test]
fn dense_scans_of_100_and_1080_beams_work() {
    for (beams, fov) in [(100usize, std::f64::consts::FRAC_PI_2), (1080, 1.5 * std::f64::consts::PI)] {
        let mut cfg = noiseless();
        cfg.sensor.beams = beams;
        cfg.sensor.fov_rad = fov;
        let w = world("env2", cfg);
        let mut v = VecEnv::new(w, 2, 3).unwrap();
        assert_eq!(v.obs_dim(), 2 * beams + 3);
        let mut out = VecStep::default();
        v.step(&[0.5, 0.1, 0.5, -0.1], &mut out).unwrap();
        assert!(out.next_obs.iter().all(|x| x.is_finite() && *x >= -1.0 && *x <= 1.0 || x.abs() < 100.0));
    }
}
