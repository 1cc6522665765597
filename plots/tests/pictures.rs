//! Pictures: maps and episodes drawn to PNG show what they should where they should.

use std::sync::Arc;

use mapless_plots::{Canvas, default_px_per_m};
use mapless_sim::{Env, EnvConfig, Map, Pose, World};

fn is_dark(p: [u8; 4]) -> bool {
    p[0] < 130 && p[1] < 130 && p[2] < 130
}

#[test]
fn map_picture_shows_obstacles_free_floor_and_shade() {
    let map = Map::builtin("outdoor20").unwrap();
    let c = Canvas::map(&map, 20.0, "OUTDOOR20").unwrap();
    let at = |x: f64, y: f64| {
        let (px, py) = c.world_to_px(x, y);
        c.pixel(px as u32, py as u32).unwrap()
    };
    assert!(is_dark(at(-4.0, -5.0)), "boulder centre is dark: {:?}", at(-4.0, -5.0));
    assert!(!is_dark(at(5.0, 0.0)), "open ground is light");
    let shade = at(-6.0, 1.5); // under the canopy of the tree at (−6, 0), off the trunk
    assert!(shade[1] > shade[0] + 30 && shade[1] > shade[2] + 30, "canopy is green: {shade:?}");
    // 20 m at 20 px/m plus margins, title, axes and footer.
    assert!(c.width() >= 400 && c.height() >= 400);
    // Axes in metres: tick labels left of and below the map, and the title above it.
    let dark = |xs: std::ops::Range<u32>, ys: std::ops::Range<u32>| ys.flat_map(|y| xs.clone().map(move |x| (x, y))).filter(|&(x, y)| is_dark(c.pixel(x, y).unwrap())).count();
    let (left, top) = c.world_to_px(-10.0, 10.0);
    let (right, bottom) = c.world_to_px(10.0, -10.0);
    let (left, top, right, bottom) = (left as u32, top as u32, right as u32, bottom as u32);
    assert!(dark(left - 40..left - 8, top..bottom) > 100, "y tick labels");
    assert!(dark(left..right, bottom + 6..bottom + 24) > 100, "x tick labels");
    assert!(dark(0..c.width(), 0..top - 4) > 50, "title");
}

#[test]
fn episode_picture_marks_visited_cells_and_writes_a_png() {
    let mut cfg = EnvConfig::default();
    cfg.sensor.noise_std_m = 0.0;
    let world = World::new(Map::builtin("env1").unwrap(), cfg).unwrap();
    let mut env = Env::new(Arc::clone(&world), 0);
    env.record_trajectory(true);
    let mut obs = vec![0.0; world.obs_dim()];
    env.reset_to(Pose { x_m: -10.0, y_m: -10.0, heading_rad: 0.0 }, &mut obs);
    for _ in 0..200 {
        env.step([1.0, 0.0], &mut obs).unwrap(); // 10 m east, along the south corridor
    }
    let map = &world.map;
    let mut c = Canvas::map(map, default_px_per_m(map), "ENV1").unwrap();
    // Cells are anchored at the map corner (−12.5, −12.5), side 2 m: the path y = −10 runs in the
    // row y ∈ [−10.5, −8.5], so (−5, −8.8) is inside a visited cell, off the drawn line.
    let before = {
        let (px, py) = c.world_to_px(-5.0, -8.8);
        c.pixel(px as u32, py as u32).unwrap()
    };
    let far_before = {
        let (px, py) = c.world_to_px(-5.0, 8.0);
        c.pixel(px as u32, py as u32).unwrap()
    };
    c.episode(map, env.trajectory().unwrap(), env.tracker(), world.cfg.exploration.ring_width_m, false).unwrap();
    let (px, py) = c.world_to_px(-5.0, -8.8);
    let after = c.pixel(px as u32, py as u32).unwrap();
    assert!(after[2] > after[0] && after != before, "visited cell is tinted blue: {before:?} -> {after:?}");
    let (px, py) = c.world_to_px(-5.0, 8.0);
    assert_eq!(c.pixel(px as u32, py as u32).unwrap(), far_before, "unvisited cells untouched");
    // Footer lines go below the axes; a second one makes the picture taller.
    let h = c.height();
    let (_, bottom) = c.world_to_px(0.0, -12.5);
    let footer_dark = |c: &Canvas, ys: std::ops::Range<u32>| ys.flat_map(|y| (0..c.width()).map(move |x| (x, y))).filter(|&(x, y)| c.pixel(x, y).unwrap()[0] < 150).count();
    assert_eq!(footer_dark(&c, bottom as u32 + 50..h), 0);
    c.footer("1000 steps · return 442.3 · EQS 195").unwrap();
    assert!(footer_dark(&c, bottom as u32 + 50..h) > 50, "footer line written");
    assert_eq!(c.height(), h);
    c.footer("a second line").unwrap();
    assert!(c.height() > h && footer_dark(&c, h..c.height()) > 20);
    let path = std::path::Path::new(env!("CARGO_TARGET_TMPDIR")).join("pictures/episode.png");
    c.save_png(&path).unwrap();
    let img = image::open(&path).unwrap();
    assert_eq!((img.width(), img.height()), (c.width(), c.height()));
}
