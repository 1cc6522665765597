//! The one font of the pictures: DejaVu Sans, embedded (fonts/DejaVuSans.ttf; its license is
//! fonts/LICENSE-DejaVu.txt, which permits redistribution), registered with plotters' ab_glyph
//! renderer under [`FONT_FAMILY`]. Nothing is read from the host's font configuration.
//!
//! Placement: plotters' ab_glyph renderer puts the baseline `size / 2` below the top of the
//! text box it is given, so the helpers here place text by its baseline.

use std::sync::OnceLock;

use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};
use plotters::style::{FontStyle, register_font};

use crate::error::{PlotError, Result};

/// The family name the embedded font is registered under.
pub const FONT_FAMILY: &str = "DejaVu Sans (mapless-plots)";

static DEJAVU_SANS: &[u8] = include_bytes!("../fonts/DejaVuSans.ttf");

/// Registers the embedded font with plotters (once per process).
pub(crate) fn register() -> Result<()> {
    static REGISTERED: OnceLock<bool> = OnceLock::new();
    if *REGISTERED.get_or_init(|| register_font(FONT_FAMILY, FontStyle::Normal, DEJAVU_SANS).is_ok()) {
        Ok(())
    } else {
        Err(PlotError::Draw { what: "text", problem: "the embedded DejaVu Sans is not a readable font".into() })
    }
}

/// The embedded font at `size` pixels (plotters' size: ascent plus descent, about 1.16 em).
pub(crate) fn font(size: f64) -> FontDesc<'static> {
    FontDesc::new(FontFamily::Name(FONT_FAMILY), size, FontStyle::Normal)
}

pub(crate) fn rgb(c: [u8; 3]) -> RGBColor {
    RGBColor(c[0], c[1], c[2])
}

/// Text style of the embedded font at `size` in colour `c`.
pub(crate) fn style(size: f64, c: [u8; 3]) -> TextStyle<'static> {
    font(size).color(&rgb(c))
}

/// Width of `s` in pixels at `size`.
pub(crate) fn width<DB: DrawingBackend>(area: &DrawingArea<DB, Shift>, s: &str, size: f64) -> u32 {
    area.estimate_text_size(s, &font(size).into()).map_or(0, |(w, _)| w)
}

/// Height of capital letters and digits above the baseline, in pixels at `size`.
pub(crate) fn cap_height(size: f64) -> f64 {
    // DejaVu Sans: caps 0.729 em, ascent + descent 1.164 em.
    size * 0.729 / 1.164
}

/// Draws `s` with its baseline at `baseline`, starting at (`Left`), centred on (`Center`) or
/// ending at (`Right`) `x`.
pub(crate) fn draw<DB: DrawingBackend>(area: &DrawingArea<DB, Shift>, s: &str, size: f64, c: [u8; 3], x: i32, baseline: i32, h: HPos) -> Result<()> {
    let st = style(size, c).pos(Pos::new(h, VPos::Top));
    area.draw_text(s, &st, (x, baseline - (size / 2.0).round() as i32)).map_err(|e| PlotError::Draw { what: "text", problem: e.to_string() })
}

/// The largest size up to `size` (down to `min`) at which `s` fits in `max_width` pixels.
pub(crate) fn fit<DB: DrawingBackend>(area: &DrawingArea<DB, Shift>, s: &str, size: f64, min: f64, max_width: u32) -> f64 {
    let w = width(area, s, size);
    if w <= max_width || w == 0 { size } else { (size * f64::from(max_width) / f64::from(w)).floor().max(min) }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_embedded_font_registers_and_measures() {
        register().unwrap();
        register().unwrap(); // twice is fine
        let f = font(20.0);
        let (w, h) = f.box_size("Episode return").unwrap();
        assert!(w > 100 && w < 200 && h > 10, "{w}x{h}");
    }
}
