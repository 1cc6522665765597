//! Time series as PNG: stacked panels sharing one time axis, each with one or more named lines
//! (`mapless bench soak`: rows/s, latency, memory over a run). plotters draws everything here
//! (axes on a 1-2-5 grid, lines, legends) in the embedded DejaVu Sans. Non-finite values are
//! left out of a line.

use std::path::Path;

use plotters::prelude::*;

use crate::axis::{Axis, fmt_value};
use crate::error::{PlotError, Result};
use crate::font;
use crate::picture::{Picture, draw_err};

/// One named line of a panel: (x, y) points in x order.
#[derive(Debug, Clone, PartialEq)]
pub struct Series {
    pub label: String,
    pub rgb: [u8; 3],
    pub points: Vec<(f64, f64)>,
}

/// One panel: its caption (above it), the y axis title, its lines.
#[derive(Debug, Clone, PartialEq)]
pub struct SeriesPanel {
    pub caption: String,
    pub y_title: String,
    pub lines: Vec<Series>,
}

/// Picture width in pixels; the height is 110 px plus 230 px a panel.
pub const SERIES_WIDTH_PX: u32 = 1000;
const PANEL_PX: u32 = 230;
const TITLE_SIZE: f64 = 22.0;
const CAPTION_SIZE: f64 = 16.0;
const LABEL_SIZE: f64 = 13.0;
const TEXT_RGB: [u8; 3] = [20, 20, 20];
const MUTED_RGB: [u8; 3] = [90, 90, 90];

/// Draws `panels` stacked, sharing the x axis titled `x_title`, under `title`, with `footer`
/// at the bottom; written atomically. At least one panel.
pub fn time_series_png(panels: &[SeriesPanel], title: &str, x_title: &str, footer: &str, path: &Path) -> Result<()> {
    const WHAT: &str = "time series";
    if panels.is_empty() {
        return Err(PlotError::Invalid { what: WHAT, problem: "no panels".into() });
    }
    let height = 110 + PANEL_PX * panels.len() as u32;
    let mut pic = Picture::new(SERIES_WIDTH_PX, height, WHAT)?;
    let finite = |p: &&(f64, f64)| p.0.is_finite() && p.1.is_finite();
    let xs = panels.iter().flat_map(|p| &p.lines).flat_map(|l| l.points.iter().filter(finite).map(|p| p.0));
    let (x_lo, x_hi) = xs.fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), x| (lo.min(x), hi.max(x)));
    let x_axis = if x_lo <= x_hi { Axis::nice(x_lo.min(0.0), x_hi.max(x_lo + 1.0), 8.0) } else { Axis::nice(0.0, 1.0, 8.0) };
    let err = draw_err(WHAT);
    pic.draw(|root| {
        font::draw(root, title, TITLE_SIZE, TEXT_RGB, 24, 34, plotters::style::text_anchor::HPos::Left)?;
        let footer_size = font::fit(root, footer, LABEL_SIZE, 9.0, SERIES_WIDTH_PX - 48);
        font::draw(root, footer, footer_size, MUTED_RGB, 24, height as i32 - 14, plotters::style::text_anchor::HPos::Left)?;
        let body = root.margin(50, 30, 10, 20);
        for (i, (panel, area)) in panels.iter().zip(body.split_evenly((panels.len(), 1))).enumerate() {
            let ys = panel.lines.iter().flat_map(|l| l.points.iter().filter(finite).map(|p| p.1));
            let (lo, hi) = ys.fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), y| (lo.min(y), hi.max(y)));
            let y_axis = if lo <= hi { Axis::nice(lo.min(0.0), if hi > lo.min(0.0) { hi * 1.05 } else { 1.0 }, 5.0) } else { Axis::nice(0.0, 1.0, 5.0) };
            let last = i + 1 == panels.len();
            let mut chart = ChartBuilder::on(&area)
                .caption(&panel.caption, font::style(CAPTION_SIZE, TEXT_RGB))
                .x_label_area_size(if last { 40 } else { 22 })
                .y_label_area_size(80)
                .build_cartesian_2d(x_axis.lo..x_axis.hi, y_axis.lo..y_axis.hi)
                .map_err(&err)?;
            let mut mesh = chart.configure_mesh();
            mesh.light_line_style(RGBColor(235, 235, 235))
                .label_style(font::style(LABEL_SIZE, TEXT_RGB))
                .y_desc(panel.y_title.as_str())
                .x_labels(10)
                .y_labels(6)
                .x_label_formatter(&|v| fmt_value(*v))
                .y_label_formatter(&|v| fmt_value(*v));
            if last {
                mesh.x_desc(x_title);
            }
            mesh.draw().map_err(&err)?;
            for line in &panel.lines {
                let c = font::rgb(line.rgb);
                chart
                    .draw_series(LineSeries::new(line.points.iter().filter(finite).copied(), c.stroke_width(2)))
                    .map_err(&err)?
                    .label(line.label.as_str())
                    .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], c.stroke_width(2)));
            }
            if panel.lines.len() > 1 {
                chart
                    .configure_series_labels()
                    .position(SeriesLabelPosition::UpperLeft)
                    .background_style(WHITE.mix(0.85))
                    .border_style(RGBColor(180, 180, 180))
                    .label_font(font::style(LABEL_SIZE, TEXT_RGB))
                    .draw()
                    .map_err(&err)?;
            }
        }
        Ok(())
    })?;
    pic.save_png(path)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn draws_panels_with_lines_and_refuses_none() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("s.png");
        let line = |label: &str, rgb, f: fn(f64) -> f64| Series { label: label.into(), rgb, points: (0..50).map(|i| (i as f64 * 5.0, f(i as f64))).collect() };
        let panels = vec![
            SeriesPanel { caption: "rows/s".into(), y_title: "rows/s".into(), lines: vec![line("acked", [10, 50, 150], |i| 25_000.0 + i)] },
            SeriesPanel { caption: "memory".into(), y_title: "MiB".into(), lines: vec![line("replay", [10, 50, 150], |i| 200.0 + i), line("learner", [200, 40, 40], |_| f64::NAN)] },
        ];
        time_series_png(&panels, "soak", "seconds", "footer", &path).unwrap();
        let img = image::open(&path).unwrap().to_rgb8();
        assert_eq!((img.width(), img.height()), (SERIES_WIDTH_PX, 110 + 2 * PANEL_PX));
        // The blue lines were drawn: some pixel is the line colour.
        assert!(img.pixels().any(|p| p.0 == [10, 50, 150]));
        assert!(time_series_png(&[], "", "", "", &path).is_err());
    }
}
