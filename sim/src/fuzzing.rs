//! Harness of the `map_files` coverage-guided fuzz target (`fuzz/` at the repository root, run
//! with `cargo +nightly fuzz run map_files`; docs/reliability.md, "Fuzzing"). It takes arbitrary
//! bytes, loads them as a map file exactly as `--set map=FILE` does, and panics only when an
//! invariant breaks, never on the input's account. `sim/tests/fuzz_corpora.rs` replays the
//! committed corpus and regression inputs through the same function on stable.
//!
//! ```text
//!   map_files   yaml_len u16 LE | YAML text | image bytes
//!               Map::parse ("fuzz/map.yaml"; any image it names reads as the image bytes)
//!               = the vector-map YAML, or a ROS map_server YAML with its PGM/PNG
//! ```
//!
//! A map that loads must be one the simulator can use: finite bounds with min < max; ray casts
//! through its obstacle index agree with casting against every obstacle, and stay within
//! [0, range]; a vector map written back as YAML loads to the same geometry; a grid map
//! rasterised at its own resolution gives back its own cells.

use std::path::Path;

use crate::map::Map;

/// Range of the probing rays, metres (the paper's sensor's 12 m).
const PROBE_RANGE_M: f32 = 12.0;
/// Above this many obstacle segments, or grid cells, only the cheap invariants are checked, so
/// that a large map does not slow the fuzzer to a crawl.
const MAX_CHECKED: usize = 40_000;

/// One input: see the module's documentation.
pub fn map_files(data: &[u8]) {
    let Some((len, rest)) = data.split_first_chunk::<2>() else { return };
    let len = usize::from(u16::from_le_bytes(*len)).min(rest.len());
    let (yaml, image) = rest.split_at(len);
    let Ok(text) = std::str::from_utf8(yaml) else { return };
    let Ok(map) = Map::parse(text, Path::new("fuzz/map.yaml"), |_| Ok(image.to_vec())) else { return };
    check(&map);
}

/// The invariants of a map that loaded.
pub fn check(map: &Map) {
    let b = map.bounds;
    assert!([b.min_x, b.min_y, b.max_x, b.max_y].iter().all(|v| v.is_finite()) && b.min_x < b.max_x && b.min_y < b.max_y, "bounds {b:?}");
    let segments: Vec<[f64; 4]> = map.segments().collect();
    assert!(segments.iter().flatten().chain(map.circles().flatten().collect::<Vec<f64>>().iter()).all(|v| v.is_finite()), "non-finite obstacle geometry");
    let cells = map.grid.as_ref().map_or(0, |g| g.width * g.height);
    if segments.len() > MAX_CHECKED || cells > MAX_CHECKED {
        return;
    }
    let scene = map.scene(0.0, 2.0);
    // Rays from a 5 × 5 lattice of points inside the bounds, eight directions each.
    for a in 0..5 {
        for c in 0..5 {
            let x = b.min_x + b.width() * (f64::from(a) + 0.5) / 5.0;
            let y = b.min_y + b.height() * (f64::from(c) + 0.5) / 5.0;
            for k in 0..8 {
                let angle = f64::from(k) * std::f64::consts::FRAC_PI_4 + 0.1;
                let (dx, dy) = (angle.cos() as f32, angle.sin() as f32);
                let fast = scene.cast_ray(x as f32, y as f32, dx, dy, PROBE_RANGE_M);
                let slow = scene.cast_ray_brute(x as f32, y as f32, dx, dy, PROBE_RANGE_M);
                assert!((0.0..=PROBE_RANGE_M).contains(&fast), "range {fast} from ({x}, {y}) at {angle} rad");
                // f32 coordinates far from the origin resolve to ~1e-7 of their magnitude.
                let tolerance = 1e-3 + 1e-6 * (x.abs() + y.abs()) as f32;
                assert!((fast - slow).abs() <= tolerance, "indexed ray {fast} vs brute force {slow} from ({x}, {y}) at {angle} rad");
            }
        }
    }
    match &map.grid {
        None => {
            let yaml = map.to_vector_yaml().expect("a vector map has a YAML form");
            let again = Map::from_vector_yaml(&yaml, Path::new("fuzz/again.yaml")).unwrap_or_else(|e| panic!("written map does not load back: {e}\n{yaml}"));
            assert_eq!(again.bounds, map.bounds, "bounds after a round trip");
            assert_eq!(again.segments().collect::<Vec<_>>(), segments, "segments after a round trip");
            assert_eq!(again.circles().collect::<Vec<_>>(), map.circles().collect::<Vec<_>>(), "circles after a round trip");
        }
        Some(g) => {
            let (w, h, px) = map.rasterize(g.resolution_m).expect("a grid map rasterises at its own resolution");
            assert_eq!((w, h), (g.width, g.height), "raster size");
            for row in 0..h {
                for col in 0..w {
                    let free = g.free[(h - 1 - row) * w + col];
                    assert_eq!(px[row * w + col] != 0, free, "raster pixel ({col}, {row}) vs its cell");
                }
            }
        }
    }
}
