//! A contact sheet: many pictures (maps, episodes) in one, on a grid, under a title — the
//! family of generated worlds (`mapless worlds show`), the trajectories of an evaluation.

use std::path::Path;

use plotters::style::text_anchor::HPos;

use crate::canvas::Canvas;
use crate::error::{PlotError, Result};
use crate::font;
use crate::picture::Picture;

const GAP_PX: u32 = 12;
const TITLE_PX: u32 = 44;
const TITLE_SIZE: f64 = 22.0;

/// Lays `tiles` out `columns` to a row (each cell as large as the largest tile, the tile
/// scaled down by `scale` ∈ (0, 1] with box filtering), titles the sheet and writes it as PNG.
pub fn contact_sheet_png(tiles: &[Canvas], columns: usize, scale: f32, title: &str, path: &Path) -> Result<()> {
    let what = "contact sheet";
    if tiles.is_empty() || columns == 0 || !(scale > 0.0 && scale <= 1.0) {
        return Err(PlotError::Invalid { what, problem: format!("{} tiles, {columns} columns, scale {scale}", tiles.len()) });
    }
    let shrink = |v: u32| ((v as f32 * scale).round() as u32).max(1);
    let cell_w = tiles.iter().map(|t| shrink(t.width())).max().unwrap_or(1);
    let cell_h = tiles.iter().map(|t| shrink(t.height())).max().unwrap_or(1);
    let cols = columns.min(tiles.len()) as u32;
    let rows = tiles.len().div_ceil(columns) as u32;
    let (w, h) = (GAP_PX + cols * (cell_w + GAP_PX), TITLE_PX + rows * (cell_h + GAP_PX));
    let mut sheet = Picture::new(w, h, what)?;
    sheet.draw(|root| font::draw(root, title, TITLE_SIZE, [20, 20, 20], GAP_PX as i32, 30, HPos::Left))?;
    for (k, tile) in tiles.iter().enumerate() {
        let (c, r) = ((k % columns) as u32, (k / columns) as u32);
        let (x0, y0) = (GAP_PX + c * (cell_w + GAP_PX), TITLE_PX + r * (cell_h + GAP_PX));
        let (tw, th) = (shrink(tile.width()), shrink(tile.height()));
        for y in 0..th {
            for x in 0..tw {
                sheet.set_rgb(x0 + x, y0 + y, box_sample(tile, x, y, scale));
            }
        }
    }
    sheet.save_png(path)
}

/// The mean colour of the tile's pixels under sheet pixel (x, y).
fn box_sample(tile: &Canvas, x: u32, y: u32, scale: f32) -> [u8; 3] {
    let (sx0, sy0) = ((x as f32 / scale) as u32, (y as f32 / scale) as u32);
    let (sx1, sy1) = ((((x + 1) as f32 / scale) as u32).max(sx0 + 1), (((y + 1) as f32 / scale) as u32).max(sy0 + 1));
    let (mut sum, mut n) = ([0u32; 3], 0u32);
    for sy in sy0..sy1 {
        for sx in sx0..sx1 {
            if let Some(p) = tile.pixel(sx, sy) {
                for i in 0..3 {
                    sum[i] += u32::from(p[i]);
                }
                n += 1;
            }
        }
    }
    if n == 0 { [255; 3] } else { sum.map(|s| (s / n) as u8) }
}
