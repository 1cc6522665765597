//! `mapless-plots` — the pictures of mapless: a map, an episode on it (trajectory, visited EQS
//! cells, rings; the paper's Figs. 5, 10, 12) and the training curves (Figs. 6–9), as PNG.
//!
//! ```text
//!   mapless-sim (Map, ExplorationTracker, stats::moving_average)
//!        │
//!        ▼
//!   canvas: Canvas (map + episode pictures)      curves: training_curves_png
//!   sheet: contact_sheet_png (many canvases on a grid)
//!        │  plotters: layout, axes in metres / episodes, tick labels, titles, legends
//!        │  tiny-skia: anti-aliased map shapes, paths, data lines (Picture::paint)
//!        ▼
//!   picture: one RGB buffer, PNG written atomically (temp file + rename, by
//!            mapless-proto's atomic_file, the workspace's one atomic write)
//! ```
//!
//! Text is DejaVu Sans, embedded in the crate (`fonts/`, Bitstream Vera license) and handed to
//! plotters' ab_glyph renderer, so pictures never depend on the host's fonts.

mod axis;
pub mod canvas;
pub mod curves;
mod error;
mod font;
mod picture;
pub mod series;
mod sheet;

pub use canvas::{Canvas, default_px_per_m};
pub use curves::{CurvePoint, CurveStyle, training_curves_png};
pub use error::{PlotError, Result};
pub use font::FONT_FAMILY;
pub use series::{Series, SeriesPanel, time_series_png};
pub use sheet::contact_sheet_png;
