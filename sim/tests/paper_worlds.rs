//! The worlds and inferred parameters against what the paper's own numbers imply
//! (docs/simulator.md, "What the paper's numbers imply").

use std::path::Path;
use std::sync::Arc;

use mapless_sim::bounds::reward_bounds;
use mapless_sim::map::Obstacle;
use mapless_sim::paper::{TABLE_III, TABLE_V, env1_per_step_return_band, env2_per_step_return_band};
use mapless_sim::worlds::{DRIVABLE_CELL_M, DRIVE_CLEARANCE_M, DrivableSpace};
use mapless_sim::{Env, EnvConfig, Map, VehicleConfig, World, baseline};

fn world(map: Map) -> Arc<World> {
    World::new(map, EnvConfig::default()).unwrap()
}

/// Mean per-step reward and collisions of the scripted driver at `m_per_step` over `episodes`
/// 1000-step episodes from random starts.
fn scripted(world: &Arc<World>, m_per_step: f64, episodes: u64) -> (f64, u32) {
    let vc = &world.cfg.vehicle;
    let fraction = m_per_step / (vc.v_max_mps * vc.dt_s);
    let angles = world.cfg.sensor.beam_angles_rad();
    let mut obs = vec![0.0; world.obs_dim()];
    let (mut reward, mut steps, mut collisions) = (0.0, 0u64, 0);
    for seed in 0..episodes {
        let mut env = Env::new(Arc::clone(world), seed);
        env.reset(&mut obs).unwrap();
        for _ in 0..1000 {
            let a = baseline::cruise(env.ranges_m(), &angles, world.cfg.sensor.max_range_m, fraction);
            let o = env.step(a, &mut obs).unwrap();
            reward += f64::from(o.reward);
            steps += 1;
            if o.terminal {
                collisions += 1;
                break;
            }
        }
    }
    (reward / steps as f64, collisions)
}

#[test]
fn env1_is_the_papers_25_m_walled_space_with_interior_walls() {
    let m = Map::builtin("env1").unwrap();
    assert_eq!((m.bounds.width(), m.bounds.height()), (25.0, 25.0));
    assert!(m.boundary_walls);
    assert!(m.obstacles.len() >= 2, "interior walls");
}

#[test]
fn standing_still_cannot_earn_the_papers_returns_on_env1_and_driving_is_bounded() {
    let (band_lo, band_hi) = env1_per_step_return_band();
    // A coarse lattice here (the docs' figure, 0.306 and 0.681, is from 0.1 m × 72 headings).
    let b = reward_bounds(&world(Map::builtin("env1").unwrap()), 0.25, 36);
    assert!(b.standing_still_per_step < band_lo, "a parked car earns {:.3} per step, the paper's agents {band_lo}", b.standing_still_per_step);
    // Driving pays at most 0.70 per step: the paper's best (TD3, 0.435) is 62 % of it.
    assert!(b.per_step < 0.70 && b.per_step > band_hi, "{b:?}");
    // The empty 25 m box that env1 used to be: a parked car in the middle reads 12 m on every
    // beam and earns 1.08 per step, three times the paper's agents.
    let text = "format: mapless-vector-map/v1\nname: box\nbounds: { min: [-12.5, -12.5], max: [12.5, 12.5] }\nboundary_walls: true\nobstacles: []\n";
    let empty = Map::from_vector_yaml(text, Path::new("box.yaml")).unwrap();
    let b = reward_bounds(&world(empty), 0.5, 36);
    assert!(b.standing_still_per_step > 1.0, "{b:?}");
}

#[test]
fn a_scripted_driver_at_the_papers_speeds_earns_the_papers_per_step_rewards_on_env1() {
    // Table III's DDPG and TD3 trajectories drive 0.0445 and 0.0471 m per step (d / 1000); their
    // agents earned 0.368 and 0.435 per step. A scripted wall-avoiding driver at those speeds
    // earns inside the paper's band 0.320–0.435, and rarely collides.
    let w = world(Map::builtin("env1").unwrap());
    let (lo, hi) = env1_per_step_return_band();
    for row in [&TABLE_III[0], &TABLE_III[1]] {
        let speed = row.distance_m() / 1000.0;
        let (per_step, collisions) = scripted(&w, speed, 12);
        assert!((lo..=hi).contains(&per_step), "{} at {speed:.4} m/step: {per_step:.3} per step", row.algorithm);
        assert!(collisions <= 1, "{collisions} collisions");
    }
}

#[test]
fn env2_is_the_papers_40_m_walled_space_with_interior_walls_and_obstacles() {
    let m = Map::builtin("env2").unwrap();
    assert_eq!((m.bounds.width(), m.bounds.height()), (40.0, 40.0));
    assert!(m.boundary_walls);
    // Interior walls: at least six stretches 7 m or longer and at most 0.5 m thick (three walls,
    // each cut by two doorways); and the paper's "various obstacles", boxes and round ones.
    let walls = m
        .obstacles
        .iter()
        .filter(|o| match o {
            Obstacle::Box { size, .. } => size[0].max(size[1]) >= 7.0 && size[0].min(size[1]) <= 0.5,
            Obstacle::Wall { from, to, .. } => (to[0] - from[0]).hypot(to[1] - from[1]) >= 7.0,
            _ => false,
        })
        .count();
    assert!(walls >= 6, "{walls} interior wall stretches");
    assert!(m.obstacles.iter().any(|o| matches!(o, Obstacle::Circle { .. })));
    assert!(m.obstacles.iter().filter(|o| matches!(o, Obstacle::Box { size, .. } if size[0].min(size[1]) > 0.5)).count() >= 4);
    // One drivable piece, and every start the sampler draws lies in it.
    let space = DrivableSpace::of(&m, DRIVE_CLEARANCE_M, DRIVABLE_CELL_M);
    assert!(space.is_connected(), "pieces {:?}", space.piece_sizes);
    let w = world(m.clone());
    let mut env = Env::new(Arc::clone(&w), 5);
    let mut obs = vec![0.0; w.obs_dim()];
    for _ in 0..500 {
        env.reset(&mut obs).unwrap();
        let p = env.pose();
        assert_eq!(space.piece_at(p.x_m, p.y_m), Some(0), "start {p:?}");
    }
    // Not cramped: a 2.5 m disc (the car's tightest circle is 1.6 m across) gets from every
    // lane to every other: the doorways and the passages past the blocks are wider than that.
    let wide = DrivableSpace::of(&m, 1.25, DRIVABLE_CELL_M);
    assert!(wide.is_connected(), "pieces {:?}", wide.piece_sizes);
    for y in [-15.0, -5.0, 5.0, 15.0] {
        assert_eq!(wide.piece_at(-18.3, y), Some(0), "lane at y = {y}");
    }
}

#[test]
fn standing_still_cannot_earn_the_papers_returns_on_env2_and_driving_is_bounded() {
    let (band_lo, band_hi) = env2_per_step_return_band();
    // A coarse lattice here (the docs' figure, 0.183 and 0.558, is from 0.1 m × 72 headings).
    let env2 = Map::builtin("env2").unwrap();
    let b = reward_bounds(&world(env2.clone()), 0.25, 36);
    assert!(b.standing_still_per_step < band_lo, "a parked car earns {:.3} per step, the paper's agents {band_lo}", b.standing_still_per_step);
    // Driving pays at most 0.56 per step; the paper's best (TD3, 0.322) is 58 % of it.
    assert!(b.per_step < 0.57 && b.per_step > band_hi, "{b:?}");
    // With plain median bars where the blocks face the doorways, a car looks through a doorway
    // and along the next lane, and standing still pays more than SAC's 0.200 again.
    let text: String = include_str!("../maps/env2.yaml")
        .lines()
        .map(|l| match l.find("center: [").filter(|_| l.contains("size: [5, 2.3]")) {
            Some(i) => {
                let c: Vec<f64> = l[i + 9..].split(']').next().unwrap().split(',').map(|v| v.trim().parse().unwrap()).collect();
                format!("  - box: {{ center: [{}, {}], size: [5, 0.8] }}\n", c[0], 10.0 * (c[1] / 10.0).floor() + 5.0)
            }
            None => format!("{l}\n"),
        })
        .collect();
    let flat = Map::from_vector_yaml(&text, Path::new("env2-without-blocks.yaml")).unwrap();
    assert_eq!(flat.obstacles.len(), env2.obstacles.len());
    assert!(!flat.is_free(-5.5, -15.0) && flat.is_free(-5.5, -14.0), "a bar, not a block");
    let b = reward_bounds(&world(flat), 0.25, 36);
    assert!(b.standing_still_per_step > band_lo, "{b:?}");
}

#[test]
fn a_scripted_driver_at_the_papers_speeds_earns_about_the_papers_per_step_rewards_on_env2() {
    // The env2 agents' speeds: Table V's TD3-env2 and SAC-env2 trajectories drive 0.0499 and
    // 0.0339 m per step (the circling DDPG-env2 row's speed is not usable), the fastest and
    // slowest of the paper. Table IV's agents earned 0.200–0.322 per step.
    let w = world(Map::builtin("env2").unwrap());
    let (lo, hi) = env2_per_step_return_band();
    let speed_term = |m_per_step: f64| w.cfg.reward.speed_weight * (m_per_step / w.cfg.vehicle.dt_s).powi(2);
    let (sac, td3) = (&TABLE_V[5], &TABLE_V[4]);
    assert_eq!((sac.algorithm, sac.trained_on, td3.algorithm, td3.trained_on), ("sac", "env2", "td3", "env2"));
    let at = |row: &mapless_sim::paper::EvalRow| {
        let speed = row.distance_m() / f64::from(row.steps);
        let (per_step, collisions) = scripted(&w, speed, 12);
        assert!(collisions <= 1, "{} at {speed:.4} m/step: {collisions} collisions", row.algorithm);
        // What the world pays beyond eq. (1)'s speed term, net of the steering cost, is small:
        // the car is always within a few metres of something (the open field paid 0.15–0.17).
        let beyond = per_step - speed_term(speed);
        assert!((0.0..0.04).contains(&beyond), "{} at {speed:.4} m/step: {per_step:.3} per step, {beyond:.3} beyond the speed term", row.algorithm);
        per_step
    };
    // At SAC's speed: at the band's bottom (inside it, or less than 0.02 below).
    let slow = at(sac);
    assert!((lo - 0.02..=hi).contains(&slow), "SAC-env2's speed: {slow:.3} per step, band {lo:.3}–{hi:.3}");
    // At TD3's speed eq. (1)'s speed term alone, 0.374, is above the band's top: the driver earns
    // that and little more (the paper's unconverged agents drove slower, or turned more).
    let fast = at(td3);
    assert!(speed_term(td3.distance_m() / f64::from(td3.steps)) > hi && (hi..hi + 0.1).contains(&fast), "TD3-env2's speed: {fast:.3} per step, band {lo:.3}–{hi:.3}");
}

#[test]
fn the_speed_cap_is_the_fastest_rows_metres_per_step() {
    // Table V gives steps, EQS and EES of one trajectory, so d / steps is known. The fastest
    // rows (DDPG-env1, TD3-env1, TD3-env2; the circling DDPG-env2's EES of 0.02 is too coarsely
    // rounded to use) drive 0.0496–0.0500 m per step; v_max · dt must be that cap.
    let vc = VehicleConfig::default();
    let cap = vc.v_max_mps * vc.dt_s;
    let speeds: Vec<f64> = TABLE_V.iter().filter(|r| !r.circling).map(|r| r.distance_m() / f64::from(r.steps)).collect();
    let fastest = speeds.iter().copied().fold(0.0, f64::max);
    assert!((cap - fastest).abs() < 0.001, "cap {cap}, fastest row {fastest}");
    assert!(speeds.iter().all(|&s| s <= cap + 0.0005), "{speeds:?}");
    // Both SAC agents drive 0.034 m per step: slower than the cap, a behaviour, not a limit.
    for r in TABLE_V.iter().filter(|r| r.algorithm == "sac") {
        assert!((r.distance_m() / f64::from(r.steps) - 0.034).abs() < 0.001);
    }
}

/// Table V: the paper evaluates on env3 agents trained elsewhere and finds its "characteristics
/// … more similar to the first than the second" environment; both SAC agents drive there at
/// their env1 speed (0.034 m/step). Held here by the scans a policy meets: env3's mean minimum
/// range lies nearer env1's than env2's, and 99 % of its poses show a nearest obstacle no
/// farther than the farthest env1 ever shows. (The open rooms of the old env3 failed the
/// second: 7 % of its poses lay beyond env1's largest, its 99th percentile at 7.9 m.)
#[test]
fn env3_shows_a_policy_the_scans_of_env1_as_table_v_says() {
    let stats = |m: &str| reward_bounds(&world(Map::builtin(m).unwrap()), 0.2, 36);
    let (e1, e2, e3) = (stats("env1"), stats("env2"), stats("env3"));
    let m = Map::builtin("env3").unwrap();
    assert_eq!((m.bounds.width(), m.bounds.height()), (40.0, 40.0));
    assert!(
        (e3.mean_min_range_m - e1.mean_min_range_m).abs() < (e3.mean_min_range_m - e2.mean_min_range_m).abs(),
        "env3 mean {:.2} m, env1 {:.2}, env2 {:.2}",
        e3.mean_min_range_m,
        e1.mean_min_range_m,
        e2.mean_min_range_m
    );
    assert!(e3.min_range_percentiles_m[2] <= e1.max_min_range_m, "env3's 99th percentile {:.2} m beyond env1's largest {:.2} m", e3.min_range_percentiles_m[2], e1.max_min_range_m);
}

/// Table V's env3 episodes last 2,151–2,971 of 3,000 steps for the agents that explore: the
/// world lets a careful driver go that long. The scripted driver at SAC's 0.034 m/step, from
/// random starts, reaches 3,000 steps in most episodes.
#[test]
fn a_scripted_driver_lasts_table_vs_episodes_on_env3() {
    let w = world(Map::builtin("env3").unwrap());
    let vc = &w.cfg.vehicle;
    let fraction = 0.034 / (vc.v_max_mps * vc.dt_s);
    let angles = w.cfg.sensor.beam_angles_rad();
    let mut obs = vec![0.0; w.obs_dim()];
    let mut full = 0;
    for seed in 0..8 {
        let mut env = Env::new(Arc::clone(&w), seed);
        env.reset(&mut obs).unwrap();
        let mut steps = 0;
        while steps < 3000 {
            let a = baseline::cruise(env.ranges_m(), &angles, w.cfg.sensor.max_range_m, fraction);
            steps += 1;
            if env.step(a, &mut obs).unwrap().terminal {
                break;
            }
        }
        full += u32::from(steps == 3000);
    }
    assert!(full >= 6, "only {full} of 8 scripted episodes reached 3,000 steps");
}
