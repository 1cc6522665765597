//! The `map_files` fuzz target's committed inputs on stable: every file of
//! `fuzz/corpus/map_files/` and `fuzz/regressions/map_files/` goes through the harness the
//! fuzzer runs (`mapless_sim::fuzzing`). The seeds are the project's own maps, written by its
//! own writers: `MAPLESS_WRITE_FUZZ_SEEDS=1 cargo test -p mapless-sim --test fuzz_corpora -- --ignored`.

use std::path::Path;

use mapless_sim::fuzzing::{check, map_files};
use mapless_sim::map::Map;
use mapless_sim::worlds::{Family, generate};

#[path = "../../tests/common/fuzz_corpus.rs"]
mod fuzz_corpus;

/// An input of the harness: `yaml_len u16 LE | yaml | image`.
fn input(yaml: &str, image: &[u8]) -> Vec<u8> {
    let mut out = u16::try_from(yaml.len()).expect("a seed's YAML fits in 64 KiB").to_le_bytes().to_vec();
    out.extend_from_slice(yaml.as_bytes());
    out.extend_from_slice(image);
    out
}

/// A map as a ROS map_server map written by `Map::write_ros`: (YAML, PGM bytes).
fn ros(map: &Map, resolution_m: f64) -> (String, Vec<u8>) {
    let dir = tempfile::tempdir().unwrap();
    let yaml_path = map.write_ros(dir.path(), resolution_m).unwrap();
    let yaml = std::fs::read_to_string(&yaml_path).unwrap();
    let image = std::fs::read(dir.path().join(format!("{}.pgm", map.name))).unwrap();
    (yaml, image)
}

/// The PGM's raster (P5 of `Map::write_ros`: three header lines after the magic) as a PNG.
fn pgm_to_png(pgm: &[u8]) -> Vec<u8> {
    let text = String::from_utf8_lossy(&pgm[..pgm.len().min(200)]).into_owned();
    let fields: Vec<&str> = text.lines().filter(|l| !l.starts_with('#')).take(3).collect();
    let dims: Vec<u32> = fields[1].split_whitespace().map(|v| v.parse().unwrap()).collect();
    let raster = &pgm[pgm.len() - (dims[0] * dims[1]) as usize..];
    let mut out = Vec::new();
    let mut enc = png::Encoder::new(&mut out, dims[0], dims[1]);
    enc.set_color(png::ColorType::Grayscale);
    enc.set_depth(png::BitDepth::Eight);
    enc.write_header().unwrap().write_image_data(raster).unwrap();
    out
}

fn seeds() -> Vec<(String, Vec<u8>)> {
    let mut out = Vec::new();
    for name in ["env1", "env2", "env3", "outdoor20"] {
        let map = Map::builtin(name).unwrap();
        out.push((format!("{name}-vector"), input(&map.to_vector_yaml().unwrap(), &[])));
        let (yaml, pgm) = ros(&map, map.bounds.width().max(map.bounds.height()) / 80.0);
        if name == "env1" {
            let png_yaml = yaml.replace(".pgm", ".png").replace("mode: trinary", "mode: scale");
            out.push((format!("{name}-ros-png"), input(&png_yaml, &pgm_to_png(&pgm))));
        }
        out.push((format!("{name}-ros-pgm"), input(&yaml, &pgm)));
    }
    let cave = generate(Family::Cave, 3).unwrap();
    let (yaml, pgm) = ros(&cave, 0.5);
    out.push(("cave-3-ros-pgm".into(), input(&yaml, &pgm)));
    out.push((
        "ros-raw-p2".into(),
        input("image: m.pgm\nresolution: 1.0\norigin: [0.0, 0.0, 0.0]\nnegate: 0\noccupied_thresh: 0.65\nfree_thresh: 0.196\nmode: raw\n", b"P2\n3 2\n100\n0 0 100\n0 100 0\n"),
    ));
    out
}

#[test]
fn map_files_corpus_and_regressions() {
    assert!(fuzz_corpus::replay_inputs("map_files", map_files) > 0, "no committed inputs for map_files");
}

/// Every seed loads (so the fuzzer starts from maps that pass, not from errors) and passes.
#[test]
fn the_seeds_load_and_pass_the_invariants() {
    for (name, data) in seeds() {
        let len = usize::from(u16::from_le_bytes([data[0], data[1]]));
        let text = std::str::from_utf8(&data[2..2 + len]).unwrap();
        let map = Map::parse(text, Path::new("seed.yaml"), |_| Ok(data[2 + len..].to_vec())).unwrap_or_else(|e| panic!("seed {name}: {e}"));
        check(&map);
    }
}

/// The check refuses a map the simulator could not use (here: bounds with min > max).
#[test]
#[should_panic(expected = "bounds")]
fn a_map_with_inverted_bounds_fails_the_check() {
    let mut map = Map::builtin("env1").unwrap();
    std::mem::swap(&mut map.bounds.min_x, &mut map.bounds.max_x);
    check(&map);
}

/// Writes the seeds into `fuzz/corpus/map_files/seed-<name>` (run by hand).
#[test]
#[ignore]
fn write_seed_corpus() {
    fuzz_corpus::write_seeds("map_files", seeds());
}
