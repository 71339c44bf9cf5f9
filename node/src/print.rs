//! Printable markers at true physical size (SVG in millimetres, PNG with its
//! resolution recorded), with the one-module white quiet zone every code set
//! assumes (`proto::marker`), cut marks at the quiet zone's corners, and the
//! code set, ID and size printed in the margin.

use opencv::core::{Mat, Point, Scalar, Vector, CV_8UC1};
use opencv::prelude::*;
use opencv::{imgcodecs, imgproc};
use shoal_proto::marker::{CodeSet, MarkerError, MarkerId};
use std::fmt::Write as _;

/// Errors of printing.
#[derive(Debug, thiserror::Error)]
pub enum PrintError {
    #[error(transparent)]
    Marker(#[from] MarkerError),
    #[error("marker side must be between 5 and 2000 mm, got {0}")]
    BadSize(f64),
    #[error("resolution must be between 72 and 2400 dpi, got {0}")]
    BadDpi(f64),
    #[error("a {page_mm:.0} mm page at {dpi} dpi is {side_px}x{side_px} pixels, more than the {} Mpx limit of a PNG marker; use --dpi {max_dpi:.0} or less, or write an SVG (any size, exact)", MAX_PNG_PIXELS as f64 / 1e6)]
    TooManyPixels {
        page_mm: f64,
        dpi: f64,
        side_px: u64,
        max_dpi: f64,
    },
    #[error("OpenCV: {0}")]
    OpenCv(#[from] opencv::Error),
}

/// The most pixels a PNG marker page may have: 100 Mpx (a 10 000 px square,
/// 100 MB in memory; 1 m of page at 254 dpi).
pub const MAX_PNG_PIXELS: u64 = 100_000_000;

/// White margin outside the quiet zone, for cut marks and the label (mm).
const MARGIN_MM: f64 = 15.0;
/// Cut-mark length (mm) and gap from the quiet zone corner (mm).
const CUT_LEN_MM: f64 = 6.0;
const CUT_GAP_MM: f64 = 2.0;

/// Page geometry in millimetres.
struct Layout {
    modules: usize,
    module_mm: f64,
    /// Top-left of the black square.
    origin_mm: f64,
    page_mm: f64,
    grid: Vec<bool>,
    label: String,
}

fn layout(codes: CodeSet, id: MarkerId, side_mm: f64) -> Result<Layout, PrintError> {
    if !(5.0..=2000.0).contains(&side_mm) {
        return Err(PrintError::BadSize(side_mm));
    }
    let grid = codes.module_grid(id)?;
    let modules = codes.modules();
    let module_mm = side_mm / modules as f64;
    let origin_mm = MARGIN_MM + module_mm;
    Ok(Layout {
        modules,
        module_mm,
        origin_mm,
        page_mm: side_mm + 2.0 * origin_mm,
        grid,
        label: format!(
            "{} id {}  {:.1} mm (black square)",
            codes.name(),
            id,
            side_mm
        ),
    })
}

impl Layout {
    /// Cut-mark segments `(x0, y0, x1, y1)` in mm at the quiet zone's corners.
    fn cut_marks(&self) -> Vec<[f64; 4]> {
        let lo = MARGIN_MM;
        let hi = self.page_mm - MARGIN_MM;
        let mut v = Vec::new();
        for &x in &[lo, hi] {
            for &y in &[lo, hi] {
                let sx = if x == lo { -1.0 } else { 1.0 };
                let sy = if y == lo { -1.0 } else { 1.0 };
                v.push([
                    x + sx * CUT_GAP_MM,
                    y,
                    x + sx * (CUT_GAP_MM + CUT_LEN_MM),
                    y,
                ]);
                v.push([
                    x,
                    y + sy * CUT_GAP_MM,
                    x,
                    y + sy * (CUT_GAP_MM + CUT_LEN_MM),
                ]);
            }
        }
        v
    }
}

/// The marker as an SVG document whose user unit is the millimetre.
pub fn marker_svg(codes: CodeSet, id: MarkerId, side_mm: f64) -> Result<String, PrintError> {
    let l = layout(codes, id, side_mm)?;
    let p = l.page_mm;
    let mut s = String::new();
    let _ = writeln!(s, r#"<?xml version="1.0" encoding="UTF-8"?>"#);
    let _ = writeln!(
        s,
        r#"<svg xmlns="http://www.w3.org/2000/svg" width="{p:.3}mm" height="{p:.3}mm" viewBox="0 0 {p:.3} {p:.3}" shape-rendering="crispEdges">"#
    );
    let _ = writeln!(
        s,
        r#"<rect x="0" y="0" width="{p:.3}" height="{p:.3}" fill="white"/>"#
    );
    let (o, m) = (l.origin_mm, l.module_mm);
    let n = l.modules;
    let _ = writeln!(
        s,
        r#"<rect x="{o:.4}" y="{o:.4}" width="{side_mm:.4}" height="{side_mm:.4}" fill="black"/>"#
    );
    // White modules, merged into horizontal runs.
    for r in 0..n {
        let mut c = 0;
        while c < n {
            if l.grid[r * n + c] {
                let start = c;
                while c < n && l.grid[r * n + c] {
                    c += 1;
                }
                let _ = writeln!(
                    s,
                    r#"<rect x="{:.4}" y="{:.4}" width="{:.4}" height="{m:.4}" fill="white"/>"#,
                    o + start as f64 * m,
                    o + r as f64 * m,
                    (c - start) as f64 * m
                );
            } else {
                c += 1;
            }
        }
    }
    for [x0, y0, x1, y1] in l.cut_marks() {
        let _ = writeln!(
            s,
            r#"<line x1="{x0:.3}" y1="{y0:.3}" x2="{x1:.3}" y2="{y1:.3}" stroke="black" stroke-width="0.2"/>"#
        );
    }
    let _ = writeln!(
        s,
        r#"<text x="{:.3}" y="{:.3}" font-family="sans-serif" font-size="3.5" fill="black">{}</text>"#,
        MARGIN_MM,
        p - MARGIN_MM / 2.0,
        l.label
    );
    let _ = writeln!(s, "</svg>");
    Ok(s)
}

/// The marker as a grey PNG at `dpi`, with the resolution stored in its
/// `pHYs` chunk so that printing at 100 % gives the true size.
pub fn marker_png(
    codes: CodeSet,
    id: MarkerId,
    side_mm: f64,
    dpi: f64,
) -> Result<Vec<u8>, PrintError> {
    if !(72.0..=2400.0).contains(&dpi) {
        return Err(PrintError::BadDpi(dpi));
    }
    let l = layout(codes, id, side_mm)?;
    let px_per_mm = dpi / 25.4;
    let side_px = (l.page_mm * px_per_mm).round() as u64;
    if side_px * side_px > MAX_PNG_PIXELS {
        return Err(PrintError::TooManyPixels {
            page_mm: l.page_mm,
            dpi,
            side_px,
            max_dpi: ((MAX_PNG_PIXELS as f64).sqrt() / l.page_mm * 25.4).floor(),
        });
    }
    let size = side_px as i32;
    let mut img = Mat::new_rows_cols_with_default(size, size, CV_8UC1, Scalar::all(255.0))?;
    {
        let data = img.data_bytes_mut()?;
        let n = l.modules as f64;
        for y in 0..size as usize {
            let ym = (y as f64 + 0.5) / px_per_mm;
            let r = ((ym - l.origin_mm) / l.module_mm).floor();
            if r < 0.0 || r >= n {
                continue;
            }
            for x in 0..size as usize {
                let xm = (x as f64 + 0.5) / px_per_mm;
                let c = ((xm - l.origin_mm) / l.module_mm).floor();
                if c < 0.0 || c >= n {
                    continue;
                }
                if !l.grid[r as usize * l.modules + c as usize] {
                    data[y * size as usize + x] = 0;
                }
            }
        }
    }
    let to_px = |v: f64| (v * px_per_mm).round() as i32;
    let thickness = to_px(0.2).max(1);
    for [x0, y0, x1, y1] in l.cut_marks() {
        imgproc::line(
            &mut img,
            Point::new(to_px(x0), to_px(y0)),
            Point::new(to_px(x1), to_px(y1)),
            Scalar::all(0.0),
            thickness,
            imgproc::LINE_8,
            0,
        )?;
    }
    // Hershey simplex: scale 1.0 is ~22 px cap height; aim for ~3 mm.
    let scale = (3.0 * px_per_mm / 22.0).max(0.3);
    imgproc::put_text(
        &mut img,
        &l.label,
        Point::new(to_px(MARGIN_MM), to_px(l.page_mm - MARGIN_MM / 2.0)),
        imgproc::FONT_HERSHEY_SIMPLEX,
        scale,
        Scalar::all(0.0),
        (scale * 1.5).ceil() as i32,
        imgproc::LINE_AA,
        false,
    )?;
    let mut buf: Vector<u8> = Vector::new();
    imgcodecs::imencode(".png", &img, &mut buf, &Vector::new())?;
    Ok(with_phys(buf.to_vec(), dpi))
}

/// Insert a `pHYs` chunk (pixels per metre) right after the PNG's IHDR chunk.
fn with_phys(png: Vec<u8>, dpi: f64) -> Vec<u8> {
    // 8-byte signature + IHDR (4 length + 4 type + 13 data + 4 CRC).
    const IHDR_END: usize = 8 + 25;
    if png.len() < IHDR_END || &png[12..16] != b"IHDR" {
        return png;
    }
    let ppm = (dpi / 0.0254).round() as u32;
    let mut chunk = Vec::with_capacity(21);
    chunk.extend_from_slice(&9u32.to_be_bytes());
    let mut body = Vec::with_capacity(13);
    body.extend_from_slice(b"pHYs");
    body.extend_from_slice(&ppm.to_be_bytes());
    body.extend_from_slice(&ppm.to_be_bytes());
    body.push(1); // unit: metre
    chunk.extend_from_slice(&body);
    chunk.extend_from_slice(&crc32(&body).to_be_bytes());
    let mut out = Vec::with_capacity(png.len() + chunk.len());
    out.extend_from_slice(&png[..IHDR_END]);
    out.extend_from_slice(&chunk);
    out.extend_from_slice(&png[IHDR_END..]);
    out
}

/// CRC-32 (IEEE, as PNG chunks use).
fn crc32(data: &[u8]) -> u32 {
    let mut crc = 0xFFFF_FFFFu32;
    for &b in data {
        crc ^= u32::from(b);
        for _ in 0..8 {
            crc = if crc & 1 != 0 {
                (crc >> 1) ^ 0xEDB8_8320
            } else {
                crc >> 1
            };
        }
    }
    !crc
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Issue #22: size and dpi were checked apart, so 390 mm at 2 400 dpi
    /// asked for 2.2 GB. The page's pixel count is checked before any allocation,
    /// and the error says which dpi would fit.
    #[test]
    fn a_png_page_over_the_pixel_limit_is_refused_with_the_dpi_that_fits() {
        let e = marker_png(CodeSet::Shoal, 17, 390.0, 2400.0).unwrap_err();
        let PrintError::TooManyPixels {
            max_dpi, side_px, ..
        } = e
        else {
            panic!("{e}");
        };
        assert!(side_px * side_px > MAX_PNG_PIXELS);
        assert!(e.to_string().contains("SVG"), "{e}");
        // The suggested dpi is the largest that fits, and it does.
        let l = layout(CodeSet::Shoal, 17, 390.0).unwrap();
        let px = |dpi: f64| (l.page_mm * dpi / 25.4).round() as u64;
        assert!(px(max_dpi).pow(2) <= MAX_PNG_PIXELS);
        assert!(px(max_dpi + 2.0).pow(2) > MAX_PNG_PIXELS);
        assert!(marker_png(CodeSet::Shoal, 17, 100.0, 300.0).is_ok());
    }

    #[test]
    fn crc32_matches_the_png_reference_value() {
        // CRC of the IEND chunk type, present in every PNG.
        assert_eq!(crc32(b"IEND"), 0xAE42_6082);
    }

    #[test]
    fn svg_is_true_size_and_labelled() {
        let s = marker_svg(CodeSet::Shoal, 17, 120.0).unwrap();
        // 120 mm + 2 modules of quiet zone (12 mm each) + 2 x 15 mm margin.
        assert!(s.contains(r#"width="174.000mm""#), "{s}");
        assert!(s.contains("shoal id 17"));
        assert_eq!(s.matches("<line").count(), 8);
        assert!(matches!(
            marker_svg(CodeSet::Shoal, 99, 120.0),
            Err(PrintError::Marker(_))
        ));
        assert!(matches!(
            marker_svg(CodeSet::Shoal, 1, f64::NAN),
            Err(PrintError::BadSize(_))
        ));
    }

    #[test]
    fn png_decodes_back_to_the_module_grid_for_every_code_set() {
        for &codes in CodeSet::all() {
            let id = 3;
            let png = marker_png(codes, id, 60.0, 300.0).unwrap();
            assert_eq!(&png[37..41], b"pHYs");
            let v: Vector<u8> = Vector::from_slice(&png);
            let img = imgcodecs::imdecode(&v, imgcodecs::IMREAD_GRAYSCALE).unwrap();
            let l = layout(codes, id, 60.0).unwrap();
            let px_per_mm = 300.0 / 25.4;
            for r in 0..l.modules {
                for c in 0..l.modules {
                    let x = ((l.origin_mm + (c as f64 + 0.5) * l.module_mm) * px_per_mm) as i32;
                    let y = ((l.origin_mm + (r as f64 + 0.5) * l.module_mm) * px_per_mm) as i32;
                    let white = *img.at_2d::<u8>(y, x).unwrap() > 127;
                    assert_eq!(
                        white,
                        l.grid[r * l.modules + c],
                        "{codes} module ({r}, {c})"
                    );
                }
            }
        }
    }
}
