//! Reading the grey images of ROS maps: PGM (P2 ASCII, P5 binary, 8 or 16 bit, any maxval) and
//! PNG, decoded by the `image` crate and reduced to 8-bit grey as ROS `map_server` does (colour
//! channels averaged, alpha ignored).

use std::io::Cursor;

use image::{DynamicImage, ImageFormat, ImageReader, Limits};

/// An 8-bit grey image, row 0 at the top.
#[derive(Debug)]
pub struct GrayImage {
    pub width: usize,
    pub height: usize,
    pub pixels: Vec<u8>,
}

/// Largest image we accept (side, pixels): a 100 m map at 1 cm is 10,000 px.
const MAX_SIDE: usize = 20_000;

/// Decodes the bytes of a PGM or PNG file as 8-bit grey. Errors are human-readable problems
/// (the caller adds the image's path).
pub fn decode_gray(bytes: &[u8]) -> Result<GrayImage, String> {
    let (format, name) = if bytes.starts_with(b"\x89PNG") {
        (ImageFormat::Png, "PNG")
    } else if bytes.starts_with(b"P5") || bytes.starts_with(b"P2") {
        (ImageFormat::Pnm, "PGM")
    } else {
        return Err("not a PGM (P2/P5) or PNG image".into());
    };
    let reader = |limits: Limits| {
        let mut r = ImageReader::with_format(Cursor::new(bytes), format);
        r.limits(limits);
        r
    };
    // The header first (it allocates nothing), so that a bad header, an oversized image and a
    // short raster each read as what they are.
    let (w, h) = reader(Limits::no_limits()).into_dimensions().map_err(|e| format!("corrupt {name} header: {e}"))?;
    let (w, h) = (w as usize, h as usize);
    if w == 0 || h == 0 || w > MAX_SIDE || h > MAX_SIDE {
        return Err(format!("image size {w}x{h} outside 1..={MAX_SIDE} per side"));
    }
    // The decoder's own limits (512 MiB of pixels by default) bound what a file can make it
    // allocate; a 20,000² grey map is 400 MB.
    let mut limits = Limits::default();
    limits.max_image_width = Some(MAX_SIDE as u32);
    limits.max_image_height = Some(MAX_SIDE as u32);
    let image = reader(limits).decode().map_err(|e| match &e {
        image::ImageError::IoError(io) if io.kind() == std::io::ErrorKind::UnexpectedEof => format!("{name} raster truncated: {w}x{h} pixels expected ({e})"),
        _ if name == "PGM" && e.to_string().to_ascii_lowercase().contains("end") => format!("{name} raster truncated: {w}x{h} pixels expected ({e})"),
        _ => format!("corrupt {name}: {e}"),
    })?;
    Ok(GrayImage { width: w, height: h, pixels: gray8(image) })
}

/// 8-bit grey as ROS `map_server` reads an image: the mean of the colour channels, alpha
/// ignored; 16-bit samples rounded to 8 bits.
fn gray8(image: DynamicImage) -> Vec<u8> {
    let to8 = |v: u16| ((u32::from(v) * 255 + 32_767) / 65_535) as u8;
    let mean = |c: &[u8]| ((u32::from(c[0]) + u32::from(c[1]) + u32::from(c[2])) / 3) as u8;
    match image {
        DynamicImage::ImageLuma8(b) => b.into_raw(),
        DynamicImage::ImageLumaA8(b) => b.pixels().map(|p| p.0[0]).collect(),
        DynamicImage::ImageLuma16(b) => b.pixels().map(|p| to8(p.0[0])).collect(),
        DynamicImage::ImageLumaA16(b) => b.pixels().map(|p| to8(p.0[0])).collect(),
        DynamicImage::ImageRgba8(b) => b.pixels().map(|p| mean(&p.0)).collect(),
        other => other.to_rgb8().pixels().map(|p| mean(&p.0)).collect(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `name` only labels the case: the format is told from the bytes.
    fn read(_name: &str, bytes: &[u8]) -> Result<GrayImage, String> {
        decode_gray(bytes)
    }

    #[test]
    fn pgm_of_any_maxval_and_depth_reads_as_8_bit_grey() {
        let g = read("a.pgm", b"P2\n# comment\n3 1\n15\n0 15 7\n").unwrap();
        assert_eq!((g.width, g.height, g.pixels), (3, 1, vec![0, 255, 119]));
        let mut p5 = b"P5\n2 1\n65535\n".to_vec();
        p5.extend_from_slice(&[0xff, 0xff, 0x80, 0x00]);
        assert_eq!(read("b.pgm", &p5).unwrap().pixels, vec![255, 128]);
    }

    #[test]
    fn colour_png_is_the_channel_mean() {
        let mut bytes = Vec::new();
        let rgb = image::RgbImage::from_raw(2, 1, vec![255, 0, 0, 30, 60, 90]).unwrap();
        DynamicImage::ImageRgb8(rgb).write_to(&mut Cursor::new(&mut bytes), ImageFormat::Png).unwrap();
        assert_eq!(read("c.png", &bytes).unwrap().pixels, vec![85, 60]);
    }

    #[test]
    fn oversized_and_other_images_are_refused_by_name() {
        assert!(read("d.pgm", b"P5\n30000 1\n255\n").unwrap_err().contains("image size 30000x1 outside"));
        assert!(read("e.ppm", b"P6\n1 1\n255\nabc").unwrap_err().contains("not a PGM"));
    }
}
