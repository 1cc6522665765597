//! One picture, two painters: plotters draws the frame (axes, tick labels, text) into an RGB
//! buffer, tiny-skia paints what needs anti-aliasing and sub-pixel positions (map shapes,
//! paths, data lines) onto the same pixels. PNG out via `image`, written atomically.

use std::path::Path;

use plotters::coord::Shift;
use plotters::prelude::*;
use tiny_skia::{Pixmap, PremultipliedColorU8};

use crate::error::{PlotError, Result};

pub(crate) type Area<'a> = DrawingArea<BitMapBackend<'a>, Shift>;

/// An opaque RGB picture (row-major, 3 bytes a pixel), white to start with.
pub(crate) struct Picture {
    width: u32,
    height: u32,
    rgb: Vec<u8>,
    what: &'static str,
}

impl Picture {
    /// A white `width` × `height` picture; `what` names it in errors ("training curves").
    pub(crate) fn new(width: u32, height: u32, what: &'static str) -> Result<Picture> {
        crate::font::register()?;
        let too_big = |_| PlotError::Invalid { what, problem: format!("a picture of {width}x{height} pixels is too large") };
        let n = usize::try_from(u64::from(width) * u64::from(height) * 3).map_err(too_big)?;
        if width == 0 || height == 0 || n > 1 << 31 {
            return Err(PlotError::Invalid { what, problem: format!("a picture of {width}x{height} pixels cannot be drawn") });
        }
        Ok(Picture { width, height, rgb: vec![255; n], what })
    }

    pub(crate) fn width(&self) -> u32 {
        self.width
    }

    pub(crate) fn height(&self) -> u32 {
        self.height
    }

    /// Draws with plotters on the whole picture (pixel coordinates, origin top left).
    pub(crate) fn draw(&mut self, f: impl FnOnce(&Area) -> Result<()>) -> Result<()> {
        let what = self.what;
        let area = BitMapBackend::with_buffer(&mut self.rgb, (self.width, self.height)).into_drawing_area();
        f(&area)?;
        area.present().map_err(|e| PlotError::Draw { what, problem: e.to_string() })
    }

    /// Paints with tiny-skia on the picture's pixels.
    pub(crate) fn paint(&mut self, f: impl FnOnce(&mut Pixmap)) -> Result<()> {
        let mut pixmap = Pixmap::new(self.width, self.height).ok_or_else(|| PlotError::Invalid { what: self.what, problem: "no pixels".into() })?;
        for (p, c) in pixmap.pixels_mut().iter_mut().zip(self.rgb.chunks_exact(3)) {
            *p = PremultipliedColorU8::from_rgba(c[0], c[1], c[2], 255).expect("opaque");
        }
        f(&mut pixmap);
        // The picture stays opaque: whatever was painted translucently is over what was there.
        for (p, c) in pixmap.pixels().iter().zip(self.rgb.chunks_exact_mut(3)) {
            let d = p.demultiply();
            c.copy_from_slice(&[d.red(), d.green(), d.blue()]);
        }
        Ok(())
    }

    /// Adds `rows` white rows at the bottom.
    pub(crate) fn grow(&mut self, rows: u32) {
        self.height += rows;
        self.rgb.resize(self.width as usize * self.height as usize * 3, 255);
    }

    /// Sets pixel (x, y) (ignored outside the picture).
    pub(crate) fn set_rgb(&mut self, x: u32, y: u32, c: [u8; 3]) {
        if x < self.width && y < self.height {
            let i = (y as usize * self.width as usize + x as usize) * 3;
            self.rgb[i..i + 3].copy_from_slice(&c);
        }
    }

    /// RGB of pixel (x, y).
    pub(crate) fn rgb(&self, x: u32, y: u32) -> Option<[u8; 3]> {
        (x < self.width && y < self.height).then(|| {
            let i = (y as usize * self.width as usize + x as usize) * 3;
            [self.rgb[i], self.rgb[i + 1], self.rgb[i + 2]]
        })
    }

    /// Encodes PNG (RGB, 8 bits) and writes it atomically (`mapless_proto::atomic_file`: temp
    /// file, fsync, rename), creating the parent directory.
    pub(crate) fn save_png(&self, path: &Path) -> Result<()> {
        let out_err = |problem: String| PlotError::Output { path: path.to_path_buf(), problem };
        let mut bytes = Vec::new();
        image::ImageEncoder::write_image(image::codecs::png::PngEncoder::new(&mut bytes), &self.rgb, self.width, self.height, image::ExtendedColorType::Rgb8).map_err(|e| out_err(e.to_string()))?;
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).map_err(|e| out_err(e.to_string()))?;
        }
        mapless_proto::atomic_file::write_file_atomically(path, &bytes).map_err(|e| out_err(format!("{}: {}", e.step, e.error)))
    }
}

/// A plotters error as ours.
pub(crate) fn draw_err<E: std::fmt::Display>(what: &'static str) -> impl Fn(E) -> PlotError {
    move |e| PlotError::Draw { what, problem: e.to_string() }
}
