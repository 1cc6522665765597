//! Training curves as PNG, like the paper's Figs. 6–9 (MATLAB's Episode Manager): two stacked
//! panels, "Episode return" and "Episode steps", against the episode number. Each shows the raw
//! per-episode values faintly and their order-W trailing moving average (MATLAB's "average
//! window", W = 50 by default) as a bold line, with optional dashed reference lines (a stop
//! criterion such as return >= 320 or steps >= 990).
//!
//! Colours: raw values light blue ([`RAW_RGB`], translucent), moving average dark blue
//! ([`AVERAGE_RGB`], opaque, 2.5 px), reference lines red dashed ([`GOAL_RGB`]). Text uses the
//! 5×7 bitmap font of `render` (upper case; `—`, `≥`, `≤` are written as `-`, `>=`, `<=`).
//!
//! Large runs stay cheap: above [`MAX_DRAWN_POINTS`] episodes the raw values are drawn as a
//! per-pixel-column min/max envelope and the average as per-column means, so 100,000 episodes
//! cost one O(n) pass. Non-finite values are skipped (lines break around them).

use std::path::Path;

use tiny_skia::{Color, FillRule, Mask, Paint, PathBuilder, Pixmap, Rect, Stroke, StrokeDash, Transform};

use crate::error::{Result, SimError};
use crate::font;

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
/// Above this many episodes raw values and the average are reduced to one entry per pixel column.
pub const MAX_DRAWN_POINTS: usize = 2000;
/// Up to this many episodes every raw value also gets a dot.
const MAX_DOTS: usize = 400;

const TEXT_RGB: [u8; 3] = [20, 20, 20];
const FONT_SCALE: f32 = 2.0;
const PLOT_LEFT: f32 = 92.0;
const PLOT_RIGHT: f32 = WIDTH_PX as f32 - 28.0;
const PANEL_H: f32 = 235.0;
const RETURN_TOP: f32 = 68.0;
const STEPS_TOP: f32 = 362.0;

/// Order-`window` trailing moving average (first window-1 points average what exists).
///
/// Entry i is the mean of the finite values among `values[i+1-window ..= i]` (fewer at the
/// start); NaN where that range holds no finite value. A `window` of 0 is treated as 1 (the
/// values themselves, non-finite ones as NaN); [`training_curves_png`] rejects 0. O(n) for any
/// window: a running sum, recomputed exactly every `window` entries so rounding cannot drift.
pub fn moving_average(values: &[f64], window: usize) -> Vec<f64> {
    let w = window.max(1);
    let mut out = Vec::with_capacity(values.len());
    let (mut sum, mut count) = (0.0f64, 0usize);
    for (i, &v) in values.iter().enumerate() {
        if v.is_finite() {
            sum += v;
            count += 1;
        }
        if i >= w {
            let old = values[i - w];
            if old.is_finite() {
                sum -= old;
                count -= 1;
            }
        }
        if (i + 1) % w == 0 {
            let (s, c) = values[i + 1 - w..=i].iter().filter(|x| x.is_finite()).fold((0.0, 0), |(s, c), x| (s + x, c + 1));
            sum = s;
            count = c;
        }
        out.push(if count > 0 { sum / count as f64 } else { f64::NAN });
    }
    out
}

/// Draws the two-panel chart; errors (SimError) for window 0; an empty `points` draws empty axes with "no episodes yet".
///
/// `points` are plotted in the given order (the average runs over that order); x is
/// `CurvePoint::episode`. The PNG ([`WIDTH_PX`] × [`HEIGHT_PX`]) is written atomically
/// (temp file + rename), creating the parent directory.
pub fn training_curves_png(points: &[CurvePoint], style: &CurveStyle, path: &Path) -> Result<()> {
    if style.window == 0 {
        return Err(SimError::InvalidConfig("training curves: moving-average window must be at least 1 (MATLAB's default is 50)".into()));
    }
    let pixmap = draw(points, style)?;
    save_png(&pixmap, path)
}

fn draw(points: &[CurvePoint], style: &CurveStyle) -> Result<Pixmap> {
    let mut pixmap = Pixmap::new(WIDTH_PX, HEIGHT_PX).ok_or_else(|| SimError::InvalidConfig("training curves: picture not drawable".into()))?;
    pixmap.fill(Color::WHITE);
    let mut c = Chart { pixmap };

    let xs: Vec<f64> = points.iter().map(|p| p.episode as f64).collect();
    let returns: Vec<f64> = points.iter().map(|p| p.episode_return).collect();
    let steps: Vec<f64> = points.iter().map(|p| f64::from(p.steps)).collect();
    let x_axis = match (xs.iter().copied().reduce(f64::min), xs.iter().copied().reduce(f64::max)) {
        // Episode 1 starts at 0, like MATLAB's Episode Manager.
        (Some(lo), Some(hi)) => Axis::nice((lo - 1.0).max(0.0), hi, 6.0),
        _ => Axis::nice(0.0, 10.0, 6.0),
    };

    c.text(24.0, 12.0, &style.title, TEXT_RGB);
    let panels = [(RETURN_TOP, "Episode return", &returns, style.return_goal), (STEPS_TOP, "Episode steps", &steps, style.steps_goal)];
    for (top, label, values, goal) in panels {
        let area = PlotArea { x0: PLOT_LEFT, y0: top, x1: PLOT_RIGHT, y1: top + PANEL_H };
        let avg = moving_average(values, style.window);
        c.panel(&area, label, &xs, values, &avg, &x_axis, goal, style.window);
    }
    let xl = "Episode";
    c.text((PLOT_LEFT + PLOT_RIGHT) / 2.0 - text_width(xl) / 2.0, STEPS_TOP + PANEL_H + 30.0, xl, TEXT_RGB);
    c.text(24.0, HEIGHT_PX as f32 - 30.0, &style.footer, [60, 60, 60]);
    Ok(c.pixmap)
}

/// Encodes PNG and writes it atomically (temp file + rename), as `render::Canvas::save_png`.
fn save_png(pixmap: &Pixmap, path: &Path) -> Result<()> {
    let out_err = |problem: String| SimError::Output { path: path.to_path_buf(), problem };
    let bytes = pixmap.encode_png().map_err(|e| out_err(e.to_string()))?;
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).map_err(|e| out_err(e.to_string()))?;
    }
    let tmp = path.with_extension("png.tmp");
    std::fs::write(&tmp, bytes).map_err(|e| out_err(e.to_string()))?;
    std::fs::rename(&tmp, path).map_err(|e| out_err(e.to_string()))
}

/// An axis from `lo` to `hi` with ticks every `step` (1-2-5 × 10^k), both ends on ticks.
#[derive(Debug, Clone, Copy)]
struct Axis {
    lo: f64,
    hi: f64,
    step: f64,
}

impl Axis {
    /// At most `target` + 2 intervals covering [min, max], the finest 1-2-5 step that allows it;
    /// a degenerate range is widened.
    fn nice(min: f64, max: f64, target: f64) -> Axis {
        let (mut min, mut max) = (min.max(-1e300), max.min(1e300));
        if max.partial_cmp(&min) != Some(std::cmp::Ordering::Greater) {
            let pad = if min.abs() > 1.0 { min.abs() * 0.1 } else { 1.0 };
            (min, max) = (min - pad, min + pad);
        }
        let mut step = nice_step((max - min) / (2.0 * target));
        for _ in 0..64 {
            if (max / step).ceil() - (min / step).floor() <= target + 2.0 {
                break;
            }
            step = nice_step(step * 1.5);
        }
        let lo = (min / step).floor() * step;
        let mut hi = (max / step).ceil() * step;
        if hi <= lo {
            hi = lo + step;
        }
        Axis { lo, hi, step }
    }

    fn ticks(&self) -> Vec<f64> {
        let n = ((self.hi - self.lo) / self.step).round();
        if !(n.is_finite() && n <= 100.0) {
            return vec![self.lo, self.hi];
        }
        (0..=n as usize).map(|k| self.lo + k as f64 * self.step).collect()
    }

    /// Fraction 0..1 of the way from lo to hi.
    fn frac(&self, v: f64) -> f64 {
        (v - self.lo) / (self.hi - self.lo)
    }

    fn label(&self, v: f64) -> String {
        if self.lo.abs().max(self.hi.abs()) >= 1e6 || self.step < 1e-6 {
            return format!("{v:e}");
        }
        let decimals = (-self.step.log10().floor()).clamp(0.0, 6.0) as usize;
        let s = format!("{v:.decimals$}");
        if s.trim_start_matches('-').chars().all(|c| c == '0' || c == '.') { s.trim_start_matches('-').to_string() } else { s }
    }
}

/// The 1-2-5 × 10^k value nearest above `raw`.
fn nice_step(raw: f64) -> f64 {
    if !(raw.is_finite() && raw > 0.0) {
        return 1.0;
    }
    let mag = 10f64.powf(raw.log10().floor());
    let norm = raw / mag;
    let m = if norm <= 1.0 {
        1.0
    } else if norm <= 2.0 {
        2.0
    } else if norm <= 5.0 {
        5.0
    } else {
        10.0
    };
    m * mag
}

/// Short form of a value for labels: integers without decimals, otherwise 4 significant digits.
fn fmt_value(v: f64) -> String {
    if v.abs() >= 1e6 {
        format!("{v:.3e}")
    } else if v.fract() == 0.0 {
        format!("{v:.0}")
    } else {
        let decimals = (3 - v.abs().max(1e-9).log10().floor() as i32).clamp(0, 6) as usize;
        let s = format!("{v:.decimals$}");
        s.trim_end_matches('0').trim_end_matches('.').to_string()
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
    fn px(&self, xa: &Axis, ya: &Axis, x: f64, y: f64) -> (f32, f32) {
        (self.x0 + (xa.frac(x) as f32) * self.width(), self.y1 - (ya.frac(y) as f32) * (self.y1 - self.y0))
    }
}

fn paint(rgb: [u8; 3], a: u8) -> Paint<'static> {
    let mut p = Paint::default();
    p.set_color_rgba8(rgb[0], rgb[1], rgb[2], a);
    p.anti_alias = true;
    p
}

/// Replaces characters the bitmap font lacks with ASCII look-alikes.
fn normalize(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    for ch in s.chars() {
        match ch {
            '—' | '–' | '−' | '‐' => out.push('-'),
            '≥' => out.push_str(">="),
            '≤' => out.push_str("<="),
            '×' => out.push('X'),
            '·' => out.push('.'),
            '…' => out.push_str("..."),
            '≈' => out.push('~'),
            '\t' | '\n' | '\r' => out.push(' '),
            c => out.push(c),
        }
    }
    out
}

/// The render font plus a few characters it lacks.
fn glyph(c: char) -> [u8; 7] {
    match c {
        '>' => [0x10, 0x08, 0x04, 0x02, 0x04, 0x08, 0x10],
        '<' => [0x01, 0x02, 0x04, 0x08, 0x04, 0x02, 0x01],
        '[' => [0x0E, 0x08, 0x08, 0x08, 0x08, 0x08, 0x0E],
        ']' => [0x0E, 0x02, 0x02, 0x02, 0x02, 0x02, 0x0E],
        '#' => [0x0A, 0x0A, 0x1F, 0x0A, 0x1F, 0x0A, 0x0A],
        '*' => [0x00, 0x04, 0x15, 0x0E, 0x15, 0x04, 0x00],
        '!' => [0x04, 0x04, 0x04, 0x04, 0x04, 0x00, 0x04],
        '?' => [0x0E, 0x11, 0x01, 0x02, 0x04, 0x00, 0x04],
        '|' => [0x04; 7],
        '~' => [0x00, 0x00, 0x08, 0x15, 0x02, 0x00, 0x00],
        '"' => [0x0A, 0x0A, 0x00, 0x00, 0x00, 0x00, 0x00],
        c => font::glyph(c),
    }
}

fn text_width(s: &str) -> f32 {
    let n = normalize(s).chars().count() as f32;
    if n == 0.0 { 0.0 } else { n * 6.0 * FONT_SCALE - FONT_SCALE }
}

struct Chart {
    pixmap: Pixmap,
}

impl Chart {
    /// Text in the 5×7 font at pixel (x, y) (top-left), each font pixel 2×2; off-picture pixels are skipped.
    fn text(&mut self, x: f32, y: f32, s: &str, rgb: [u8; 3]) {
        let mut p = paint(rgb, 255);
        p.anti_alias = false;
        font::draw(&mut self.pixmap, x, y, FONT_SCALE, normalize(s).chars().map(glyph), &p);
    }

    fn segment(&mut self, a: (f32, f32), b: (f32, f32), width: f32, p: &Paint, dash: Option<StrokeDash>, mask: Option<&Mask>) {
        let mut pb = PathBuilder::new();
        pb.move_to(a.0, a.1);
        pb.line_to(b.0, b.1);
        if let Some(path) = pb.finish() {
            let stroke = Stroke { width, dash, ..Stroke::default() };
            self.pixmap.stroke_path(&path, p, &stroke, Transform::identity(), mask);
        }
    }

    /// Strokes a polyline through the given pixel points; `None` breaks the line.
    fn polyline(&mut self, pts: impl Iterator<Item = Option<(f32, f32)>>, width: f32, p: &Paint, mask: Option<&Mask>) {
        let mut pb = PathBuilder::new();
        let mut pen_down = false;
        for pt in pts {
            match pt {
                Some((x, y)) if x.is_finite() && y.is_finite() => {
                    if pen_down {
                        pb.line_to(x, y)
                    } else {
                        pb.move_to(x, y)
                    }
                    pen_down = true;
                }
                _ => pen_down = false,
            }
        }
        if let Some(path) = pb.finish() {
            let stroke = Stroke { width, line_join: tiny_skia::LineJoin::Round, line_cap: tiny_skia::LineCap::Round, ..Stroke::default() };
            self.pixmap.stroke_path(&path, p, &stroke, Transform::identity(), mask);
        }
    }

    /// One panel: frame, grid and tick labels, raw values, moving average, reference line, legend.
    #[allow(clippy::too_many_arguments)]
    fn panel(&mut self, area: &PlotArea, label: &str, xs: &[f64], ys: &[f64], avg: &[f64], xa: &Axis, goal: Option<f64>, window: usize) {
        let goal = goal.filter(|g| g.is_finite());
        let finite = ys.iter().chain(avg).copied().chain(goal).filter(|v| v.is_finite());
        let (lo, hi) = finite.fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| (lo.min(v), hi.max(v)));
        let ya = if lo <= hi {
            // A little room so lines at the extremes are not hidden by the frame, but no
            // negative axis for values that cannot be negative (steps).
            let pad = (hi - lo) * 0.02;
            let lo_p = if lo >= 0.0 { (lo - pad).max(0.0) } else { lo - pad };
            let hi_p = if hi <= 0.0 { (hi + pad).min(0.0) } else { hi + pad };
            Axis::nice(lo_p, hi_p, 5.0)
        } else {
            Axis::nice(0.0, 1.0, 5.0)
        };

        // Background, grid, ticks and labels.
        if let Some(r) = Rect::from_ltrb(area.x0, area.y0, area.x1, area.y1) {
            self.pixmap.fill_rect(r, &paint([252, 252, 252], 255), Transform::identity(), None);
        }
        let grid = paint([222, 222, 222], 255);
        let frame = paint([60, 60, 60], 255);
        for t in ya.ticks() {
            let (_, y) = area.px(xa, &ya, xa.lo, t);
            self.segment((area.x0, y), (area.x1, y), 1.0, &grid, None, None);
            self.segment((area.x0 - 5.0, y), (area.x0, y), 1.0, &frame, None, None);
            let s = ya.label(t);
            self.text(area.x0 - 9.0 - text_width(&s), y - 7.0, &s, TEXT_RGB);
        }
        for t in xa.ticks() {
            let (x, _) = area.px(xa, &ya, t, ya.lo);
            self.segment((x, area.y0), (x, area.y1), 1.0, &grid, None, None);
            self.segment((x, area.y1), (x, area.y1 + 5.0), 1.0, &frame, None, None);
            let s = xa.label(t);
            let lx = (x - text_width(&s) / 2.0).min(WIDTH_PX as f32 - 4.0 - text_width(&s));
            self.text(lx, area.y1 + 9.0, &s, TEXT_RGB);
        }
        if let Some(r) = Rect::from_ltrb(area.x0, area.y0, area.x1, area.y1) {
            self.pixmap.stroke_path(&PathBuilder::from_rect(r), &frame, &Stroke { width: 1.0, ..Stroke::default() }, Transform::identity(), None);
        }

        // Title of the panel, with the latest average.
        let last = avg.iter().rev().find(|v| v.is_finite());
        let title = match last {
            Some(v) => format!("{label}  (last avg {})", fmt_value(*v)),
            None => label.to_string(),
        };
        self.text(area.x0, area.y0 - 22.0, &title, TEXT_RGB);

        // Data, clipped to the plot area.
        let mask = Rect::from_ltrb(area.x0, area.y0, area.x1, area.y1).and_then(|r| {
            let mut m = Mask::new(WIDTH_PX, HEIGHT_PX)?;
            m.fill_path(&PathBuilder::from_rect(r), FillRule::Winding, false, Transform::identity());
            Some(m)
        });
        let mask = mask.as_ref();
        let raw_line = paint(RAW_RGB, 110);
        let n = xs.len();
        if n > MAX_DRAWN_POINTS {
            let cols = columns(area, xa, &ya, xs, ys, avg);
            // Raw values: a min–max envelope, one vertical run per pixel column.
            let env = cols.iter().flat_map(|c| [c.map(|c| (c.x, c.min)), c.map(|c| (c.x, c.max))]);
            self.polyline(env, 1.0, &raw_line, mask);
            if let Some(g) = goal {
                self.goal_line(area, xa, &ya, g, mask);
            }
            let means = cols.iter().map(|c| c.and_then(|c| (c.avg_n > 0).then(|| (c.x, area.px(xa, &ya, xa.lo, c.avg_sum / c.avg_n as f64).1))));
            self.polyline(means, 2.5, &paint(AVERAGE_RGB, 255), mask);
        } else {
            let pts: Vec<Option<(f32, f32)>> = xs.iter().zip(ys).map(|(&x, &y)| y.is_finite().then(|| area.px(xa, &ya, x, y))).collect();
            self.polyline(pts.iter().copied(), 1.0, &raw_line, mask);
            if n <= MAX_DOTS {
                let dot = paint(RAW_RGB, 170);
                for (x, y) in pts.iter().flatten() {
                    if let Some(path) = PathBuilder::from_circle(*x, *y, 2.0) {
                        self.pixmap.fill_path(&path, &dot, FillRule::Winding, Transform::identity(), mask);
                    }
                }
            }
            if let Some(g) = goal {
                self.goal_line(area, xa, &ya, g, mask);
            }
            let avg_pts = xs.iter().zip(avg).map(|(&x, &y)| y.is_finite().then(|| area.px(xa, &ya, x, y)));
            self.polyline(avg_pts, 2.5, &paint(AVERAGE_RGB, 255), mask);
        }
        if let Some(g) = goal {
            self.goal_label(area, xa, &ya, g);
        }
        if n == 0 {
            let s = "no episodes yet";
            self.boxed_text((area.x0 + area.x1) / 2.0 - text_width(s) / 2.0, (area.y0 + area.y1) / 2.0 - 7.0, s, [120, 120, 120]);
        }
        self.legend(area, window, goal.is_some());
    }

    fn goal_line(&mut self, area: &PlotArea, xa: &Axis, ya: &Axis, g: f64, mask: Option<&Mask>) {
        let (_, y) = area.px(xa, ya, xa.lo, g);
        self.segment((area.x0, y), (area.x1, y), 1.5, &paint(GOAL_RGB, 255), StrokeDash::new(vec![8.0, 5.0], 0.0), mask);
    }

    /// "goal >= g" at the right end, above the line unless that would leave the panel.
    fn goal_label(&mut self, area: &PlotArea, xa: &Axis, ya: &Axis, g: f64) {
        let (_, y) = area.px(xa, ya, xa.lo, g);
        let s = format!("goal >= {}", fmt_value(g));
        let ty = if y - 20.0 >= area.y0 + 2.0 { y - 20.0 } else { y + 7.0 };
        self.boxed_text(area.x1 - 6.0 - text_width(&s), ty, &s, GOAL_RGB);
    }

    /// Text on a translucent white box, readable over data.
    fn boxed_text(&mut self, x: f32, y: f32, s: &str, rgb: [u8; 3]) {
        if let Some(r) = Rect::from_xywh(x - 3.0, y - 3.0, text_width(s) + 6.0, 14.0 + 6.0) {
            self.pixmap.fill_rect(r, &paint([255, 255, 255], 210), Transform::identity(), None);
        }
        self.text(x, y, s, rgb);
    }

    /// Legend right-aligned on the panel's title line.
    fn legend(&mut self, area: &PlotArea, window: usize, goal: bool) {
        let avg_label = format!("avg of {window}");
        let mut items: Vec<(Paint<'static>, f32, Option<StrokeDash>, String)> = vec![(paint(RAW_RGB, 200), 1.5, None, "episode".into()), (paint(AVERAGE_RGB, 255), 2.5, None, avg_label)];
        if goal {
            items.push((paint(GOAL_RGB, 255), 1.5, StrokeDash::new(vec![6.0, 4.0], 0.0), "goal".into()));
        }
        const SWATCH: f32 = 22.0;
        let total: f32 = items.iter().map(|(.., s)| SWATCH + 6.0 + text_width(s) + 18.0).sum::<f32>() - 18.0;
        let mut x = area.x1 - total;
        let y = area.y0 - 22.0;
        for (p, w, dash, s) in items {
            self.segment((x, y + 7.0), (x + SWATCH, y + 7.0), w, &p, dash, None);
            x += SWATCH + 6.0;
            self.text(x, y, &s, TEXT_RGB);
            x += text_width(&s) + 18.0;
        }
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
        let (_, py) = if y.is_finite() { area.px(xa, ya, x, y) } else { (0.0, f32::NAN) };
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nice_axes_use_1_2_5_steps() {
        let a = Axis::nice(0.0, 1000.0, 6.0);
        assert_eq!((a.lo, a.hi, a.step), (0.0, 1000.0, 200.0));
        let a = Axis::nice(-37.0, 312.0, 5.0);
        assert_eq!((a.lo, a.hi, a.step), (-100.0, 400.0, 100.0));
        let a = Axis::nice(0.0, 1020.0, 5.0);
        assert_eq!((a.lo, a.hi, a.step), (0.0, 1200.0, 200.0));
        let a = Axis::nice(0.0, 0.9, 5.0);
        assert_eq!(a.step, 0.2);
        assert_eq!(a.label(0.4 + 0.2), "0.6");
        let a = Axis::nice(5.0, 5.0, 5.0);
        assert!(a.lo < 5.0 && a.hi > 5.0);
        let a = Axis::nice(-f64::MAX, f64::MAX, 5.0);
        assert!(a.lo.is_finite() && a.hi.is_finite() && a.ticks().len() >= 2);
    }

    #[test]
    fn values_print_short() {
        assert_eq!(fmt_value(320.0), "320");
        assert_eq!(fmt_value(312.456), "312.5");
        assert_eq!(fmt_value(-0.5), "-0.5");
    }
}
