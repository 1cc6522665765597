//! Reading the grey images of ROS maps: PGM (P2 ASCII, P5 binary, 8 or 16 bit) and PNG.

use std::path::Path;

/// An 8-bit grey image, row 0 at the top.
pub struct GrayImage {
    pub width: usize,
    pub height: usize,
    pub pixels: Vec<u8>,
}

/// Largest image we accept (side, pixels): a 100 m map at 1 cm is 10,000 px.
const MAX_SIDE: usize = 20_000;

/// Reads a PGM or PNG file as 8-bit grey. Errors are human-readable problems (the caller adds
/// the path).
pub fn read_gray(path: &Path) -> Result<GrayImage, String> {
    let bytes = std::fs::read(path).map_err(|e| format!("cannot read image: {e}"))?;
    if bytes.starts_with(b"\x89PNG") {
        read_png(&bytes)
    } else if bytes.starts_with(b"P5") || bytes.starts_with(b"P2") {
        read_pgm(&bytes)
    } else {
        Err("not a PGM (P2/P5) or PNG image".into())
    }
}

fn read_png(bytes: &[u8]) -> Result<GrayImage, String> {
    let mut dec = png::Decoder::new(bytes);
    dec.set_transformations(png::Transformations::EXPAND | png::Transformations::STRIP_16);
    let mut reader = dec.read_info().map_err(|e| format!("corrupt PNG: {e}"))?;
    let mut buf = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut buf).map_err(|e| format!("corrupt PNG: {e}"))?;
    let (w, h) = (info.width as usize, info.height as usize);
    check_size(w, h)?;
    let ch = match info.color_type {
        png::ColorType::Grayscale => 1,
        png::ColorType::GrayscaleAlpha => 2,
        png::ColorType::Rgb => 3,
        png::ColorType::Rgba => 4,
        png::ColorType::Indexed => return Err("indexed PNG was not expanded".into()),
    };
    let pixels = buf[..w * h * ch]
        .chunks_exact(ch)
        .map(|p| match ch {
            1 | 2 => p[0],
            _ => ((p[0] as u32 + p[1] as u32 + p[2] as u32) / 3) as u8,
        })
        .collect();
    Ok(GrayImage { width: w, height: h, pixels })
}

fn check_size(w: usize, h: usize) -> Result<(), String> {
    if w == 0 || h == 0 || w > MAX_SIDE || h > MAX_SIDE {
        return Err(format!("image size {w}x{h} outside 1..={MAX_SIDE} per side"));
    }
    Ok(())
}

fn read_pgm(bytes: &[u8]) -> Result<GrayImage, String> {
    // Header: magic, width, height, maxval, separated by whitespace, '#' comments allowed;
    // one whitespace byte, then the raster.
    let mut pos = 2;
    let mut fields = [0usize; 3];
    for f in &mut fields {
        loop {
            while pos < bytes.len() && bytes[pos].is_ascii_whitespace() {
                pos += 1;
            }
            if pos < bytes.len() && bytes[pos] == b'#' {
                while pos < bytes.len() && bytes[pos] != b'\n' {
                    pos += 1;
                }
            } else {
                break;
            }
        }
        let start = pos;
        while pos < bytes.len() && bytes[pos].is_ascii_digit() {
            pos += 1;
        }
        if start == pos {
            return Err("corrupt PGM header (expected width, height and maxval)".into());
        }
        *f = std::str::from_utf8(&bytes[start..pos]).ok().and_then(|s| s.parse().ok()).ok_or("corrupt PGM header: number too large")?;
    }
    let [w, h, maxval] = fields;
    check_size(w, h)?;
    if maxval == 0 || maxval > 65535 {
        return Err(format!("PGM maxval {maxval} outside 1..=65535"));
    }
    let scale = |v: usize| ((v.min(maxval) * 255 + maxval / 2) / maxval) as u8;
    let n = w * h;
    let pixels: Vec<u8> = if bytes.starts_with(b"P5") {
        pos += 1; // the single whitespace after maxval
        let bpp = if maxval > 255 { 2 } else { 1 };
        let raster = bytes.get(pos..).unwrap_or(&[]);
        if raster.len() < n * bpp {
            return Err(format!("PGM raster truncated: {w}x{h} needs {} bytes, file has {}", n * bpp, raster.len()));
        }
        if bpp == 1 { raster[..n].iter().map(|&v| scale(v as usize)).collect() } else { raster[..2 * n].chunks_exact(2).map(|p| scale(u16::from_be_bytes([p[0], p[1]]) as usize)).collect() }
    } else {
        let text = std::str::from_utf8(&bytes[pos..]).map_err(|_| "P2 raster is not ASCII")?;
        let vals: Vec<u8> = text.split_ascii_whitespace().take(n).map(|t| t.parse::<usize>().map(scale).map_err(|_| format!("P2 raster value `{t}` is not a number"))).collect::<Result<_, _>>()?;
        if vals.len() < n {
            return Err(format!("PGM raster truncated: {w}x{h} needs {n} values, file has {}", vals.len()));
        }
        vals
    };
    Ok(GrayImage { width: w, height: h, pixels })
}
