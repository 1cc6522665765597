//! Pictures: a map, and an episode on it — trajectory, the EQS cells it visited and the rings
//! around its start (like the paper's Figs. 5, 10 and 12). PNG via tiny-skia.
//!
//! Colours: obstacles dark grey, walls black, shaded regions (canopies) green, visited EQS cells
//! light blue, rings dashed grey with their index n, trajectory blue from the green start dot to
//! the end (a red cross if the episode ended in a collision).

use std::path::Path;

use tiny_skia::{Color, FillRule, Mask, Paint, PathBuilder, Pixmap, Rect, Stroke, StrokeDash, Transform};

use crate::error::{Result, SimError};
use crate::explore::ExplorationTracker;
use crate::font;
use crate::map::{Map, Obstacle, Region};

const MARGIN_PX: f32 = 24.0;
const TITLE_PX: f32 = 40.0;
const FOOTER_PX: f32 = 46.0;

/// A map drawn at a fixed scale, ready for overlays.
pub struct Canvas {
    pixmap: Pixmap,
    min_x: f64,
    max_y: f64,
    px_per_m: f32,
}

fn paint(r: u8, g: u8, b: u8, a: u8) -> Paint<'static> {
    let mut p = Paint::default();
    p.set_color_rgba8(r, g, b, a);
    p.anti_alias = true;
    p
}

impl Canvas {
    /// Draws `map` at `px_per_m` pixels per metre with a title line and a scale bar.
    pub fn map(map: &Map, px_per_m: f32, title: &str) -> Result<Canvas> {
        let b = map.bounds;
        let w = (b.width() as f32 * px_per_m + 2.0 * MARGIN_PX).ceil() as u32;
        let h = (b.height() as f32 * px_per_m + 2.0 * MARGIN_PX + TITLE_PX + FOOTER_PX).ceil() as u32;
        let mut pixmap = Pixmap::new(w.max(1), h.max(1)).ok_or_else(|| SimError::InvalidConfig(format!("picture size {w}x{h} not drawable")))?;
        pixmap.fill(Color::WHITE);
        let mut c = Canvas { pixmap, min_x: b.min_x, max_y: b.max_y, px_per_m };
        // The floor.
        let (x0, y0) = c.px(b.min_x, b.max_y);
        if let Some(r) = Rect::from_xywh(x0, y0, b.width() as f32 * px_per_m, b.height() as f32 * px_per_m) {
            c.pixmap.fill_rect(r, &paint(250, 248, 242, 255), Transform::identity(), None);
        }
        if let Some(g) = &map.grid {
            c.draw_grid(map, g);
        }
        for r in &map.shaded {
            c.fill_region(r, paint(60, 160, 60, 90));
        }
        c.draw_obstacles(map);
        c.text(MARGIN_PX, 12.0, 2.0, title, [20, 20, 20]);
        c.scale_bar(map);
        Ok(c)
    }

    /// World (x, y) to pixel coordinates (y grows downwards in the picture).
    fn px(&self, x: f64, y: f64) -> (f32, f32) {
        (MARGIN_PX + ((x - self.min_x) as f32) * self.px_per_m, TITLE_PX + MARGIN_PX + ((self.max_y - y) as f32) * self.px_per_m)
    }

    fn draw_grid(&mut self, map: &Map, g: &crate::map::OccupancyGrid) {
        // Paint every picture pixel of the map area from the cell under its centre.
        let (w, _) = (self.pixmap.width() as usize, self.pixmap.height());
        let (x0, y0) = self.px(map.bounds.min_x, map.bounds.max_y);
        let (x1, y1) = self.px(map.bounds.max_x, map.bounds.min_y);
        let dark = tiny_skia::PremultipliedColorU8::from_rgba(70, 70, 70, 255).expect("opaque colour");
        let ppm = self.px_per_m as f64;
        let pixels = self.pixmap.pixels_mut();
        for py in y0.floor() as usize..(y1.ceil() as usize) {
            for px in x0.floor() as usize..(x1.ceil() as usize) {
                let wx = map.bounds.min_x + (px as f64 + 0.5 - x0 as f64) / ppm;
                let wy = map.bounds.max_y - (py as f64 + 0.5 - y0 as f64) / ppm;
                if map.bounds.contains(wx, wy)
                    && !g.is_free(wx, wy)
                    && let Some(p) = pixels.get_mut(py * w + px)
                {
                    *p = dark;
                }
            }
        }
    }

    fn fill_region(&mut self, r: &Region, p: Paint) {
        let path = match r {
            Region::Circle { center, radius } => {
                let (cx, cy) = self.px(center[0], center[1]);
                PathBuilder::from_circle(cx, cy, *radius as f32 * self.px_per_m)
            }
            Region::Polygon { points } => self.polygon_path(points),
        };
        if let Some(path) = path {
            self.pixmap.fill_path(&path, &p, FillRule::Winding, Transform::identity(), None);
        }
    }

    fn polygon_path(&self, pts: &[[f64; 2]]) -> Option<tiny_skia::Path> {
        let mut pb = PathBuilder::new();
        for (k, p) in pts.iter().enumerate() {
            let (x, y) = self.px(p[0], p[1]);
            if k == 0 { pb.move_to(x, y) } else { pb.line_to(x, y) }
        }
        pb.close();
        pb.finish()
    }

    /// Obstacles and walls (vector maps; grid maps are painted cell by cell).
    fn draw_obstacles(&mut self, map: &Map) {
        for o in &map.obstacles {
            self.draw_obstacle(o);
        }
        if map.grid.is_none() {
            let black = paint(20, 20, 20, 255);
            for s in map.segments() {
                self.line(s[0], s[1], s[2], s[3], 2.0, &black, None);
            }
        }
    }

    fn draw_obstacle(&mut self, o: &Obstacle) {
        let fill = paint(90, 90, 90, 255);
        let path = match o {
            Obstacle::Circle { center, radius, height_m } => {
                let (cx, cy) = self.px(center[0], center[1]);
                // Tall round obstacles (tree trunks) in brown, rocks in grey.
                let p = if *height_m > 2.0 { paint(110, 70, 30, 255) } else { fill.clone() };
                if let Some(path) = PathBuilder::from_circle(cx, cy, (*radius as f32 * self.px_per_m).max(1.5)) {
                    self.pixmap.fill_path(&path, &p, FillRule::Winding, Transform::identity(), None);
                }
                return;
            }
            Obstacle::Wall { .. } => return, // drawn with the segments
            _ => self.polygon_path(&o.outline()),
        };
        if let Some(path) = path {
            self.pixmap.fill_path(&path, &fill, FillRule::Winding, Transform::identity(), None);
        }
    }

    fn line(&mut self, ax: f64, ay: f64, bx: f64, by: f64, width: f32, p: &Paint, dash: Option<StrokeDash>) {
        let (x0, y0) = self.px(ax, ay);
        let (x1, y1) = self.px(bx, by);
        let mut pb = PathBuilder::new();
        pb.move_to(x0, y0);
        pb.line_to(x1, y1);
        if let Some(path) = pb.finish() {
            let stroke = Stroke { width, dash, ..Stroke::default() };
            self.pixmap.stroke_path(&path, p, &stroke, Transform::identity(), None);
        }
    }

    /// Text in the 5×7 font at pixel (x, y) (top-left), each font pixel `scale` pixels.
    pub fn text(&mut self, x: f32, y: f32, scale: f32, s: &str, rgb: [u8; 3]) {
        let mut p = paint(rgb[0], rgb[1], rgb[2], 255);
        p.anti_alias = false; // font pixels are squares; AA fill of off-canvas rects trips tiny-skia
        font::draw(&mut self.pixmap, x, y, scale, s.chars().map(font::glyph), &p);
    }

    fn scale_bar(&mut self, map: &Map) {
        let span = map.bounds.width();
        let metres = [1.0, 2.0, 5.0, 10.0, 20.0, 50.0].into_iter().rev().find(|m| *m <= span / 4.0).unwrap_or(1.0);
        let y = self.pixmap.height() as f32 - FOOTER_PX + 8.0;
        let x = MARGIN_PX;
        let len = metres as f32 * self.px_per_m;
        let black = paint(20, 20, 20, 255);
        if let Some(r) = Rect::from_xywh(x, y, len, 4.0) {
            self.pixmap.fill_rect(r, &black, Transform::identity(), None);
        }
        self.text(x + len + 8.0, y - 5.0, 2.0, &format!("{metres} M"), [20, 20, 20]);
    }

    /// Overlays an episode: visited EQS cells, rings around the start, the path, start and end.
    pub fn episode(&mut self, map: &Map, trajectory: &[[f64; 2]], tracker: &ExplorationTracker, ring_width_m: f64, collided: bool) {
        let Some(&start) = trajectory.first() else { return };
        let side = tracker.cell_side_m();
        let cell_paint = paint(80, 150, 230, 70);
        for (i, j) in tracker.visited_cells() {
            let x = map.bounds.min_x + i as f64 * side;
            let y = map.bounds.min_y + (j as f64 + 1.0) * side;
            let (px, py) = self.px(x, y);
            let s = side as f32 * self.px_per_m;
            if let Some(r) = Rect::from_xywh(px, py, s, s) {
                self.pixmap.fill_rect(r, &cell_paint, Transform::identity(), None);
            }
        }
        // Obstacles stay visible over the cell shading.
        self.draw_obstacles(map);
        // Rings up to the farthest map corner.
        let b = map.bounds;
        let far = [(b.min_x, b.min_y), (b.max_x, b.min_y), (b.min_x, b.max_y), (b.max_x, b.max_y)].iter().map(|(x, y)| (x - start[0]).hypot(y - start[1])).fold(0.0, f64::max);
        let ring_paint = paint(120, 120, 120, 200);
        let (sx, sy) = self.px(start[0], start[1]);
        // Rings are clipped to the map area.
        let clip = self.map_mask(map);
        let mut n = 1;
        while (n as f64 - 1.0) * ring_width_m < far {
            let r = (n as f64 * ring_width_m) as f32 * self.px_per_m;
            if let Some(path) = PathBuilder::from_circle(sx, sy, r) {
                let stroke = Stroke { width: 1.5, dash: StrokeDash::new(vec![6.0, 4.0], 0.0), ..Stroke::default() };
                self.pixmap.stroke_path(&path, &ring_paint, &stroke, Transform::identity(), clip.as_ref());
            }
            // Label each ring inside its band, on the diagonal towards the map's centre.
            let label_r = (n as f64 - 0.5) * ring_width_m;
            let (mx, my) = ((b.min_x + b.max_x) / 2.0 - start[0], (b.min_y + b.max_y) / 2.0 - start[1]);
            let d = std::f64::consts::FRAC_1_SQRT_2;
            let (ux, uy) = (if mx >= 0.0 { d } else { -d }, if my >= 0.0 { d } else { -d });
            let (wx, wy) = (start[0] + label_r * ux, start[1] + label_r * uy);
            if b.contains(wx, wy) {
                let (lx, ly) = self.px(wx, wy);
                self.text(lx - 5.0, ly - 7.0, 2.0, &n.to_string(), [110, 110, 110]);
            }
            n += 1;
        }
        // The path.
        let mut pb = PathBuilder::new();
        for (k, p) in trajectory.iter().enumerate() {
            let (x, y) = self.px(p[0], p[1]);
            if k == 0 { pb.move_to(x, y) } else { pb.line_to(x, y) }
        }
        if let Some(path) = pb.finish() {
            let stroke = Stroke { width: 2.0, ..Stroke::default() };
            self.pixmap.stroke_path(&path, &paint(30, 70, 200, 255), &stroke, Transform::identity(), None);
        }
        if let Some(path) = PathBuilder::from_circle(sx, sy, 5.0) {
            self.pixmap.fill_path(&path, &paint(20, 160, 40, 255), FillRule::Winding, Transform::identity(), None);
        }
        if let Some(&end) = trajectory.last() {
            let red = paint(220, 30, 30, 255);
            let d = 6.0 / self.px_per_m as f64;
            if collided {
                self.line(end[0] - d, end[1] - d, end[0] + d, end[1] + d, 3.0, &red, None);
                self.line(end[0] - d, end[1] + d, end[0] + d, end[1] - d, 3.0, &red, None);
            } else {
                let (ex, ey) = self.px(end[0], end[1]);
                if let Some(path) = PathBuilder::from_circle(ex, ey, 4.0) {
                    self.pixmap.fill_path(&path, &paint(30, 70, 200, 255), FillRule::Winding, Transform::identity(), None);
                }
            }
        }
    }

    /// A mask that lets drawing through only inside the map's bounds.
    fn map_mask(&self, map: &Map) -> Option<Mask> {
        let (x0, y0) = self.px(map.bounds.min_x, map.bounds.max_y);
        let rect = Rect::from_xywh(x0, y0, map.bounds.width() as f32 * self.px_per_m, map.bounds.height() as f32 * self.px_per_m)?;
        let mut mask = Mask::new(self.pixmap.width(), self.pixmap.height())?;
        mask.fill_path(&PathBuilder::from_rect(rect), FillRule::Winding, false, Transform::identity());
        Some(mask)
    }

    /// Writes a line of text in the footer, right of the scale bar.
    pub fn footer(&mut self, s: &str) {
        let y = self.pixmap.height() as f32 - FOOTER_PX + 26.0;
        self.text(MARGIN_PX, y, 2.0, s, [60, 60, 60]);
    }

    pub fn width(&self) -> u32 {
        self.pixmap.width()
    }
    pub fn height(&self) -> u32 {
        self.pixmap.height()
    }
    /// RGBA value of a pixel (for tests).
    pub fn pixel(&self, x: u32, y: u32) -> Option<[u8; 4]> {
        self.pixmap.pixel(x, y).map(|p| {
            let c = p.demultiply();
            [c.red(), c.green(), c.blue(), c.alpha()]
        })
    }
    /// Pixel position of a world point (for tests and overlays).
    pub fn world_to_px(&self, x: f64, y: f64) -> (f32, f32) {
        self.px(x, y)
    }

    /// Encodes PNG and writes it atomically (temp file + rename).
    pub fn save_png(&self, path: &Path) -> Result<()> {
        let out_err = |problem: String| SimError::Output { path: path.to_path_buf(), problem };
        let bytes = self.pixmap.encode_png().map_err(|e| out_err(e.to_string()))?;
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).map_err(|e| out_err(e.to_string()))?;
        }
        let tmp = path.with_extension("png.tmp");
        std::fs::write(&tmp, bytes).map_err(|e| out_err(e.to_string()))?;
        std::fs::rename(&tmp, path).map_err(|e| out_err(e.to_string()))
    }
}

/// Default scale: about 900 pixels across the map's longer side.
pub fn default_px_per_m(map: &Map) -> f32 {
    (900.0 / map.bounds.width().max(map.bounds.height()) as f32).clamp(2.0, 200.0)
}
