//! The mirror image of a transition is a transition: what `actors.mirror_share` relies on.
//! A car driven in a world and, with the turn's sign flipped, from the mirror-image pose in
//! that world's mirror image reads mirrored observations and earns the same rewards, step by
//! step, collision included.

use std::sync::Arc;

use mapless_sim::map::Map;
use mapless_sim::vehicle::Pose;
use mapless_sim::{Env, EnvConfig, World};

/// An asymmetric room and its image under x → −x.
fn room(mirror: bool) -> Map {
    let s = if mirror { -1.0 } else { 1.0 };
    let text = format!(
        "format: mapless-vector-map/v1\nname: room\nbounds: {{ min: [-10, -8], max: [10, 8] }}\nboundary_walls: true\nobstacles:\n  - box: {{ center: [{}, 2.5], size: [1.5, 3.0] }}\n  - circle: {{ center: [{}, -1.0], radius: 0.4 }}\n  - polygon: {{ points: [[{}, -6], [{}, -6], [{}, -3.5]] }}\n",
        s * 3.0,
        s * -2.5,
        s * 5.0,
        s * 8.0,
        s * 6.0
    );
    Map::from_vector_yaml(&text, std::path::Path::new("room.yaml")).unwrap()
}

fn mirrored_pose(p: Pose) -> Pose {
    Pose { x_m: -p.x_m, y_m: p.y_m, heading_rad: std::f64::consts::PI - p.heading_rad }
}

fn check(cfg: EnvConfig) {
    let world = World::new(room(false), cfg.clone()).unwrap();
    let image = World::new(room(true), cfg.clone()).unwrap();
    let d = cfg.obs_dim();
    let (mut o, mut om, mut mirrored) = (vec![0f32; d], vec![0f32; d], vec![0f32; d]);
    let close = |a: &[f32], b: &[f32]| a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-4);
    let mut collisions = 0;
    // Starts off the EQS grid's cell edges in x (every 2 m from −10), where a cell and its mirror
    // image would not be each other's.
    for (k, start) in [Pose { x_m: -4.1, y_m: 1.0, heading_rad: 0.3 }, Pose { x_m: 1.0, y_m: -2.0, heading_rad: -2.0 }, Pose { x_m: 6.1, y_m: 0.0, heading_rad: 1.2 }].into_iter().enumerate() {
        let mut a = Env::new(Arc::clone(&world), 1);
        let mut b = Env::new(Arc::clone(&image), 1);
        a.reset_to(start, &mut o);
        b.reset_to(mirrored_pose(start), &mut om);
        for t in 0..400u32 {
            cfg.mirror_obs(&o, &mut mirrored);
            assert!(close(&mirrored, &om), "start {k}, step {t}: {mirrored:?} is not {om:?}");
            // Turns that change sign and size, so that both sides of the car matter.
            let act = [((t % 7) as f32 / 3.0 - 1.0), ((t as f32) * 0.37).sin()];
            let ra = a.step(act, &mut o).unwrap();
            let rb = b.step(EnvConfig::mirror_action(act), &mut om).unwrap();
            assert!((ra.reward - rb.reward).abs() < 1e-4 && ra.terminal == rb.terminal && ra.truncated == rb.truncated, "start {k}, step {t}: {ra:?} vs {rb:?}");
            if ra.done() {
                collisions += u32::from(ra.terminal);
                break;
            }
        }
    }
    assert!(collisions > 0, "no start ended in a collision: the walls were never met");
    // The mirror is an involution.
    cfg.mirror_obs(&o, &mut mirrored);
    let mut back = vec![0f32; d];
    cfg.mirror_obs(&mirrored, &mut back);
    assert_eq!(back, o);
}

#[test]
fn a_mirrored_transition_is_the_transition_in_the_mirrored_world() {
    let mut cfg = EnvConfig::default();
    cfg.sensor.noise_std_m = 0.0;
    cfg.episode.max_steps = 400;
    check(cfg.clone());
    // More rays per beam, and a full circle, whose beam 0 looks straight back.
    cfg.sensor.rays_per_beam = 5;
    check(cfg.clone());
    // With the staleness appended: the mirrored drive enters the mirrored cells at the same steps.
    cfg.observation.staleness_steps = 30;
    check(cfg.clone());
    // And the start's offset: its bearing changes sign, its distance does not.
    cfg.observation.start_offset_m = 10.0;
    check(cfg.clone());
    cfg.sensor.fov_rad = std::f64::consts::TAU;
    cfg.sensor.beams = 12;
    check(cfg);
}

#[test]
fn the_mirror_maps_each_beam_to_the_one_at_the_opposite_angle() {
    for (beams, fov) in [(7, 3.0 * std::f64::consts::FRAC_PI_4), (6, 2.0), (12, std::f64::consts::TAU), (1, 1.0)] {
        let mut cfg = EnvConfig::default();
        cfg.sensor.beams = beams;
        cfg.sensor.fov_rad = fov;
        let angles = cfg.sensor.beam_angles_rad();
        for k in 0..beams {
            let m = cfg.sensor.mirrored_beam(k);
            let diff = (angles[m] + angles[k]).rem_euclid(std::f64::consts::TAU);
            assert!(diff < 1e-9 || std::f64::consts::TAU - diff < 1e-9, "{beams} beams over {fov}: beam {k} at {} mirrored to {m} at {}", angles[k], angles[m]);
        }
    }
}
