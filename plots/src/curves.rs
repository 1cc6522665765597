//! Training curves as PNG, like the paper's Figs. 6–9 (MATLAB's Episode Manager): two stacked
//! panels, "Episode return" and "Steps per episode", against the episode number. Each shows the
//! raw per-episode values faintly and their order-W trailing moving average (MATLAB's "average
//! window", W = 50 by default; `mapless_sim::stats::moving_average`) as a bold line, with
//! optional dashed reference lines (a stop criterion such as return ≥ 320 or steps ≥ 990).
//!
//! plotters lays the picture out and draws the axes (ticks on a 1-2-5 grid, tick labels, axis
//! titles), the captions, legends and text in the embedded DejaVu Sans; the data lines are
//! painted with tiny-skia (anti-aliased, at sub-pixel positions), clipped to the plot areas.
//!
//! Colours: raw values light blue ([`RAW_RGB`], translucent), moving average dark blue
//! ([`AVERAGE_RGB`], opaque, 2.5 px), reference lines red dashed ([`GOAL_RGB`]).
//!
//! Large runs stay cheap: above [`MAX_DRAWN_POINTS`] episodes the raw values are drawn as a
//! per-pixel-column min/max envelope and the average as per-column means, so 100,000 episodes
//! cost one O(n) pass. Non-finite values are skipped (lines break around them).

use std::path::Path;

use mapless_sim::stats::moving_average;
use plotters::prelude::*;
use plotters::style::text_anchor::HPos;
use tiny_skia::{FillRule, Mask, Paint, PathBuilder, Pixmap, Rect, Stroke, StrokeDash, Transform};

use crate::axis::{Axis, Ticked, fmt_value};
use crate::error::{PlotError, Result};
use crate::font;
use crate::picture::{Area, Picture, draw_err};

/// One finished training episode.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CurvePoint {
    /// Episode number (1-based), the x coordinate.
    pub episode: u64,
    pub episode_return: f64,
    pub steps: u32,
}

/// What to write on the chart and how to average.
#[derive(Debug, Clone, PartialEq)]
pub struct CurveStyle {
    /// First line of the picture, e.g. "env1 SAC — order-50 moving average".
    pub title: String,
    /// Order of the trailing moving average (MATLAB's average window); must be ≥ 1.
    pub window: usize,
    /// Dashed reference line in the return panel (e.g. the stop criterion 320).
    pub return_goal: Option<f64>,
    /// Dashed reference line in the steps panel (e.g. 990).
    pub steps_goal: Option<f64>,
    /// Last line of the picture (run id, date, config …).
    pub footer: String,
}

impl Default for CurveStyle {
    fn default() -> Self {
        CurveStyle { title: String::new(), window: 50, return_goal: None, steps_goal: None, footer: String::new() }
    }
}

/// Picture size in pixels.
pub const WIDTH_PX: u32 = 1000;
pub const HEIGHT_PX: u32 = 700;
/// Colour of the bold moving-average line (drawn opaque).
pub const AVERAGE_RGB: [u8; 3] = [10, 50, 150];
/// Colour of the raw per-episode values (drawn translucent, so lighter on white).
pub const RAW_RGB: [u8; 3] = [110, 160, 225];
/// Colour of the dashed reference lines and their labels.
pub const GOAL_RGB: [u8; 3] = [200, 40, 40];
/// Colour of the "no episodes yet" (or "no finite values") note.
pub const NOTE_RGB: [u8; 3] = [120, 120, 120];
/// Above this many episodes raw values and the average are reduced to one entry per pixel column.
pub const MAX_DRAWN_POINTS: usize = 2000;
/// Up to this many episodes every raw value also gets a dot.
const MAX_DOTS: usize = 400;

const TEXT_RGB: [u8; 3] = [20, 20, 20];
const MUTED_RGB: [u8; 3] = [90, 90, 90];
const FRAME_RGB: [u8; 3] = [60, 60, 60];
const GRID_RGB: [u8; 3] = [225, 225, 225];
const PLOT_BG_RGB: [u8; 3] = [252, 252, 252];

// Layout (pixels). Both plot areas span x PLOT_LEFT..PLOT_RIGHT; the return panel's plot area
// is y RETURN_TOP..RETURN_TOP+PANEL_H and the steps panel's STEPS_TOP..STEPS_TOP+PANEL_H, each
// with its caption and legend on the line above it.
const TITLE_BASELINE: i32 = 34;
const PLOT_LEFT: i32 = 96;
const PLOT_RIGHT: i32 = WIDTH_PX as i32 - 28;
const PANEL_H: i32 = 230;
const RETURN_TOP: i32 = 80;
const STEPS_TOP: i32 = 380;
/// Room left of the plot area for the tick labels and the rotated axis title.
const Y_LABELS_W: i32 = 84;
/// Room below a plot area for the tick labels (and, under the steps panel, the axis title).
const X_LABELS_H: i32 = 30;
const X_LABELS_AND_TITLE_H: i32 = 54;
const FOOTER_BASELINE: i32 = HEIGHT_PX as i32 - 14;

const TITLE_SIZE: f64 = 22.0;
const CAPTION_SIZE: f64 = 17.0;
const LABEL_SIZE: f64 = 14.0;
const FOOTER_SIZE: f64 = 14.0;

/// Draws the two-panel chart; errors ([`PlotError::Invalid`]) for window 0; an empty `points`
/// draws empty axes with "no episodes yet".
///
/// `points` are plotted in the given order (the average runs over that order); x is
/// `CurvePoint::episode`. The PNG ([`WIDTH_PX`] × [`HEIGHT_PX`]) is written atomically
/// (temp file + rename), creating the parent directory.
pub fn training_curves_png(points: &[CurvePoint], style: &CurveStyle, path: &Path) -> Result<()> {
    if style.window == 0 {
        return Err(PlotError::Invalid { what: "training curves", problem: "the moving-average window must be at least 1 (MATLAB's default is 50)".into() });
    }
    draw(points, style)?.save_png(path)
}

/// One panel's data and where it goes.
struct Panel<'a> {
    caption: &'static str,
    axis_title: &'static str,
    values: &'a [f64],
    avg: Vec<f64>,
    goal: Option<f64>,
    y_axis: Axis,
    top: i32,
    x_labels_h: i32,
}

impl Panel<'_> {
    fn plot(&self) -> PlotArea {
        PlotArea { x0: PLOT_LEFT as f32, y0: self.top as f32, x1: PLOT_RIGHT as f32, y1: (self.top + PANEL_H) as f32 }
    }
}

fn draw(points: &[CurvePoint], style: &CurveStyle) -> Result<Picture> {
    let mut pic = Picture::new(WIDTH_PX, HEIGHT_PX, "training curves")?;
    let xs: Vec<f64> = points.iter().map(|p| p.episode as f64).collect();
    let returns: Vec<f64> = points.iter().map(|p| p.episode_return).collect();
    let steps: Vec<f64> = points.iter().map(|p| f64::from(p.steps)).collect();
    let x_axis = match (xs.iter().copied().reduce(f64::min), xs.iter().copied().reduce(f64::max)) {
        // Episode 1 starts at 0, like MATLAB's Episode Manager.
        (Some(lo), Some(hi)) => Axis::nice((lo - 1.0).max(0.0), hi, 6.0),
        _ => Axis::nice(0.0, 10.0, 6.0),
    }
    .min_step(1.0);
    let panels = [
        make_panel("Episode return", "Return", &returns, style.return_goal, style.window, RETURN_TOP, X_LABELS_H),
        make_panel("Steps per episode", "Steps", &steps, style.steps_goal, style.window, STEPS_TOP, X_LABELS_AND_TITLE_H),
    ];

    // Frame, axes, text.
    pic.draw(|root| {
        font::draw(root, &style.title, TITLE_SIZE, TEXT_RGB, 24, TITLE_BASELINE, HPos::Left)?;
        for p in &panels {
            axes(root, p, &x_axis, p.x_labels_h == X_LABELS_AND_TITLE_H)?;
        }
        let footer_size = font::fit(root, &style.footer, FOOTER_SIZE, 9.0, WIDTH_PX - 48);
        font::draw(root, &style.footer, footer_size, MUTED_RGB, 24, FOOTER_BASELINE, HPos::Left)
    })?;
    // Data.
    pic.paint(|pixmap| {
        for p in &panels {
            paint_data(pixmap, &p.plot(), &x_axis, &p.y_axis, &xs, p.values, &p.avg, p.goal);
        }
    })?;
    // What goes over the data: goal labels, the empty note, the frame; caption and legend.
    pic.draw(|root| {
        for p in &panels {
            overlays(root, p, points.is_empty(), style.window)?;
        }
        Ok(())
    })?;
    Ok(pic)
}

fn make_panel<'a>(caption: &'static str, axis_title: &'static str, values: &'a [f64], goal: Option<f64>, window: usize, top: i32, x_labels_h: i32) -> Panel<'a> {
    let goal = goal.filter(|g| g.is_finite());
    let avg = moving_average(values, window);
    let y_axis = value_axis(values, &avg, goal);
    Panel { caption, axis_title, values, avg, goal, y_axis, top, x_labels_h }
}

/// The y axis over the finite values, averages and goal, with a little room so lines at the
/// extremes are not hidden by the frame, but no negative axis for values that cannot be
/// negative (steps).
fn value_axis(values: &[f64], avg: &[f64], goal: Option<f64>) -> Axis {
    let finite = values.iter().chain(avg).copied().chain(goal).filter(|v| v.is_finite());
    let (lo, hi) = finite.fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| (lo.min(v), hi.max(v)));
    if lo <= hi {
        let pad = (hi - lo) * 0.02;
        let lo_p = if lo >= 0.0 { (lo - pad).max(0.0) } else { lo - pad };
        let hi_p = if hi <= 0.0 { (hi + pad).min(0.0) } else { hi + pad };
        Axis::nice(lo_p, hi_p, 5.0)
    } else {
        Axis::nice(0.0, 1.0, 5.0)
    }
}

/// The panel's plot background, grid, axes with tick labels and axis titles (plotters).
fn axes(root: &Area, p: &Panel, xa: &Axis, x_title: bool) -> Result<()> {
    let err = draw_err("training curves");
    let ya = &p.y_axis;
    let area = root.clone().shrink((PLOT_LEFT - Y_LABELS_W, p.top), (PLOT_RIGHT - PLOT_LEFT + Y_LABELS_W, PANEL_H + p.x_labels_h));
    let mut chart = ChartBuilder::on(&area).y_label_area_size(Y_LABELS_W).x_label_area_size(p.x_labels_h).build_cartesian_2d(Ticked::new(xa), Ticked::new(ya)).map_err(&err)?;
    chart.plotting_area().fill(&font::rgb(PLOT_BG_RGB)).map_err(&err)?;
    let (xl, yl) = (|v: &f64| xa.label(*v), |v: &f64| ya.label(*v));
    let mut mesh = chart.configure_mesh();
    mesh.bold_line_style(font::rgb(GRID_RGB))
        .axis_style(font::rgb(FRAME_RGB))
        .label_style(font::style(LABEL_SIZE, TEXT_RGB))
        .axis_desc_style(font::style(CAPTION_SIZE - 1.0, TEXT_RGB))
        // plotters centres y labels on a box taller than the digits: bring them onto the tick.
        .y_label_offset((font::cap_height(LABEL_SIZE) * 0.35).round() as i32)
        .x_label_formatter(&xl)
        .y_label_formatter(&yl)
        .y_desc(p.axis_title);
    if x_title {
        mesh.x_desc("Episode");
    }
    mesh.draw().map_err(&err)?;
    // The frame, under the data: a value on the axis' end stays visible.
    let (x0, y0, x1, y1) = (PLOT_LEFT, p.top, PLOT_RIGHT, p.top + PANEL_H);
    root.draw(&Rectangle::new([(x0, y0), (x1, y1)], font::rgb(FRAME_RGB))).map_err(&err)
}

/// Goal label, the empty note, the frame, the caption and the legend (plotters).
fn overlays(root: &Area, p: &Panel, empty: bool, window: usize) -> Result<()> {
    let err = draw_err("training curves");
    let a = p.plot();
    let (x0, y0, x1, y1) = (a.x0 as i32, a.y0 as i32, a.x1 as i32, a.y1 as i32);
    if let Some(g) = p.goal {
        let (_, gy) = a.px(&Axis::within(0.0, 1.0, 1.0), &p.y_axis, 0.0, g.clamp(p.y_axis.lo, p.y_axis.hi));
        let s = format!("goal ≥ {}", fmt_value(g));
        let cap = font::cap_height(LABEL_SIZE).round() as i32;
        // Above the line unless that would leave the panel.
        let baseline = if gy as i32 - 6 - cap >= y0 + 4 { gy as i32 - 6 } else { gy as i32 + 6 + cap };
        boxed_text(root, &s, LABEL_SIZE, GOAL_RGB, x1 - 8, baseline, HPos::Right)?;
    }
    let note = if empty {
        Some("no episodes yet")
    } else if !p.values.iter().any(|v| v.is_finite()) {
        Some("no finite values")
    } else {
        None
    };
    if let Some(note) = note {
        let size = CAPTION_SIZE;
        boxed_text(root, note, size, NOTE_RGB, (x0 + x1) / 2, (y0 + y1) / 2 + (font::cap_height(size) / 2.0) as i32, HPos::Center)?;
    }

    // Caption, with the latest average, left; legend right; on the line above the plot.
    let baseline = y0 - 10;
    let last = p.avg.iter().rev().find(|v| v.is_finite());
    font::draw(root, p.caption, CAPTION_SIZE, TEXT_RGB, x0, baseline, HPos::Left)?;
    if let Some(v) = last {
        let x = x0 + font::width(root, p.caption, CAPTION_SIZE) as i32 + 12;
        font::draw(root, &format!("last average {}", fmt_value(*v)), LABEL_SIZE, MUTED_RGB, x, baseline, HPos::Left)?;
    }
    let avg_label = format!("average of {window}");
    let mut items = vec![(Swatch::Raw, "episode".to_string()), (Swatch::Average, avg_label)];
    if p.goal.is_some() {
        items.push((Swatch::Goal, "goal".to_string()));
    }
    const SWATCH: i32 = 24;
    const GAP: i32 = 20;
    let total: i32 = items.iter().map(|(_, s)| SWATCH + 6 + font::width(root, s, LABEL_SIZE) as i32 + GAP).sum::<i32>() - GAP;
    let mut x = x1 - total;
    let mid = baseline - (font::cap_height(LABEL_SIZE) / 2.0).round() as i32;
    for (swatch, s) in items {
        swatch.draw(root, x, mid, SWATCH).map_err(&err)?;
        x += SWATCH + 6;
        font::draw(root, &s, LABEL_SIZE, TEXT_RGB, x, baseline, HPos::Left)?;
        x += font::width(root, &s, LABEL_SIZE) as i32 + GAP;
    }
    Ok(())
}

/// Text on a translucent white box, readable over data.
fn boxed_text(root: &Area, s: &str, size: f64, c: [u8; 3], x: i32, baseline: i32, h: HPos) -> Result<()> {
    let w = font::width(root, s, size) as i32;
    let left = match h {
        HPos::Left => x,
        HPos::Center => x - w / 2,
        HPos::Right => x - w,
    };
    let cap = font::cap_height(size).round() as i32;
    let descent = (size * 0.236 / 1.164).round() as i32;
    root.draw(&Rectangle::new([(left - 4, baseline - cap - 4), (left + w + 4, baseline + descent + 3)], WHITE.mix(0.85).filled())).map_err(draw_err("training curves"))?;
    font::draw(root, s, size, c, x, baseline, h)
}

/// Legend swatches, drawn as the lines they stand for.
enum Swatch {
    Raw,
    Average,
    Goal,
}

impl Swatch {
    fn draw(&self, root: &Area, x: i32, y: i32, w: i32) -> std::result::Result<(), DrawingAreaErrorKind<<BitMapBackend<'_> as DrawingBackend>::ErrorType>> {
        match self {
            Swatch::Raw => {
                root.draw(&PathElement::new(vec![(x, y), (x + w, y)], font::rgb(RAW_RGB).stroke_width(2)))?;
                root.draw(&Circle::new((x + w / 2, y), 3, font::rgb(RAW_RGB).filled()))
            }
            Swatch::Average => root.draw(&PathElement::new(vec![(x, y), (x + w, y)], font::rgb(AVERAGE_RGB).stroke_width(3))),
            Swatch::Goal => {
                for k in 0..3 {
                    let a = x + k * 9;
                    root.draw(&PathElement::new(vec![(a, y), ((a + 6).min(x + w), y)], font::rgb(GOAL_RGB).stroke_width(2)))?;
                }
                Ok(())
            }
        }
    }
}

#[derive(Debug, Clone, Copy)]
struct PlotArea {
    x0: f32,
    y0: f32,
    x1: f32,
    y1: f32,
}

impl PlotArea {
    fn width(&self) -> f32 {
        self.x1 - self.x0
    }
    /// Pixel position of (x, y), as plotters maps it (x.lo at x0, x.hi at x1; y.lo at y1).
    fn px(&self, xa: &Axis, ya: &Axis, x: f64, y: f64) -> (f32, f32) {
        let frac = |a: &Axis, v: f64| ((v - a.lo) / (a.hi - a.lo)) as f32;
        (self.x0 + frac(xa, x) * self.width(), self.y1 - frac(ya, y) * (self.y1 - self.y0))
    }
    /// The plot area and a 3-pixel rim: a dot or line end on the axis' end shows whole, over
    /// the frame.
    fn mask(&self) -> Option<Mask> {
        let r = Rect::from_ltrb(self.x0 - 3.0, self.y0 - 3.0, self.x1 + 3.0, self.y1 + 3.0)?;
        let mut m = Mask::new(WIDTH_PX, HEIGHT_PX)?;
        m.fill_path(&PathBuilder::from_rect(r), FillRule::Winding, false, Transform::identity());
        Some(m)
    }
}

fn paint(rgb: [u8; 3], a: u8) -> Paint<'static> {
    let mut p = Paint::default();
    p.set_color_rgba8(rgb[0], rgb[1], rgb[2], a);
    p.anti_alias = true;
    p
}

/// Raw values, goal line and moving average of one panel (tiny-skia), clipped to its plot area
/// (and rim).
fn paint_data(pixmap: &mut Pixmap, area: &PlotArea, xa: &Axis, ya: &Axis, xs: &[f64], ys: &[f64], avg: &[f64], goal: Option<f64>) {
    let mask = area.mask();
    let mask = mask.as_ref();
    // Values beyond the axis (only ever beyond ±1e300) are drawn at its end.
    let at = |x: f64, y: f64| area.px(xa, ya, x, y.clamp(ya.lo, ya.hi));
    let raw_line = paint(RAW_RGB, 110);
    let goal_line = |pixmap: &mut Pixmap| {
        if let Some(g) = goal {
            let (_, y) = at(xa.lo, g);
            segment(pixmap, (area.x0, y), (area.x1, y), 1.5, &paint(GOAL_RGB, 255), StrokeDash::new(vec![8.0, 5.0], 0.0), mask);
        }
    };
    if xs.len() > MAX_DRAWN_POINTS {
        let cols = columns(area, xa, ya, xs, ys, avg);
        // Raw values: a min–max envelope, one vertical run per pixel column.
        let env = cols.iter().flat_map(|c| [c.map(|c| (c.x, c.min)), c.map(|c| (c.x, c.max))]);
        polyline(pixmap, env, 1.0, &raw_line, mask);
        goal_line(pixmap);
        let means = cols.iter().map(|c| c.and_then(|c| (c.avg_n > 0).then(|| (c.x, at(xa.lo, c.avg_sum / c.avg_n as f64).1))));
        polyline(pixmap, means, 2.5, &paint(AVERAGE_RGB, 255), mask);
    } else {
        let pts: Vec<Option<(f32, f32)>> = xs.iter().zip(ys).map(|(&x, &y)| y.is_finite().then(|| at(x, y))).collect();
        polyline(pixmap, pts.iter().copied(), 1.0, &raw_line, mask);
        if xs.len() <= MAX_DOTS {
            let dot = paint(RAW_RGB, 170);
            for (x, y) in pts.iter().flatten() {
                if let Some(path) = PathBuilder::from_circle(*x, *y, 2.0) {
                    pixmap.fill_path(&path, &dot, FillRule::Winding, Transform::identity(), mask);
                }
            }
        }
        goal_line(pixmap);
        let avg_pts = xs.iter().zip(avg).map(|(&x, &y)| y.is_finite().then(|| at(x, y)));
        polyline(pixmap, avg_pts, 2.5, &paint(AVERAGE_RGB, 255), mask);
    }
}

fn segment(pixmap: &mut Pixmap, a: (f32, f32), b: (f32, f32), width: f32, p: &Paint, dash: Option<StrokeDash>, mask: Option<&Mask>) {
    let mut pb = PathBuilder::new();
    pb.move_to(a.0, a.1);
    pb.line_to(b.0, b.1);
    if let Some(path) = pb.finish() {
        let stroke = Stroke { width, dash, ..Stroke::default() };
        pixmap.stroke_path(&path, p, &stroke, Transform::identity(), mask);
    }
}

/// Strokes a polyline through the given pixel points; `None` breaks the line. A point alone
/// between breaks (a single episode, an average between non-finite values) is a round dot.
fn polyline(pixmap: &mut Pixmap, pts: impl Iterator<Item = Option<(f32, f32)>>, width: f32, p: &Paint, mask: Option<&Mask>) {
    let mut pb = PathBuilder::new();
    // Points in the current run, and the last one.
    let mut run: Option<(usize, (f32, f32))> = None;
    let end_run = |pb: &mut PathBuilder, run: Option<(usize, (f32, f32))>| {
        if let Some((1, (x, y))) = run {
            pb.line_to(x + 0.01, y); // a zero-length segment gets no round caps
        }
    };
    for pt in pts {
        match pt {
            Some((x, y)) if x.is_finite() && y.is_finite() => {
                run = Some(match run {
                    Some((n, _)) => {
                        pb.line_to(x, y);
                        (n + 1, (x, y))
                    }
                    None => {
                        pb.move_to(x, y);
                        (1, (x, y))
                    }
                });
            }
            _ => {
                end_run(&mut pb, run);
                run = None;
            }
        }
    }
    end_run(&mut pb, run);
    if let Some(path) = pb.finish() {
        let stroke = Stroke { width, line_join: tiny_skia::LineJoin::Round, line_cap: tiny_skia::LineCap::Round, ..Stroke::default() };
        pixmap.stroke_path(&path, p, &stroke, Transform::identity(), mask);
    }
}

/// Per-pixel-column summary of many episodes.
#[derive(Debug, Clone, Copy)]
struct Column {
    x: f32,
    /// Pixel y of the smallest and largest finite raw value (infinite if none: breaks the line).
    min: f32,
    max: f32,
    /// Sum and count of the finite moving-average values, in data units.
    avg_sum: f64,
    avg_n: usize,
}

fn columns(area: &PlotArea, xa: &Axis, ya: &Axis, xs: &[f64], ys: &[f64], avg: &[f64]) -> Vec<Option<Column>> {
    let n_cols = area.width().ceil().max(1.0) as usize;
    let mut cols: Vec<Option<Column>> = vec![None; n_cols + 1];
    for ((&x, &y), &a) in xs.iter().zip(ys).zip(avg) {
        let (px, _) = area.px(xa, ya, x, 0.0);
        let k = ((px - area.x0).floor().max(0.0) as usize).min(n_cols);
        let cx = area.x0 + k as f32 + 0.5;
        let py = if y.is_finite() { area.px(xa, ya, x, y.clamp(ya.lo, ya.hi)).1 } else { f32::NAN };
        let c = cols[k].get_or_insert(Column { x: cx, min: f32::INFINITY, max: f32::NEG_INFINITY, avg_sum: 0.0, avg_n: 0 });
        if py.is_finite() {
            c.min = c.min.min(py);
            c.max = c.max.max(py);
        }
        if a.is_finite() {
            c.avg_sum += a;
            c.avg_n += 1;
        }
    }
    cols
}
