//! Map files: the ROS map_server loader on a small image with known obstacles, vector maps,
//! and a clear error (naming the file and the problem) for every kind of corrupt input.

use std::path::{Path, PathBuf};

use mapless_sim::Map;

fn dir(name: &str) -> PathBuf {
    let d = Path::new(env!("CARGO_TARGET_TMPDIR")).join("map_files").join(name);
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// 10 × 8 px at 0.5 m, origin (−1, −2): white (free) everywhere except a black 2 × 2 block at
/// image rows 2–3, columns 3–4 (world x ∈ [0.5, 1.5], y ∈ [0, 1]) and a grey (unknown) band in
/// columns 8–9 (x ∈ [3, 4]).
fn small_image() -> Vec<u8> {
    let (w, h) = (10, 8);
    let mut px = vec![254u8; w * h];
    for r in 2..4 {
        for c in 3..5 {
            px[r * w + c] = 0;
        }
    }
    for r in 0..h {
        for c in 8..10 {
            px[r * w + c] = 128;
        }
    }
    px
}

const ROS_YAML: &str = "image: IMAGE\nresolution: 0.5\norigin: [-1.0, -2.0, 0.0]\nnegate: 0\noccupied_thresh: 0.65\nfree_thresh: 0.196\n";

fn write_pgm(path: &Path, px: &[u8]) {
    let mut bytes = b"P5\n# made by a test\n10 8\n255\n".to_vec();
    bytes.extend_from_slice(px);
    std::fs::write(path, bytes).unwrap();
}

fn check_small_map(map: &Map) {
    assert_eq!((map.bounds.min_x, map.bounds.min_y, map.bounds.max_x, map.bounds.max_y), (-1.0, -2.0, 4.0, 2.0));
    assert!(map.is_free(-0.75, 0.5));
    assert!(!map.is_free(1.0, 0.5), "black block is occupied");
    assert!(!map.is_free(3.5, 0.0), "grey band is unknown, so blocked");
    let scene = map.scene(0.0, 1.0);
    // From (−0.75, 0.5): +x meets the block's west face at x = 0.5 → 1.25 m; −x meets the grid
    // border at x = −1 → 0.25 m.
    assert!((scene.cast_ray(-0.75, 0.5, 1.0, 0.0, 12.0) - 1.25).abs() < 1e-5);
    assert!((scene.cast_ray(-0.75, 0.5, -1.0, 0.0, 12.0) - 0.25).abs() < 1e-5);
    // From (2.25, −1.75) along +x: the unknown band starts at x = 3 → 0.75 m.
    assert!((scene.cast_ray(2.25, -1.75, 1.0, 0.0, 12.0) - 0.75).abs() < 1e-5);
    // Straight up from (1.0, −1.75): the block's south face at y = 0 → 1.75 m.
    assert!((scene.cast_ray(1.0, -1.75, 0.0, 1.0, 12.0) - 1.75).abs() < 1e-5);
}

#[test]
fn ros_pgm_map_loads_with_known_obstacles() {
    let d = dir("pgm");
    write_pgm(&d.join("small.pgm"), &small_image());
    std::fs::write(d.join("small.yaml"), ROS_YAML.replace("IMAGE", "small.pgm")).unwrap();
    let map = Map::load(&d.join("small.yaml")).unwrap();
    assert_eq!(map.name, "small");
    check_small_map(&map);
}

#[test]
fn ros_png_map_loads_the_same() {
    let d = dir("png");
    let f = std::fs::File::create(d.join("small.png")).unwrap();
    let mut enc = png::Encoder::new(f, 10, 8);
    enc.set_color(png::ColorType::Grayscale);
    enc.write_header().unwrap().write_image_data(&small_image()).unwrap();
    std::fs::write(d.join("small.yaml"), ROS_YAML.replace("IMAGE", "small.png")).unwrap();
    check_small_map(&Map::load(&d.join("small.yaml")).unwrap());
}

#[test]
fn ascii_pgm_and_negate_are_honoured() {
    let d = dir("p2");
    // Negated: 255 means occupied. 3 × 2: one occupied pixel top-left.
    std::fs::write(d.join("n.pgm"), "P2\n3 2\n255\n255 0 0\n0 0 0\n").unwrap();
    std::fs::write(d.join("n.yaml"), "image: n.pgm\nresolution: 1.0\norigin: [0, 0, 0]\nnegate: 1\noccupied_thresh: 0.65\nfree_thresh: 0.196\n").unwrap();
    let map = Map::load(&d.join("n.yaml")).unwrap();
    assert!(!map.is_free(0.5, 1.5));
    assert!(map.is_free(1.5, 1.5) && map.is_free(0.5, 0.5));
}

#[test]
fn user_vector_map_loads_and_is_usable() {
    let d = dir("vector");
    let p = d.join("room.yaml");
    std::fs::write(&p, "format: mapless-vector-map/v1\nname: room\nbounds: {min: [0, 0], max: [6, 4]}\nboundary_walls: true\nobstacles:\n  - polygon: {points: [[2, 1], [3, 1], [3, 2]]}\n  - box: {center: [5, 3], size: [0.5, 0.5], height_m: 0.1}\nshaded:\n  - polygon: {points: [[0, 0], [1, 0], [1, 1], [0, 1]]}\n").unwrap();
    let map = Map::resolve(p.to_str().unwrap()).unwrap();
    assert!(!map.is_free(2.9, 1.2));
    assert!(map.in_shade(0.5, 0.5));
    // The 0.1 m box is invisible to a sensor at 0.15 m but blocks the car.
    assert_eq!(map.scene(0.15, 1.0).segment_count(), 4 + 3);
    assert_eq!(map.scene(0.0, 1.0).segment_count(), 4 + 3 + 4);
}

/// Writes `files` into a fresh folder, loads `main`, and returns the error text.
fn load_err(case: &str, files: &[(&str, &[u8])], main: &str) -> String {
    let d = dir(case);
    for (name, bytes) in files {
        std::fs::write(d.join(name), bytes).unwrap();
    }
    match Map::load(&d.join(main)) {
        Ok(_) => panic!("{case}: corrupt map loaded"),
        Err(e) => e.to_string(),
    }
}

fn assert_names(err: &str, file: &str, problem: &str) {
    assert!(err.contains(file), "error does not name the file {file}: {err}");
    assert!(err.to_lowercase().contains(&problem.to_lowercase()), "error does not say `{problem}`: {err}");
}

#[test]
fn corrupt_vector_maps_get_errors_naming_file_and_problem() {
    let head = "format: mapless-vector-map/v1\nname: bad\nbounds: {min: [0, 0], max: [10, 10]}\n";
    let cases: &[(&str, String, &str)] = &[
        ("syntax", "format: [unclosed\n".into(), "not valid YAML"),
        ("format", head.replace("v1", "v9"), "unsupported format"),
        ("radius", format!("{head}obstacles:\n  - circle: {{center: [1, 1], radius: -2}}\n"), "obstacle 0 (circle)"),
        ("outside", format!("{head}obstacles:\n  - box: {{center: [11, 5], size: [2, 2]}}\n"), "outside the map bounds"),
        ("field", format!("{head}obstacles:\n  - circle: {{centre: [1, 1], radius: 1}}\n"), "unknown field `centre`"),
        ("kind", format!("{head}obstacles:\n  - triangle: {{}}\n"), "unknown variant `triangle`"),
        ("bounds", "format: mapless-vector-map/v1\nname: b\nbounds: {min: [5, 0], max: [1, 10]}\n".into(), "min < max"),
        ("polygon", format!("{head}obstacles:\n  - polygon: {{points: [[1, 1], [2, 2]]}}\n"), "at least 3"),
        ("neither", "hello: world\n".into(), "neither a vector map"),
        ("empty", String::new(), "neither"),
    ];
    for (case, text, problem) in cases {
        let err = load_err(case, &[("m.yaml", text.as_bytes())], "m.yaml");
        assert_names(&err, "m.yaml", problem);
    }
}

#[test]
fn corrupt_ros_maps_get_errors_naming_file_and_problem() {
    let good_yaml = ROS_YAML.replace("IMAGE", "i.pgm");
    let mut pgm = b"P5\n10 8\n255\n".to_vec();
    pgm.extend_from_slice(&small_image());
    // (case, files written, the file the error must name, what it must say)
    type Case<'a> = (&'a str, Vec<(&'a str, Vec<u8>)>, &'a str, &'a str);
    let cases: Vec<Case> = vec![
        ("missing-image", vec![("m.yaml", good_yaml.clone().into_bytes())], "i.pgm", "cannot read image"),
        ("truncated", vec![("m.yaml", good_yaml.clone().into_bytes()), ("i.pgm", pgm[..40].to_vec())], "i.pgm", "truncated"),
        ("header", vec![("m.yaml", good_yaml.clone().into_bytes()), ("i.pgm", b"P5\nten 8\n255\n".to_vec())], "i.pgm", "corrupt PGM header"),
        ("not-image", vec![("m.yaml", good_yaml.clone().into_bytes()), ("i.pgm", b"GIF89a....".to_vec())], "i.pgm", "not a PGM"),
        ("bad-png", vec![("m.yaml", good_yaml.replace("i.pgm", "i.png").into_bytes()), ("i.png", b"\x89PNG\r\n\x1a\nxxxxxxxxxxxx".to_vec())], "i.png", "corrupt PNG"),
        ("resolution", vec![("m.yaml", good_yaml.replace("0.5", "-0.5").into_bytes()), ("i.pgm", pgm.clone())], "m.yaml", "resolution"),
        ("thresholds", vec![("m.yaml", good_yaml.replace("free_thresh: 0.196", "free_thresh: 0.9").into_bytes()), ("i.pgm", pgm.clone())], "m.yaml", "free_thresh < occupied_thresh"),
        ("yaw", vec![("m.yaml", good_yaml.replace("0.0]", "0.3]").into_bytes()), ("i.pgm", pgm.clone())], "m.yaml", "yaw"),
        ("no-resolution", vec![("m.yaml", b"image: i.pgm\norigin: [0, 0, 0]\noccupied_thresh: 0.65\nfree_thresh: 0.2\n".to_vec()), ("i.pgm", pgm.clone())], "m.yaml", "resolution"),
        (
            "all-blocked",
            vec![
                ("m.yaml", good_yaml.clone().into_bytes()),
                ("i.pgm", {
                    let mut p = b"P5\n10 8\n255\n".to_vec();
                    p.extend(vec![0u8; 80]);
                    p
                }),
            ],
            "m.yaml",
            "no free cell",
        ),
    ];
    for (case, files, file, problem) in cases {
        let refs: Vec<(&str, &[u8])> = files.iter().map(|(n, b)| (*n, b.as_slice())).collect();
        let err = load_err(case, &refs, "m.yaml");
        assert_names(&err, file, problem);
    }
}

/// A 10 m × 4 m room with one wall from (5, 0) to (5, 1.25) and another from (5, 2.75) to
/// (5, 4): a 1.5 m doorway, each jamb's end pointing along y.
fn doorway(thickness: &str) -> String {
    format!(
        "format: mapless-vector-map/v1\nname: door\nbounds: {{ min: [0, 0], max: [10, 4] }}\nboundary_walls: true\n{thickness}obstacles:\n  - wall: {{ from: [5, 0], to: [5, 1.25] }}\n  - wall: {{ from: [5, 2.75], to: [5, 4] }}\n"
    )
}

#[test]
fn a_thick_wall_is_a_solid_bar_that_a_ray_meets_end_on_and_keeps_the_doorway() {
    let line = Map::from_vector_yaml(&doorway(""), "line.yaml".as_ref()).unwrap();
    let bar = Map::from_vector_yaml(&doorway("wall_thickness_m: 1.0\n"), "bar.yaml".as_ref()).unwrap();
    let (sl, sb) = (line.scene(0.0, 2.0), bar.scene(0.0, 2.0));
    // A ray along the lower jamb's line, from inside the doorway towards its end: the line is
    // parallel to the ray and never hit (the ray runs on to the far wall); the bar's end face
    // at y = 1.25 is 1.25 m away.
    let (far, near) = (sl.cast_ray(5.0, 2.5, 0.0, -1.0, 12.0), sb.cast_ray(5.0, 2.5, 0.0, -1.0, 12.0));
    assert!((far - 2.5).abs() < 1e-4, "the line is seen end-on only where the ray ends, at the outer wall: {far}");
    assert!((near - 1.25).abs() < 1e-4, "the bar's end face: {near}");
    // The bar is 1 m thick, centred on the line, and solid; the doorway between the ends keeps
    // its 1.5 m.
    assert!(!bar.is_free(4.6, 0.6) && !bar.is_free(5.4, 3.4) && bar.is_free(4.4, 0.6) && bar.is_free(5.0, 2.0));
    assert!(line.is_free(4.6, 0.6));
    assert!((sb.cast_ray(4.0, 0.6, 1.0, 0.0, 12.0) - 0.5).abs() < 1e-4, "the bar's side face at x = 4.5");
    assert!((sb.cast_ray(5.0, 2.0, 0.0, 1.0, 12.0) - 0.75).abs() < 1e-4, "the upper jamb's end at y = 2.75");
    // Loaded, a thick wall is written back as the box it became, and reloads identically.
    let again = Map::from_vector_yaml(&bar.to_vector_yaml().unwrap(), "again.yaml".as_ref()).unwrap();
    assert_eq!(again.segments().collect::<Vec<_>>(), bar.segments().collect::<Vec<_>>());
}

#[test]
fn a_wall_thickness_that_cannot_be_built_is_a_clear_error() {
    let err = Map::from_vector_yaml(&doorway("wall_thickness_m: -0.5\n"), "neg.yaml".as_ref()).unwrap_err().to_string();
    assert!(err.contains("neg.yaml") && err.contains("wall_thickness_m must be finite and >= 0"), "{err}");
    // A wall laid along the bounds would stick out of the map once thick.
    let along = "format: mapless-vector-map/v1\nname: along\nbounds: { min: [0, 0], max: [10, 4] }\nwall_thickness_m: 0.5\nobstacles:\n  - wall: { from: [0, 0], to: [10, 0] }\n";
    let err = Map::from_vector_yaml(along, "along.yaml".as_ref()).unwrap_err().to_string();
    assert!(err.contains("along.yaml") && err.contains("obstacle 0 (wall)") && err.contains("outside the map bounds"), "{err}");
}

/// Found by the `map_files` fuzz target: 3 cells of 0.4 m are 1.2000000000000002 m, and the
/// raster at the map's own resolution took the ceiling of 3.0000000000000004, a column more than
/// the map has; a ROS map written back (`Map::write_ros`) loaded as a different map.
#[test]
fn a_ros_map_written_back_at_its_own_resolution_keeps_its_size() {
    let d = dir("round-trip");
    for (res, w, h) in [(0.4, 3, 2), (0.1, 7, 3), (0.05, 13, 11), (0.3, 10, 10)] {
        let mut pgm = format!("P5\n{w} {h}\n255\n").into_bytes();
        pgm.extend((0..w * h).map(|k| if k % 3 == 0 { 0u8 } else { 254 }));
        std::fs::write(d.join("m.pgm"), pgm).unwrap();
        std::fs::write(d.join("m.yaml"), format!("image: m.pgm\nresolution: {res}\norigin: [0.0, 0.0, 0.0]\nnegate: 0\noccupied_thresh: 0.65\nfree_thresh: 0.196\n")).unwrap();
        let map = Map::load(&d.join("m.yaml")).unwrap();
        let (rw, rh, px) = map.rasterize(res).unwrap();
        assert_eq!((rw, rh), (w, h), "raster of a {w}x{h} map at {res} m");
        let again = Map::load(&map.write_ros(&d.join("again"), res).unwrap()).unwrap();
        let g = again.grid.as_ref().unwrap();
        assert_eq!((g.width, g.height), (w, h), "{w}x{h} at {res} m, written back");
        assert_eq!(again.rasterize(res).unwrap().2, px, "{w}x{h} at {res} m, written back");
    }
}
