//! Worlds the vehicle drives in: the paper's built-in maps and user maps.
//!
//! Two file formats load into one [`Map`]:
//! - **mapless vector maps** (`format: mapless-vector-map/v1`, YAML): bounds, optional boundary
//!   walls, obstacles (`box`, `circle`, `wall`, `polygon`, each with a `height_m`) and shaded
//!   regions (`circle`, `polygon`). The built-in maps `env1`, `env2`, `env3` and `outdoor20`
//!   are such files, embedded in the binary (see `sim/maps/`).
//! - **ROS map_server maps** (YAML with `image`, `resolution`, `origin`, `negate`,
//!   `occupied_thresh`, `free_thresh`, optional `mode`; image PGM (P2/P5) or PNG). Occupied
//!   and unknown cells are both treated as blocked (the car does not drive into unobserved
//!   space); the grid's outside is blocked too. Rotated origins (yaw ≠ 0) are rejected.
//!
//! Every error names the file and the problem.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::error::{Result, SimError};
use crate::scene::{Aabb, Scene};

/// Format tag every vector map must carry.
pub const VECTOR_FORMAT: &str = "mapless-vector-map/v1";

/// Names of the built-in maps, in the paper's order.
pub const BUILTIN_MAPS: [&str; 4] = ["env1", "env2", "env3", "outdoor20"];

fn builtin_source(name: &str) -> Option<&'static str> {
    Some(match name {
        "env1" => include_str!("../maps/env1.yaml"),
        "env2" => include_str!("../maps/env2.yaml"),
        "env3" => include_str!("../maps/env3.yaml"),
        "outdoor20" => include_str!("../maps/outdoor20.yaml"),
        _ => return None,
    })
}

fn is_zero(v: &f64) -> bool {
    *v == 0.0
}

fn default_height_m() -> f64 {
    1.0
}

#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Bounds {
    pub min: [f64; 2],
    pub max: [f64; 2],
}

/// One obstacle of a vector map. `height_m` decides whether the range sensor (mounted at
/// `SensorConfig::height_m`) sees it; every obstacle blocks the car.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum Obstacle {
    /// Solid rectangle, `size` = [length along x, width along y] before rotation.
    Box {
        center: [f64; 2],
        size: [f64; 2],
        #[serde(default)]
        angle_deg: f64,
        #[serde(default = "default_height_m")]
        height_m: f64,
    },
    /// Solid disc.
    Circle {
        center: [f64; 2],
        radius: f64,
        #[serde(default = "default_height_m")]
        height_m: f64,
    },
    /// Wall from `from` to `to`: a line, or a solid bar `VectorMapFile::wall_thickness_m` thick.
    Wall {
        from: [f64; 2],
        to: [f64; 2],
        #[serde(default = "default_height_m")]
        height_m: f64,
    },
    /// Solid simple polygon (vertices in order, not closed explicitly).
    Polygon {
        points: Vec<[f64; 2]>,
        #[serde(default = "default_height_m")]
        height_m: f64,
    },
}

/// A region of ground, e.g. under a tree canopy, that aerial surveillance cannot observe.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum Region {
    Circle { center: [f64; 2], radius: f64 },
    Polygon { points: Vec<[f64; 2]> },
}

/// The YAML document of a vector map.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VectorMapFile {
    pub format: String,
    pub name: String,
    #[serde(default)]
    pub description: String,
    pub bounds: Bounds,
    /// Closed walls along the bounds.
    #[serde(default)]
    pub boundary_walls: bool,
    /// How thick every `wall` of the map is, in metres, centred on its line and spanning exactly
    /// `from`–`to` (so a doorway between two walls keeps its width). 0 (the default) draws each
    /// wall as a line. A thin line seen end-on is invisible to a sparse scan: a ray parallel to it
    /// never hits it, so a wall pointing at the car shows nothing until the car touches it, which
    /// no real wall does. The paper's worlds set 1.0: its set-up follows MathWorks' obstacle
    /// avoidance example, whose map is an occupancy grid of 1 m cells (`mapScale = 1`), where
    /// every wall is at least one cell thick [inferred].
    #[serde(default, skip_serializing_if = "is_zero")]
    pub wall_thickness_m: f64,
    /// Each entry a one-key map: `- box: {...}` (serde_yaml's singleton-map enum form).
    #[serde(default, with = "serde_yaml::with::singleton_map_recursive")]
    pub obstacles: Vec<Obstacle>,
    #[serde(default, with = "serde_yaml::with::singleton_map_recursive")]
    pub shaded: Vec<Region>,
}

/// A trinary occupancy grid (from a ROS map). Row 0 is the bottom row (y = origin.y).
#[derive(Clone, Debug)]
pub struct OccupancyGrid {
    pub width: usize,
    pub height: usize,
    pub resolution_m: f64,
    pub origin: [f64; 2],
    /// Per cell: `true` where the car may be (known free).
    pub free: Vec<bool>,
}

impl OccupancyGrid {
    fn cell(&self, x: f64, y: f64) -> Option<usize> {
        let i = ((x - self.origin[0]) / self.resolution_m).floor();
        let j = ((y - self.origin[1]) / self.resolution_m).floor();
        if i < 0.0 || j < 0.0 || i >= self.width as f64 || j >= self.height as f64 {
            return None;
        }
        Some(j as usize * self.width + i as usize)
    }
    pub fn is_free(&self, x: f64, y: f64) -> bool {
        self.cell(x, y).is_some_and(|k| self.free[k])
    }
}

/// A loaded world, whatever its source.
#[derive(Clone, Debug)]
pub struct Map {
    pub name: String,
    pub description: String,
    pub bounds: Aabb,
    /// Vector obstacles (empty for grid maps, whose obstacles are in `grid`).
    pub obstacles: Vec<Obstacle>,
    pub boundary_walls: bool,
    pub shaded: Vec<Region>,
    pub grid: Option<OccupancyGrid>,
    /// Pre-computed obstacle geometry: segments [ax, ay, bx, by] and circles [x, y, r], each
    /// with its height.
    segments: Vec<([f64; 4], f64)>,
    circles: Vec<([f64; 3], f64)>,
}

impl Map {
    /// A built-in map by name.
    pub fn builtin(name: &str) -> Result<Map> {
        let src = builtin_source(name).ok_or_else(|| SimError::UnknownMap(name.to_string()))?;
        Self::from_vector_yaml(src, Path::new(&format!("<built-in {name}>")))
    }

    /// A built-in map name, or a path to a vector or ROS map YAML file (a generated world
    /// `gen:FAMILY:SEED` too: [`crate::worlds::resolve`]).
    pub fn resolve(name_or_path: &str) -> Result<Map> {
        if builtin_source(name_or_path).is_some() {
            return Self::builtin(name_or_path);
        }
        let p = Path::new(name_or_path);
        if p.extension().is_some_and(|e| e == "yaml" || e == "yml") || p.exists() {
            return Self::load(p);
        }
        Err(SimError::UnknownMap(name_or_path.to_string()))
    }

    /// Loads a map file, telling the two formats apart by their keys.
    pub fn load(path: &Path) -> Result<Map> {
        let text = std::fs::read_to_string(path).map_err(|e| map_err(path, format!("cannot read: {e}")))?;
        Self::parse(&text, path, |image| std::fs::read(image))
    }

    /// [`Map::load`] on a map file's text in hand (`path` names it in errors and places a ROS
    /// map's image): `read_image` returns the bytes of the image file the text names.
    pub fn parse(text: &str, path: &Path, read_image: impl FnOnce(&Path) -> std::io::Result<Vec<u8>>) -> Result<Map> {
        let probe: serde_yaml::Value = serde_yaml::from_str(text).map_err(|e| map_err(path, format!("not valid YAML: {e}")))?;
        let has = |k: &str| probe.get(k).is_some();
        if has("format") {
            Self::from_vector_yaml(text, path)
        } else if has("image") {
            Self::from_ros_yaml_with(text, path, read_image)
        } else {
            Err(map_err(path, format!("neither a vector map (no `format: {VECTOR_FORMAT}`) nor a ROS map_server map (no `image:`)")))
        }
    }

    /// Parses and validates a vector map.
    pub fn from_vector_yaml(text: &str, path: &Path) -> Result<Map> {
        let f: VectorMapFile = serde_yaml::from_str(text).map_err(|e| map_err(path, e.to_string()))?;
        if f.format != VECTOR_FORMAT {
            return Err(map_err(path, format!("unsupported format `{}` (expected `{VECTOR_FORMAT}`)", f.format)));
        }
        let [x0, y0] = f.bounds.min;
        let [x1, y1] = f.bounds.max;
        if ![x0, y0, x1, y1].iter().all(|v| v.is_finite()) || x1 <= x0 || y1 <= y0 {
            return Err(map_err(path, format!("bounds must be finite with min < max, got min {:?} max {:?}", f.bounds.min, f.bounds.max)));
        }
        let bounds = Aabb { min_x: x0, min_y: y0, max_x: x1, max_y: y1 };
        let t = f.wall_thickness_m;
        if !(t.is_finite() && t >= 0.0) {
            return Err(map_err(path, format!("wall_thickness_m must be finite and >= 0, got {t}")));
        }
        let mut map =
            Map { name: f.name, description: f.description, bounds, obstacles: f.obstacles, boundary_walls: f.boundary_walls, shaded: f.shaded, grid: None, segments: Vec::new(), circles: Vec::new() };
        map.validate_vector(path)?;
        if t > 0.0 {
            map.thicken_walls(t, path)?;
        }
        map.build_geometry();
        Ok(map)
    }

    fn validate_vector(&self, path: &Path) -> Result<()> {
        let b = &self.bounds;
        let tol = 1e-9;
        let inside = |p: &[f64; 2]| p[0] >= b.min_x - tol && p[0] <= b.max_x + tol && p[1] >= b.min_y - tol && p[1] <= b.max_y + tol;
        let finite = |v: &[f64]| v.iter().all(|x| x.is_finite());
        for (k, o) in self.obstacles.iter().enumerate() {
            let bad = |what: &str| map_err(path, format!("obstacle {k} ({}): {what}", o.kind()));
            if !(o.height_m().is_finite() && o.height_m() > 0.0) {
                return Err(bad("height_m must be > 0"));
            }
            match o {
                Obstacle::Box { center, size, angle_deg, .. } => {
                    if !finite(center) || !finite(size) || !angle_deg.is_finite() || size[0] <= 0.0 || size[1] <= 0.0 {
                        return Err(bad("center, size and angle must be finite, size > 0"));
                    }
                }
                Obstacle::Circle { center, radius, .. } => {
                    if !finite(center) || !radius.is_finite() || *radius <= 0.0 {
                        return Err(bad("center must be finite and radius > 0"));
                    }
                }
                Obstacle::Wall { from, to, .. } => {
                    if !finite(from) || !finite(to) || from == to {
                        return Err(bad("endpoints must be finite and distinct"));
                    }
                }
                Obstacle::Polygon { points, .. } => {
                    if points.len() < 3 || !points.iter().all(|p| finite(p)) {
                        return Err(bad("a polygon needs at least 3 finite points"));
                    }
                }
            }
            if !o.outline().iter().all(inside) {
                return Err(bad("lies outside the map bounds"));
            }
        }
        for (k, r) in self.shaded.iter().enumerate() {
            let ok = match r {
                Region::Circle { center, radius } => finite(center) && radius.is_finite() && *radius > 0.0,
                Region::Polygon { points } => points.len() >= 3 && points.iter().all(|p| finite(p)),
            };
            if !ok {
                return Err(map_err(path, format!("shaded region {k}: needs finite coordinates and a positive size")));
            }
        }
        Ok(())
    }

    /// Replaces every wall by a solid bar `t` thick centred on its line, spanning exactly its
    /// endpoints; a bar that would cross the map's bounds (a wall laid along them) is an error.
    fn thicken_walls(&mut self, t: f64, path: &Path) -> Result<()> {
        let b = self.bounds;
        let tol = 1e-9;
        for (k, o) in self.obstacles.iter_mut().enumerate() {
            if let Obstacle::Wall { from, to, height_m } = *o {
                let (dx, dy) = (to[0] - from[0], to[1] - from[1]);
                let bar = Obstacle::Box { center: [(from[0] + to[0]) / 2.0, (from[1] + to[1]) / 2.0], size: [dx.hypot(dy), t], angle_deg: dy.atan2(dx).to_degrees(), height_m };
                if !bar.outline().iter().all(|p| p[0] >= b.min_x - tol && p[0] <= b.max_x + tol && p[1] >= b.min_y - tol && p[1] <= b.max_y + tol) {
                    return Err(map_err(path, format!("obstacle {k} (wall): {t} m thick (wall_thickness_m), it reaches outside the map bounds")));
                }
                *o = bar;
            }
        }
        Ok(())
    }

    /// Flattens obstacles into segments and circles.
    fn build_geometry(&mut self) {
        let b = self.bounds;
        let mut segs = Vec::new();
        let mut circles = Vec::new();
        if self.boundary_walls {
            let c = [[b.min_x, b.min_y], [b.max_x, b.min_y], [b.max_x, b.max_y], [b.min_x, b.max_y]];
            for k in 0..4 {
                let (p, q) = (c[k], c[(k + 1) % 4]);
                segs.push(([p[0], p[1], q[0], q[1]], f64::INFINITY));
            }
        }
        for o in &self.obstacles {
            let h = o.height_m();
            match o {
                Obstacle::Circle { center, radius, .. } => circles.push(([center[0], center[1], *radius], h)),
                Obstacle::Wall { from, to, .. } => segs.push(([from[0], from[1], to[0], to[1]], h)),
                _ => {
                    let pts = o.outline();
                    for k in 0..pts.len() {
                        let (p, q) = (pts[k], pts[(k + 1) % pts.len()]);
                        segs.push(([p[0], p[1], q[0], q[1]], h));
                    }
                }
            }
        }
        self.segments = segs;
        self.circles = circles;
    }

    /// Obstacle geometry taller than `min_height_m`, indexed for ray casting and collision.
    /// `min_height_m = 0` gives everything the car can hit.
    pub fn scene(&self, min_height_m: f64, cell_m: f64) -> Scene {
        let segs: Vec<[f64; 4]> = self.segments.iter().filter(|(_, h)| *h > min_height_m).map(|(s, _)| *s).collect();
        let circles: Vec<[f64; 3]> = self.circles.iter().filter(|(_, h)| *h > min_height_m).map(|(c, _)| *c).collect();
        Scene::new(self.bounds, &segs, &circles, cell_m)
    }

    /// Segments [ax, ay, bx, by] of all obstacles (for drawing).
    pub fn segments(&self) -> impl Iterator<Item = [f64; 4]> + '_ {
        self.segments.iter().map(|(s, _)| *s)
    }
    /// Circles [x, y, r] of all obstacles (for drawing).
    pub fn circles(&self) -> impl Iterator<Item = [f64; 3]> + '_ {
        self.circles.iter().map(|(c, _)| *c)
    }

    /// True if the point is where the car may stand: inside the map, outside every solid
    /// obstacle, and (for grid maps) on a known-free cell.
    pub fn is_free(&self, x: f64, y: f64) -> bool {
        if !self.bounds.contains(x, y) {
            return false;
        }
        if let Some(g) = &self.grid {
            return g.is_free(x, y);
        }
        !self.obstacles.iter().any(|o| match o {
            Obstacle::Circle { center, radius, .. } => (x - center[0]).hypot(y - center[1]) <= *radius,
            Obstacle::Wall { .. } => false,
            _ => point_in_polygon(x, y, &o.outline()),
        })
    }

    /// Rasterises the map as a ROS map_server occupancy image at `resolution_m` per pixel:
    /// returns (width, height, pixels row 0 = top, 0 = occupied, 254 = free). A pixel is occupied
    /// if its centre is not free or (vector maps) lies within half a pixel diagonal of an
    /// obstacle surface, so thin walls stay closed in the raster.
    pub fn rasterize(&self, resolution_m: f64) -> Result<(usize, usize, Vec<u8>)> {
        if !(resolution_m.is_finite() && resolution_m > 0.0) {
            return Err(SimError::InvalidConfig(format!("resolution must be > 0, got {resolution_m}")));
        }
        // Pixels to cover a side: the ceiling, except that a side that is a whole number of
        // pixels up to rounding stays that number (3 cells of 0.4 m are 1.2000000000000002 m,
        // and a grid map rasterised at its own resolution must keep its size).
        let pixels = |side_m: f64| {
            let n = side_m / resolution_m;
            if (n - n.round()).abs() <= 1e-9 * n.max(1.0) { n.round() as usize } else { n.ceil() as usize }
        };
        let (w, h) = (pixels(self.bounds.width()), pixels(self.bounds.height()));
        if w == 0 || h == 0 || w > 20_000 || h > 20_000 {
            return Err(SimError::InvalidConfig(format!("raster of {w}x{h} pixels is out of range")));
        }
        let scene = self.scene(0.0, 2.0);
        let half_diag = resolution_m * std::f64::consts::FRAC_1_SQRT_2;
        let mut px = vec![254u8; w * h];
        for row in 0..h {
            let y = self.bounds.max_y - (row as f64 + 0.5) * resolution_m;
            for col in 0..w {
                let x = self.bounds.min_x + (col as f64 + 0.5) * resolution_m;
                // A grid map's walls are cell edges, never thinner than a cell: its raster is its
                // cells, so a ROS map written from a raster loads back to the same raster.
                let thin_wall_near = self.grid.is_none() && scene.distance_to_nearest(x, y) <= half_diag;
                if !self.is_free(x, y) || thin_wall_near {
                    px[row * w + col] = 0;
                }
            }
        }
        Ok((w, h, px))
    }

    /// True if the point lies in a shaded region.
    pub fn in_shade(&self, x: f64, y: f64) -> bool {
        self.shaded.iter().any(|r| r.contains(x, y))
    }

    /// Parses a ROS map_server YAML (`path` is where it was read, for the image's relative
    /// path and for errors) and its image, whose bytes come from `read_image`.
    fn from_ros_yaml_with(text: &str, path: &Path, read_image: impl FnOnce(&Path) -> std::io::Result<Vec<u8>>) -> Result<Map> {
        let meta: RosMapYaml = serde_yaml::from_str(text).map_err(|e| map_err(path, e.to_string()))?;
        if !(meta.resolution.is_finite() && meta.resolution > 0.0) {
            return Err(map_err(path, format!("resolution must be > 0, got {}", meta.resolution)));
        }
        if meta.origin.len() < 2 || !meta.origin.iter().all(|v| v.is_finite()) {
            return Err(map_err(path, "origin must be [x, y, yaw] with finite values".into()));
        }
        if meta.origin.get(2).is_some_and(|yaw| yaw.abs() > 1e-9) {
            return Err(map_err(path, "origin yaw ≠ 0 (rotated maps) is not supported".into()));
        }
        if !(0.0..=1.0).contains(&meta.free_thresh) || !(0.0..=1.0).contains(&meta.occupied_thresh) || meta.free_thresh >= meta.occupied_thresh {
            return Err(map_err(path, format!("thresholds must satisfy 0 ≤ free_thresh < occupied_thresh ≤ 1, got free {} occupied {}", meta.free_thresh, meta.occupied_thresh)));
        }
        if meta.negate > 1 {
            return Err(map_err(path, format!("negate must be 0 or 1, got {}", meta.negate)));
        }
        if let Some(mode) = &meta.mode
            && mode != "trinary"
            && mode != "scale"
            && mode != "raw"
        {
            return Err(map_err(path, format!("unknown mode `{mode}` (trinary, scale or raw)")));
        }
        let img_path = path.parent().unwrap_or(Path::new(".")).join(&meta.image);
        let bytes = read_image(&img_path).map_err(|e| map_err(&img_path, format!("cannot read image: {e}")))?;
        let img = crate::image::decode_gray(&bytes).map_err(|problem| map_err(&img_path, problem))?;
        let (w, h) = (img.width, img.height);
        // Image row 0 is the top of the map; grid row 0 is the bottom.
        let mut free = vec![false; w * h];
        let raw = meta.mode.as_deref() == Some("raw");
        for row in 0..h {
            for col in 0..w {
                let v = img.pixels[row * w + col] as f64;
                let j = h - 1 - row;
                free[j * w + col] = if raw {
                    v == 0.0 // raw: the value is the occupancy in percent
                } else {
                    let p = if meta.negate == 1 { v / 255.0 } else { (255.0 - v) / 255.0 };
                    p < meta.free_thresh
                };
            }
        }
        if !free.iter().any(|f| *f) {
            return Err(map_err(path, "the image has no free cell".into()));
        }
        let res = meta.resolution;
        let name = path.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_else(|| "ros-map".into());
        let grid = OccupancyGrid { width: w, height: h, resolution_m: res, origin: [meta.origin[0], meta.origin[1]], free };
        let description = format!("ROS map_server map {} ({w}x{h} cells at {res} m)", path.display());
        Ok(Self::from_grid(name, description, grid))
    }

    /// A map whose obstacles are the blocked cells of `grid` (outside the grid is blocked too):
    /// what a ROS map loads into, and what generated caves are.
    pub fn from_grid(name: String, description: String, grid: OccupancyGrid) -> Map {
        let (w, h, res) = (grid.width as f64, grid.height as f64, grid.resolution_m);
        let [ox, oy] = grid.origin;
        let bounds = Aabb { min_x: ox, min_y: oy, max_x: ox + w * res, max_y: oy + h * res };
        let segments = grid_boundary_segments(&grid).into_iter().map(|s| (s, f64::INFINITY)).collect();
        Map { name, description, bounds, obstacles: Vec::new(), boundary_walls: false, shaded: Vec::new(), grid: Some(grid), segments, circles: Vec::new() }
    }

    /// A vector map's YAML document (the inverse of [`Map::from_vector_yaml`]); `None` for a
    /// grid map, which has no vector form.
    pub fn to_vector_yaml(&self) -> Option<String> {
        if self.grid.is_some() {
            return None;
        }
        let b = self.bounds;
        let file = VectorMapFile {
            format: VECTOR_FORMAT.into(),
            name: self.name.clone(),
            description: self.description.clone(),
            bounds: Bounds { min: [b.min_x, b.min_y], max: [b.max_x, b.max_y] },
            boundary_walls: self.boundary_walls,
            // Thick walls were turned into boxes on loading: what is written is already solid.
            wall_thickness_m: 0.0,
            obstacles: self.obstacles.clone(),
            shaded: self.shaded.clone(),
        };
        serde_yaml::to_string(&file).ok()
    }

    /// Writes the map as a ROS map_server map, `dir/NAME.pgm` (P5, 0 occupied, 254 free) and
    /// `dir/NAME.yaml` (trinary, the thresholds map_server's defaults), at `resolution_m` metres
    /// per pixel; creates `dir`. Returns the YAML's path. Loading it back gives the same raster.
    pub fn write_ros(&self, dir: &Path, resolution_m: f64) -> Result<PathBuf> {
        let (w, h, px) = self.rasterize(resolution_m)?;
        let io = |p: &Path, e: std::io::Error| map_err(p, format!("cannot write: {e}"));
        std::fs::create_dir_all(dir).map_err(|e| io(dir, e))?;
        let mut pgm = format!("P5\n# mapless: {}\n{w} {h}\n255\n", self.name).into_bytes();
        pgm.extend_from_slice(&px);
        let pgm_path = dir.join(format!("{}.pgm", self.name));
        std::fs::write(&pgm_path, pgm).map_err(|e| io(&pgm_path, e))?;
        let yaml = format!(
            "image: {}.pgm\nresolution: {resolution_m}\norigin: [{}, {}, 0.0]\nnegate: 0\noccupied_thresh: 0.65\nfree_thresh: 0.196\nmode: trinary\n",
            self.name, self.bounds.min_x, self.bounds.min_y
        );
        let yaml_path = dir.join(format!("{}.yaml", self.name));
        std::fs::write(&yaml_path, yaml).map_err(|e| io(&yaml_path, e))?;
        Ok(yaml_path)
    }
}

impl Obstacle {
    pub fn kind(&self) -> &'static str {
        match self {
            Obstacle::Box { .. } => "box",
            Obstacle::Circle { .. } => "circle",
            Obstacle::Wall { .. } => "wall",
            Obstacle::Polygon { .. } => "polygon",
        }
    }
    pub fn height_m(&self) -> f64 {
        match self {
            Obstacle::Box { height_m, .. } | Obstacle::Circle { height_m, .. } | Obstacle::Wall { height_m, .. } | Obstacle::Polygon { height_m, .. } => *height_m,
        }
    }
    /// Outline points: box corners, polygon vertices, wall endpoints, or the circle's
    /// bounding-box corners.
    pub fn outline(&self) -> Vec<[f64; 2]> {
        match self {
            Obstacle::Box { center, size, angle_deg, .. } => {
                let (s, c) = angle_deg.to_radians().sin_cos();
                let (hx, hy) = (size[0] / 2.0, size[1] / 2.0);
                [(-hx, -hy), (hx, -hy), (hx, hy), (-hx, hy)].iter().map(|&(u, v)| [center[0] + c * u - s * v, center[1] + s * u + c * v]).collect()
            }
            Obstacle::Circle { center, radius, .. } => {
                let r = *radius;
                vec![[center[0] - r, center[1] - r], [center[0] + r, center[1] + r]]
            }
            Obstacle::Wall { from, to, .. } => vec![*from, *to],
            Obstacle::Polygon { points, .. } => points.clone(),
        }
    }
}

impl Region {
    pub fn contains(&self, x: f64, y: f64) -> bool {
        match self {
            Region::Circle { center, radius } => (x - center[0]).hypot(y - center[1]) <= *radius,
            Region::Polygon { points } => point_in_polygon(x, y, points),
        }
    }
}

#[derive(Debug, Deserialize)]
struct RosMapYaml {
    image: PathBuf,
    resolution: f64,
    origin: Vec<f64>,
    #[serde(default)]
    negate: u8,
    occupied_thresh: f64,
    free_thresh: f64,
    #[serde(default)]
    mode: Option<String>,
}

fn map_err(path: &Path, problem: String) -> SimError {
    SimError::MapFile { path: path.to_path_buf(), problem }
}

/// Even–odd point-in-polygon test.
pub fn point_in_polygon(x: f64, y: f64, pts: &[[f64; 2]]) -> bool {
    let mut inside = false;
    let n = pts.len();
    for k in 0..n {
        let (a, b) = (pts[k], pts[(k + n - 1) % n]);
        if (a[1] > y) != (b[1] > y) && x < (b[0] - a[0]) * (y - a[1]) / (b[1] - a[1]) + a[0] {
            inside = !inside;
        }
    }
    inside
}

/// The edges between free and blocked cells (outside the grid counts as blocked), merged into
/// maximal straight runs.
fn grid_boundary_segments(g: &OccupancyGrid) -> Vec<[f64; 4]> {
    let (w, h) = (g.width as i64, g.height as i64);
    let free = |i: i64, j: i64| i >= 0 && j >= 0 && i < w && j < h && g.free[(j * w + i) as usize];
    let (res, ox, oy) = (g.resolution_m, g.origin[0], g.origin[1]);
    let mut out = Vec::new();
    // Horizontal edges on grid line y = j (between rows j-1 and j).
    for j in 0..=h {
        let mut run: Option<i64> = None;
        for i in 0..=w {
            let edge = i < w && free(i, j - 1) != free(i, j);
            match (edge, run) {
                (true, None) => run = Some(i),
                (false, Some(i0)) => {
                    let y = oy + j as f64 * res;
                    out.push([ox + i0 as f64 * res, y, ox + i as f64 * res, y]);
                    run = None;
                }
                _ => {}
            }
        }
    }
    // Vertical edges on grid line x = i.
    for i in 0..=w {
        let mut run: Option<i64> = None;
        for j in 0..=h {
            let edge = j < h && free(i - 1, j) != free(i, j);
            match (edge, run) {
                (true, None) => run = Some(j),
                (false, Some(j0)) => {
                    let x = ox + i as f64 * res;
                    out.push([x, oy + j0 as f64 * res, x, oy + j as f64 * res]);
                    run = None;
                }
                _ => {}
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn builtin_maps_load_and_match_the_paper() {
        let env1 = Map::builtin("env1").unwrap();
        assert_eq!((env1.bounds.width(), env1.bounds.height()), (25.0, 25.0));
        assert_eq!(env1.obstacles.len(), 9); // a central block and eight stubs (sim/tests/paper_worlds.rs checks what they imply)
        let env2 = Map::builtin("env2").unwrap();
        assert_eq!((env2.bounds.width(), env2.bounds.height()), (40.0, 40.0));
        assert_eq!(env2.obstacles.len(), 43); // walls, medians, blocks, round ends (sim/tests/paper_worlds.rs checks what they imply)
        let env3 = Map::builtin("env3").unwrap();
        assert!(!env3.obstacles.is_empty());
        let out = Map::builtin("outdoor20").unwrap();
        assert_eq!((out.bounds.width(), out.bounds.height()), (20.0, 20.0));
        assert_eq!(out.obstacles.len(), 11); // 4 trunks + 7 boulders
        assert_eq!(out.shaded.len(), 4);
        assert!(out.in_shade(0.0, -6.5) && !out.in_shade(0.0, 0.0));
    }

    #[test]
    fn free_space_excludes_solid_obstacles_and_outside() {
        let env2 = Map::builtin("env2").unwrap();
        assert!(!env2.is_free(0.0, 0.0)); // inside the interior wall at y = 0
        assert!(!env2.is_free(15.4, 15.0)); // inside a round median end
        assert!(!env2.is_free(-5.5, -14.0)); // inside a block
        assert!(env2.is_free(-18.0, 18.0));
        assert!(env2.is_free(-10.5, 0.0)); // in a doorway
        assert!(!env2.is_free(25.0, 0.0));
    }

    #[test]
    fn unknown_map_name_is_a_clear_error() {
        let e = Map::resolve("env9").unwrap_err().to_string();
        assert!(e.contains("env9") && e.contains("env1"), "{e}");
    }

    #[test]
    fn grid_edges_of_a_single_blocked_cell_form_its_square() {
        // 3x3 grid, all free except the centre.
        let mut free = vec![true; 9];
        free[4] = false;
        let g = OccupancyGrid { width: 3, height: 3, resolution_m: 1.0, origin: [0.0, 0.0], free };
        let segs = grid_boundary_segments(&g);
        // 4 outer sides (grid border) + 4 sides of the centre cell.
        assert_eq!(segs.len(), 8, "{segs:?}");
        assert!(segs.contains(&[1.0, 1.0, 2.0, 1.0]) && segs.contains(&[0.0, 0.0, 3.0, 0.0]));
    }
}
