//! Pictures of a map and of an episode on it — trajectory, the EQS cells it visited and the
//! rings around its start (like the paper's Figs. 5, 10 and 12).
//!
//! The map sits in a frame with axes in metres (plotters: ticks, tick labels, axis titles, the
//! title and footer lines in the embedded DejaVu Sans); the map itself, the cells, rings and
//! path are painted with tiny-skia (anti-aliased), one map metre `px_per_m` pixels.
//!
//! Colours: obstacles dark grey, walls black, shaded regions (canopies) green, visited EQS cells
//! light blue, rings dashed grey with their index n, trajectory blue from the green start dot to
//! the end (a red cross if the episode ended in a collision).

use std::path::Path;

use mapless_sim::ExplorationTracker;
use mapless_sim::map::{Map, Obstacle, OccupancyGrid, Region};
use plotters::prelude::*;
use plotters::style::text_anchor::HPos;
use tiny_skia::{FillRule, Mask, Paint, PathBuilder, Pixmap, Rect, Stroke, StrokeDash, Transform};

use crate::axis::{Axis, Ticked, nice_step};
use crate::error::{PlotError, Result};
use crate::font;
use crate::picture::{Picture, draw_err};

/// Left of the map: tick labels and the rotated "y (m)".
const LEFT_PX: f32 = 70.0;
/// Above the map: the title line.
const TOP_PX: f32 = 50.0;
const RIGHT_PX: f32 = 24.0;
/// Blank edge left of the rotated "y (m)" and of the title and footer lines.
const EDGE_PX: i32 = 10;
/// Below the map: tick labels and "x (m)".
const X_LABELS_PX: f32 = 50.0;
/// One footer line (one is always there).
const FOOTER_LINE_PX: u32 = 24;
const BOTTOM_PAD_PX: u32 = 8;

const TITLE_SIZE: f64 = 20.0;
const LABEL_SIZE: f64 = 14.0;
const AXIS_TITLE_SIZE: f64 = 15.0;
const FOOTER_SIZE: f64 = 15.0;
const RING_LABEL_SIZE: f64 = 14.0;
const TEXT_RGB: [u8; 3] = [20, 20, 20];
const FOOTER_RGB: [u8; 3] = [60, 60, 60];
const FRAME_RGB: [u8; 3] = [60, 60, 60];

/// A map drawn at a fixed scale, ready for overlays.
pub struct Canvas {
    pic: Picture,
    geo: Geo,
    /// Footer lines written so far.
    footer_lines: u32,
}

/// Where the map lies in the picture.
#[derive(Debug, Clone, Copy)]
struct Geo {
    min_x: f64,
    max_y: f64,
    px_per_m: f32,
    /// Map area in pixels: left, top, width, height.
    left: f32,
    top: f32,
    w: f32,
    h: f32,
}

impl Geo {
    /// World (x, y) to pixel coordinates (y grows downwards in the picture).
    fn px(&self, x: f64, y: f64) -> (f32, f32) {
        (self.left + ((x - self.min_x) as f32) * self.px_per_m, self.top + ((self.max_y - y) as f32) * self.px_per_m)
    }

    /// A mask that lets drawing through only inside the map's area.
    fn mask(&self, width: u32, height: u32) -> Option<Mask> {
        let rect = Rect::from_xywh(self.left, self.top, self.w, self.h)?;
        let mut mask = Mask::new(width, height)?;
        mask.fill_path(&PathBuilder::from_rect(rect), FillRule::Winding, false, Transform::identity());
        Some(mask)
    }
}

fn paint(r: u8, g: u8, b: u8, a: u8) -> Paint<'static> {
    let mut p = Paint::default();
    p.set_color_rgba8(r, g, b, a);
    p.anti_alias = true;
    p
}

impl Canvas {
    /// Draws `map` at `px_per_m` pixels per metre, in a frame with axes in metres and a title.
    pub fn map(map: &Map, px_per_m: f32, title: &str) -> Result<Canvas> {
        let b = map.bounds;
        if !(px_per_m.is_finite() && px_per_m > 0.0) {
            return Err(PlotError::Invalid { what: "map picture", problem: format!("{px_per_m} pixels per metre") });
        }
        let (mw, mh) = ((b.width() as f32 * px_per_m).ceil().max(1.0), (b.height() as f32 * px_per_m).ceil().max(1.0));
        let w = (LEFT_PX + mw + RIGHT_PX) as u32;
        let h = (TOP_PX + mh + X_LABELS_PX) as u32 + FOOTER_LINE_PX + BOTTOM_PAD_PX;
        let mut pic = Picture::new(w, h, "map picture")?;
        let geo = Geo { min_x: b.min_x, max_y: b.max_y, px_per_m, left: LEFT_PX, top: TOP_PX, w: mw, h: mh };

        pic.draw(|root| {
            let err = draw_err("map picture");
            let size = font::fit(root, title, TITLE_SIZE, 10.0, w.saturating_sub(EDGE_PX as u32 + RIGHT_PX as u32));
            font::draw(root, title, size, TEXT_RGB, EDGE_PX, (TOP_PX - 18.0) as i32, HPos::Left)?;
            // Axes in metres: the plot area is the map's pixels, one pixel 1/px_per_m metres.
            let (x0, x1) = (b.min_x, b.min_x + f64::from(mw / px_per_m));
            let (y0, y1) = (b.max_y - f64::from(mh / px_per_m), b.max_y);
            // A tick every 1-2-5 × 10^k metres, at least 60 pixels apart.
            let step = nice_step(60.0 / f64::from(px_per_m));
            let (xa, ya) = (Axis::within(x0, x1, step), Axis::within(y0, y1, step));
            let area = root.clone().shrink((EDGE_PX, TOP_PX as i32), ((LEFT_PX + mw) as i32 - EDGE_PX, (mh + X_LABELS_PX) as i32));
            let mut chart =
                ChartBuilder::on(&area).y_label_area_size(LEFT_PX as i32 - EDGE_PX).x_label_area_size(X_LABELS_PX as i32).build_cartesian_2d(Ticked::new(&xa), Ticked::new(&ya)).map_err(&err)?;
            let (xl, yl) = (|v: &f64| xa.label(*v), |v: &f64| ya.label(*v));
            chart
                .configure_mesh()
                .disable_mesh()
                .axis_style(font::rgb(FRAME_RGB))
                .label_style(font::style(LABEL_SIZE, TEXT_RGB))
                .axis_desc_style(font::style(AXIS_TITLE_SIZE, TEXT_RGB))
                .y_label_offset((font::cap_height(LABEL_SIZE) * 0.35).round() as i32)
                .x_label_formatter(&xl)
                .y_label_formatter(&yl)
                .x_desc("x (m)")
                .y_desc("y (m)")
                .draw()
                .map_err(&err)?;
            Ok(())
        })?;
        let (pw, ph) = (pic.width(), pic.height());
        pic.paint(|pixmap| {
            // The floor.
            if let Some(r) = Rect::from_xywh(geo.left, geo.top, b.width() as f32 * px_per_m, b.height() as f32 * px_per_m) {
                pixmap.fill_rect(r, &paint(250, 248, 242, 255), Transform::identity(), None);
            }
            if let Some(g) = &map.grid {
                draw_grid(pixmap, &geo, map, g);
            }
            let clip = geo.mask(pw, ph);
            for r in &map.shaded {
                fill_region(pixmap, &geo, r, paint(60, 160, 60, 90), clip.as_ref());
            }
            draw_obstacles(pixmap, &geo, map, clip.as_ref());
        })?;
        let mut c = Canvas { pic, geo, footer_lines: 0 };
        c.frame()?;
        Ok(c)
    }

    /// A 1-pixel frame just outside the map's area (over the axis lines).
    fn frame(&mut self) -> Result<()> {
        let g = self.geo;
        self.pic.draw(|root| {
            let (l, t) = (g.left as i32 - 1, g.top as i32 - 1);
            let (r, b) = ((g.left + g.w) as i32, (g.top + g.h) as i32);
            root.draw(&Rectangle::new([(l, t), (r, b)], font::rgb(FRAME_RGB))).map_err(draw_err("map picture"))
        })
    }

    /// Text in the embedded font, `size_px` pixels (ascent plus descent; capitals are about
    /// 0.63 of it), the top of its capitals at pixel (x, y).
    pub fn text(&mut self, x: f32, y: f32, size_px: f32, s: &str, rgb: [u8; 3]) -> Result<()> {
        let size = f64::from(size_px);
        self.pic.draw(|root| font::draw(root, s, size, rgb, x.round() as i32, (f64::from(y) + font::cap_height(size)).round() as i32, HPos::Left))
    }

    /// Overlays an episode: visited EQS cells, rings around the start, the path, start and end.
    pub fn episode(&mut self, map: &Map, trajectory: &[[f64; 2]], tracker: &ExplorationTracker, ring_width_m: f64, collided: bool) -> Result<()> {
        let Some(&start) = trajectory.first() else { return Ok(()) };
        let geo = self.geo;
        let (pw, ph) = (self.pic.width(), self.pic.height());
        let b = map.bounds;
        // Ring n is at n·ring_width from the start, up to the farthest map corner; each is
        // labelled inside its band, on the diagonal towards the map's centre.
        let far = [(b.min_x, b.min_y), (b.max_x, b.min_y), (b.min_x, b.max_y), (b.max_x, b.max_y)].iter().map(|(x, y)| (x - start[0]).hypot(y - start[1])).fold(0.0, f64::max);
        let rings = if ring_width_m > 0.0 && ring_width_m.is_finite() { (far / ring_width_m).floor() as usize + 1 } else { 0 };
        let rings = rings.min(1000);
        let mut labels = Vec::new();
        for n in 1..=rings {
            let label_r = (n as f64 - 0.5) * ring_width_m;
            let (mx, my) = ((b.min_x + b.max_x) / 2.0 - start[0], (b.min_y + b.max_y) / 2.0 - start[1]);
            let d = std::f64::consts::FRAC_1_SQRT_2;
            let (ux, uy) = (if mx >= 0.0 { d } else { -d }, if my >= 0.0 { d } else { -d });
            let (wx, wy) = (start[0] + label_r * ux, start[1] + label_r * uy);
            if b.contains(wx, wy) {
                labels.push((n, geo.px(wx, wy)));
            }
        }
        self.pic.paint(|pixmap| {
            let clip = geo.mask(pw, ph);
            let side = tracker.cell_side_m();
            let cell_paint = paint(80, 150, 230, 70);
            for (i, j) in tracker.visited_cells() {
                let x = b.min_x + i as f64 * side;
                let y = b.min_y + (j as f64 + 1.0) * side;
                let (px, py) = geo.px(x, y);
                let s = side as f32 * geo.px_per_m;
                if let Some(r) = Rect::from_xywh(px, py, s, s) {
                    pixmap.fill_rect(r, &cell_paint, Transform::identity(), clip.as_ref());
                }
            }
            // Obstacles stay visible over the cell shading.
            draw_obstacles(pixmap, &geo, map, clip.as_ref());
            let ring_paint = paint(120, 120, 120, 200);
            let (sx, sy) = geo.px(start[0], start[1]);
            for n in 1..=rings {
                let r = (n as f64 * ring_width_m) as f32 * geo.px_per_m;
                if let Some(path) = PathBuilder::from_circle(sx, sy, r) {
                    let stroke = Stroke { width: 1.5, dash: StrokeDash::new(vec![6.0, 4.0], 0.0), ..Stroke::default() };
                    pixmap.stroke_path(&path, &ring_paint, &stroke, Transform::identity(), clip.as_ref());
                }
            }
            // The path.
            let mut pb = PathBuilder::new();
            for (k, p) in trajectory.iter().enumerate() {
                let (x, y) = geo.px(p[0], p[1]);
                if k == 0 { pb.move_to(x, y) } else { pb.line_to(x, y) }
            }
            if let Some(path) = pb.finish() {
                let stroke = Stroke { width: 2.0, line_join: tiny_skia::LineJoin::Round, line_cap: tiny_skia::LineCap::Round, ..Stroke::default() };
                pixmap.stroke_path(&path, &paint(30, 70, 200, 255), &stroke, Transform::identity(), None);
            }
            if let Some(path) = PathBuilder::from_circle(sx, sy, 5.0) {
                pixmap.fill_path(&path, &paint(20, 160, 40, 255), FillRule::Winding, Transform::identity(), None);
            }
            if let Some(&end) = trajectory.last() {
                let red = paint(220, 30, 30, 255);
                let d = 6.0 / geo.px_per_m as f64;
                if collided {
                    line(pixmap, &geo, [end[0] - d, end[1] - d, end[0] + d, end[1] + d], 3.0, &red, None);
                    line(pixmap, &geo, [end[0] - d, end[1] + d, end[0] + d, end[1] - d], 3.0, &red, None);
                } else {
                    let (ex, ey) = geo.px(end[0], end[1]);
                    if let Some(path) = PathBuilder::from_circle(ex, ey, 4.0) {
                        pixmap.fill_path(&path, &paint(30, 70, 200, 255), FillRule::Winding, Transform::identity(), None);
                    }
                }
            }
        })?;
        // Ring numbers, on a translucent white patch so they read over obstacles and cells.
        self.pic.draw(|root| {
            let cap = font::cap_height(RING_LABEL_SIZE);
            for (n, (lx, ly)) in labels {
                let s = n.to_string();
                let w = font::width(root, &s, RING_LABEL_SIZE) as i32;
                let (cx, base) = (lx.round() as i32, (f64::from(ly) + cap / 2.0).round() as i32);
                let patch = [(cx - w / 2 - 3, base - cap.round() as i32 - 3), (cx + w / 2 + 3, base + 3)];
                root.draw(&Rectangle::new(patch, WHITE.mix(0.7).filled())).map_err(draw_err("episode picture"))?;
                font::draw(root, &s, RING_LABEL_SIZE, [90, 90, 90], cx, base, HPos::Center)?;
            }
            Ok(())
        })?;
        self.frame()
    }

    /// Writes a line of text under the map and its axes; each call adds a line (the picture
    /// grows from the second on).
    pub fn footer(&mut self, s: &str) -> Result<()> {
        if self.footer_lines > 0 {
            self.pic.grow(FOOTER_LINE_PX);
        }
        let baseline = (self.geo.top + self.geo.h + X_LABELS_PX) as i32 + 17 + (self.footer_lines * FOOTER_LINE_PX) as i32;
        self.footer_lines += 1;
        let max_w = self.pic.width().saturating_sub(2 * EDGE_PX as u32);
        self.pic.draw(|root| {
            let size = font::fit(root, s, FOOTER_SIZE, 9.0, max_w);
            font::draw(root, s, size, FOOTER_RGB, EDGE_PX, baseline, HPos::Left)
        })
    }

    pub fn width(&self) -> u32 {
        self.pic.width()
    }
    pub fn height(&self) -> u32 {
        self.pic.height()
    }
    /// RGBA value of a pixel (for tests; the picture is opaque).
    pub fn pixel(&self, x: u32, y: u32) -> Option<[u8; 4]> {
        self.pic.rgb(x, y).map(|[r, g, b]| [r, g, b, 255])
    }
    /// Pixel position of a world point (for tests and overlays).
    pub fn world_to_px(&self, x: f64, y: f64) -> (f32, f32) {
        self.geo.px(x, y)
    }

    /// Encodes PNG and writes it atomically (temp file + rename), creating the parent directory.
    pub fn save_png(&self, path: &Path) -> Result<()> {
        self.pic.save_png(path)
    }
}

/// Default scale: about 900 pixels across the map's longer side.
pub fn default_px_per_m(map: &Map) -> f32 {
    (900.0 / map.bounds.width().max(map.bounds.height()) as f32).clamp(2.0, 200.0)
}

/// Occupied cells of a grid map: every picture pixel of the map area from the cell under its centre.
fn draw_grid(pixmap: &mut Pixmap, geo: &Geo, map: &Map, g: &OccupancyGrid) {
    let w = pixmap.width() as usize;
    let (x0, y0) = geo.px(map.bounds.min_x, map.bounds.max_y);
    let (x1, y1) = geo.px(map.bounds.max_x, map.bounds.min_y);
    let dark = tiny_skia::PremultipliedColorU8::from_rgba(70, 70, 70, 255).expect("opaque colour");
    let ppm = geo.px_per_m as f64;
    let pixels = pixmap.pixels_mut();
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

fn fill_region(pixmap: &mut Pixmap, geo: &Geo, r: &Region, p: Paint, clip: Option<&Mask>) {
    let path = match r {
        Region::Circle { center, radius } => {
            let (cx, cy) = geo.px(center[0], center[1]);
            PathBuilder::from_circle(cx, cy, *radius as f32 * geo.px_per_m)
        }
        Region::Polygon { points } => polygon_path(geo, points),
    };
    if let Some(path) = path {
        pixmap.fill_path(&path, &p, FillRule::Winding, Transform::identity(), clip);
    }
}

fn polygon_path(geo: &Geo, pts: &[[f64; 2]]) -> Option<tiny_skia::Path> {
    let mut pb = PathBuilder::new();
    for (k, p) in pts.iter().enumerate() {
        let (x, y) = geo.px(p[0], p[1]);
        if k == 0 { pb.move_to(x, y) } else { pb.line_to(x, y) }
    }
    pb.close();
    pb.finish()
}

/// Obstacles and walls (vector maps; grid maps are painted cell by cell).
fn draw_obstacles(pixmap: &mut Pixmap, geo: &Geo, map: &Map, clip: Option<&Mask>) {
    for o in &map.obstacles {
        draw_obstacle(pixmap, geo, o, clip);
    }
    if map.grid.is_none() {
        let black = paint(20, 20, 20, 255);
        for s in map.segments() {
            line(pixmap, geo, s, 2.0, &black, None);
        }
    }
}

fn draw_obstacle(pixmap: &mut Pixmap, geo: &Geo, o: &Obstacle, clip: Option<&Mask>) {
    let fill = paint(90, 90, 90, 255);
    let path = match o {
        Obstacle::Circle { center, radius, height_m } => {
            let (cx, cy) = geo.px(center[0], center[1]);
            // Tall round obstacles (tree trunks) in brown, rocks in grey.
            let p = if *height_m > 2.0 { paint(110, 70, 30, 255) } else { fill.clone() };
            if let Some(path) = PathBuilder::from_circle(cx, cy, (*radius as f32 * geo.px_per_m).max(1.5)) {
                pixmap.fill_path(&path, &p, FillRule::Winding, Transform::identity(), clip);
            }
            return;
        }
        Obstacle::Wall { .. } => return, // drawn with the segments
        _ => polygon_path(geo, &o.outline()),
    };
    if let Some(path) = path {
        pixmap.fill_path(&path, &fill, FillRule::Winding, Transform::identity(), clip);
    }
}

/// A straight line between world points [ax, ay, bx, by].
fn line(pixmap: &mut Pixmap, geo: &Geo, s: [f64; 4], width: f32, p: &Paint, dash: Option<StrokeDash>) {
    let (x0, y0) = geo.px(s[0], s[1]);
    let (x1, y1) = geo.px(s[2], s[3]);
    let mut pb = PathBuilder::new();
    pb.move_to(x0, y0);
    pb.line_to(x1, y1);
    if let Some(path) = pb.finish() {
        let stroke = Stroke { width, dash, ..Stroke::default() };
        pixmap.stroke_path(&path, p, &stroke, Transform::identity(), None);
    }
}
