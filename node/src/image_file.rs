//! One bounded reader for every image file shoal takes (`shoal detect`,
//! `shoal restore`, the image-folder source, the real-footage evaluation):
//! the file's size and the pixel count its header declares are checked
//! before anything is decoded, a file cut short is an error rather than an
//! image with a grey bottom, and 16-bit data keeps its contrast (issue #22).
//!
//! - The size on disk is bounded by [`MAX_IMAGE_FILE_BYTES`] and read once.
//! - The header's width × height is bounded by the caller's pixel limit
//!   ([`MAX_IMAGE_PIXELS`] for reading and detection; restoration has its own,
//!   smaller one, [`crate::restore::MAX_RESTORE_PIXELS`]). A format whose header
//!   cannot be read here is refused: a decoder must not be the first to learn
//!   how large a picture is.
//! - PNG (chunk walk to `IEND`), JPEG (`EOI` after the scan), BMP, binary
//!   PNM and TIFF (pixel data as long as the header or the strip table says)
//!   are checked for truncation; the decoders of those formats return a
//!   partial picture without an error.
//! - 16-bit grey (a 12-bit machine-vision camera's PNGs) is scaled from its
//!   significant bits (the PNG `sBIT` chunk, else the largest value) instead
//!   of keeping only the top byte, which leaves 12-bit data a few grey levels.

use opencv::core::{Mat, Vector, CV_16U, CV_8U, CV_8UC1};
use opencv::imgcodecs;
use opencv::prelude::*;
use opencv::videoio::{self, VideoCapture};
use std::path::Path;

/// The largest image file read (bytes on disk).
pub const MAX_IMAGE_FILE_BYTES: u64 = 256 << 20;

/// The most pixels an image may declare to be read or detected in: 64 Mpx
/// (8 000 x 8 000). Detection of a busy 48 Mpx frame peaks at ~215 MB
/// (`docs/results.md`, "Hostile files"); a colour JPEG at the limit
/// decodes into ~260 MB before it is turned grey.
pub const MAX_IMAGE_PIXELS: u64 = 64_000_000;

/// Why an image file was not read.
#[derive(Debug, thiserror::Error)]
pub enum ImageError {
    #[error("{path}: cannot read: {source}")]
    Io {
        path: String,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: {bytes} bytes is more than the {max}-byte limit for an image file")]
    FileTooLarge { path: String, bytes: u64, max: u64 },
    #[error("{path}: not an image shoal reads ({reason})")]
    Format { path: String, reason: String },
    #[error("{path}: not a video shoal reads ({reason})")]
    Video { path: String, reason: String },
    #[error("{path}: {width}x{height} pixels ({} Mpx) is more than the limit of {} Mpx{for_what}", mpx(*width, *height), *max as f64 / 1e6)]
    TooManyPixels {
        path: String,
        width: u64,
        height: u64,
        max: u64,
        /// ` for restoration`, … (empty for plain reading).
        for_what: &'static str,
    },
    #[error("{path}: truncated or damaged: {reason}")]
    Truncated { path: String, reason: String },
    #[error("{path}: cannot decode: {reason}")]
    Decode { path: String, reason: String },
}

fn mpx(w: u64, h: u64) -> String {
    format!("{:.1}", (w * h) as f64 / 1e6)
}

/// An image file read as 8-bit grey.
#[derive(Debug)]
pub struct GrayFile {
    /// `CV_8UC1`, never empty.
    pub gray: Mat,
    /// What was done to the pixels that a user should know (16-bit scaling, …).
    pub notes: Vec<String>,
}

/// The declared size of an image from its header; `None` for a format whose
/// header is not understood here.
pub fn declared_size(bytes: &[u8]) -> Option<(u64, u64)> {
    let s = imagesize::blob_size(bytes).ok()?;
    Some((s.width as u64, s.height as u64))
}

/// Check `width` x `height` against `max` pixels.
pub fn check_pixels(
    path: &str,
    width: u64,
    height: u64,
    max: u64,
    for_what: &'static str,
) -> Result<(), ImageError> {
    if width.saturating_mul(height) > max {
        return Err(ImageError::TooManyPixels {
            path: path.to_string(),
            width,
            height,
            max,
            for_what,
        });
    }
    Ok(())
}

/// Open a video file, refusing one whose frames are larger than `max_pixels`
/// before a frame is decoded. Also gives the frame count the container
/// declares (0 when it does not say), to tell a cut-short video from a whole one.
pub fn open_video(path: &Path, max_pixels: u64) -> Result<(VideoCapture, u64), ImageError> {
    let name = path.display().to_string();
    let format = |reason: String| ImageError::Video {
        path: name.clone(),
        reason,
    };
    if !path.is_file() {
        return Err(ImageError::Io {
            path: name.clone(),
            source: std::io::Error::new(std::io::ErrorKind::NotFound, "no such file"),
        });
    }
    let cap = VideoCapture::from_file(&name, videoio::CAP_ANY)
        .map_err(|e| format(format!("cannot open as a video: {e}")))?;
    if !cap.is_opened().unwrap_or(false) {
        return Err(format("cannot open as a video".into()));
    }
    let prop = |p| cap.get(p).unwrap_or(0.0);
    let (w, h) = (
        prop(videoio::CAP_PROP_FRAME_WIDTH),
        prop(videoio::CAP_PROP_FRAME_HEIGHT),
    );
    if !(w >= 1.0 && h >= 1.0) {
        return Err(format(format!("the video gives no frame size ({w}x{h})")));
    }
    check_pixels(&name, w as u64, h as u64, max_pixels, "")?;
    let frames = prop(videoio::CAP_PROP_FRAME_COUNT);
    let frames = if frames.is_finite() && frames > 0.0 {
        frames as u64
    } else {
        0
    };
    Ok((cap, frames))
}

/// Why a video that gave `read` frames before its end is cut short or
/// damaged, when its container declared `declared` (0: not declared). A
/// container's count can be an estimate from duration x rate: a shortfall
/// of one frame or 1 % is not called damage.
pub fn video_shortfall(read: u64, declared: u64) -> Option<String> {
    let slack = (declared / 100).max(1);
    (declared > 0 && read + slack < declared).then(|| {
        format!("the video ended after {read} of the {declared} frames its container declares (truncated or damaged)")
    })
}

/// Read `path` as 8-bit grey, refusing more than `max_pixels`.
pub fn read_gray(path: &Path, max_pixels: u64) -> Result<GrayFile, ImageError> {
    read_gray_for(path, max_pixels, "")
}

/// [`read_gray`], with `for_what` (e.g. `" for restoration"`) saying whose limit `max_pixels` is.
pub fn read_gray_for(
    path: &Path,
    max_pixels: u64,
    for_what: &'static str,
) -> Result<GrayFile, ImageError> {
    let name = path.display().to_string();
    let bytes = read_bounded(path, &name)?;
    decode(&name, &bytes, max_pixels, for_what)
}

fn read_bounded(path: &Path, name: &str) -> Result<Vec<u8>, ImageError> {
    use std::io::Read;
    let io = |source| ImageError::Io {
        path: name.to_string(),
        source,
    };
    let file = std::fs::File::open(path).map_err(io)?;
    if file.metadata().map_err(io)?.is_dir() {
        return Err(ImageError::Format {
            path: name.to_string(),
            reason: "a directory".into(),
        });
    }
    let mut bytes = Vec::new();
    file.take(MAX_IMAGE_FILE_BYTES + 1)
        .read_to_end(&mut bytes)
        .map_err(io)?;
    if bytes.len() as u64 > MAX_IMAGE_FILE_BYTES {
        return Err(ImageError::FileTooLarge {
            path: name.to_string(),
            bytes: std::fs::metadata(path).map_or(bytes.len() as u64, |m| m.len()),
            max: MAX_IMAGE_FILE_BYTES,
        });
    }
    Ok(bytes)
}

/// [`read_gray`] of bytes already in memory; `name` is used in messages.
pub fn decode_gray(name: &str, bytes: &[u8], max_pixels: u64) -> Result<GrayFile, ImageError> {
    decode(name, bytes, max_pixels, "")
}

fn decode(
    name: &str,
    bytes: &[u8],
    max_pixels: u64,
    for_what: &'static str,
) -> Result<GrayFile, ImageError> {
    let format = |reason: &str| ImageError::Format {
        path: name.to_string(),
        reason: reason.to_string(),
    };
    if bytes.is_empty() {
        return Err(format("empty file"));
    }
    let kind = imagesize::image_type(bytes).map_err(|_| format("unknown format"))?;
    let (w, h) = declared_size(bytes).ok_or_else(|| format("its header gives no size"))?;
    if w == 0 || h == 0 {
        return Err(format("its header gives a size of zero"));
    }
    check_pixels(name, w, h, max_pixels, for_what)?;
    if let Some(reason) = truncation(kind, bytes, w, h) {
        return Err(ImageError::Truncated {
            path: name.to_string(),
            reason,
        });
    }
    let decode = |reason: String| ImageError::Decode {
        path: name.to_string(),
        reason,
    };
    let buf = Vector::<u8>::from_slice(bytes);
    let mat = imgcodecs::imdecode(
        &buf,
        imgcodecs::IMREAD_GRAYSCALE | imgcodecs::IMREAD_ANYDEPTH,
    )
    .map_err(|e| decode(e.to_string()))?;
    if mat.empty() {
        return Err(decode("the decoder gave no picture".into()));
    }
    // The decoder turns a photo by its EXIF orientation: width and height may swap.
    let got = (mat.cols() as u64, mat.rows() as u64);
    if got != (w, h) && got != (h, w) {
        return Err(decode(format!(
            "the header says {w}x{h} but the picture is {}x{}",
            mat.cols(),
            mat.rows()
        )));
    }
    to_gray8(&mat, sbit_gray(kind, bytes)).map_err(|e| decode(e.to_string()))
}

/// Scale a decoded grey picture of any depth to `CV_8UC1`.
fn to_gray8(mat: &Mat, sbit: Option<u8>) -> opencv::Result<GrayFile> {
    let mut notes = Vec::new();
    if mat.typ() == CV_8UC1 {
        return Ok(GrayFile {
            gray: mat.clone(),
            notes,
        });
    }
    let mut out = Mat::default();
    if mat.depth() == CV_16U {
        let mut max = 0.0;
        opencv::core::min_max_loc(
            mat,
            None,
            Some(&mut max),
            None,
            None,
            &opencv::core::no_array(),
        )?;
        let (bits, from) = match sbit {
            Some(b @ 1..=16) => (u32::from(b), "its sBIT chunk"),
            _ => (
                (max as u32 + 1)
                    .next_power_of_two()
                    .trailing_zeros()
                    .clamp(8, 16),
                "its largest value",
            ),
        };
        if bits < 16 {
            notes.push(format!(
                "16-bit picture with {bits} significant bits (from {from}; largest value {max}): scaled by 255/{}",
                (1u32 << bits) - 1
            ));
        }
        mat.convert_to(&mut out, CV_8U, 255.0 / f64::from((1u32 << bits) - 1), 0.0)?;
    } else {
        // Floating-point (EXR, HDR, PFM) or other depths: stretch the range.
        let (mut lo, mut hi) = (0.0, 0.0);
        opencv::core::min_max_loc(
            mat,
            Some(&mut lo),
            Some(&mut hi),
            None,
            None,
            &opencv::core::no_array(),
        )?;
        let scale = if hi > lo { 255.0 / (hi - lo) } else { 1.0 };
        notes.push(format!(
            "picture of depth {} with values {lo}..{hi}: stretched to 0..255",
            mat.depth()
        ));
        mat.convert_to(&mut out, CV_8U, scale, -lo * scale)?;
    }
    Ok(GrayFile { gray: out, notes })
}

/// A PNG's `sBIT` for grey (or the first channel of colour), if present.
fn sbit_gray(kind: imagesize::ImageType, bytes: &[u8]) -> Option<u8> {
    if kind != imagesize::ImageType::Png {
        return None;
    }
    png_chunks(bytes)
        .ok()?
        .into_iter()
        .find(|(t, _)| t == b"sBIT")
        .and_then(|(_, data)| data.first().copied())
}

/// A PNG chunk's type and data.
type PngChunk<'a> = ([u8; 4], &'a [u8]);

/// The chunks of a PNG up to `IEND`, or why the walk failed.
fn png_chunks(bytes: &[u8]) -> Result<Vec<PngChunk<'_>>, String> {
    let mut at = 8usize;
    let mut chunks = Vec::new();
    loop {
        let Some(head) = bytes.get(at..at + 8) else {
            return Err(format!(
                "the file ends at byte {} before the IEND chunk",
                bytes.len()
            ));
        };
        let len = u32::from_be_bytes([head[0], head[1], head[2], head[3]]) as usize;
        let kind = [head[4], head[5], head[6], head[7]];
        let end = at
            .checked_add(12)
            .and_then(|v| v.checked_add(len))
            .filter(|&e| e <= bytes.len())
            .ok_or_else(|| {
                format!(
                    "chunk {:?} at byte {at} needs {len} bytes, the file ends at {}",
                    String::from_utf8_lossy(&kind),
                    bytes.len()
                )
            })?;
        chunks.push((kind, &bytes[at + 8..at + 8 + len]));
        if &kind == b"IEND" {
            return Ok(chunks);
        }
        at = end;
    }
}

/// Why a file of `kind`, declared `w` x `h`, is shorter than its picture; `None` when whole
/// (or when the format is not checked here).
fn truncation(kind: imagesize::ImageType, bytes: &[u8], w: u64, h: u64) -> Option<String> {
    use imagesize::ImageType;
    match kind {
        ImageType::Png => png_chunks(bytes).err(),
        ImageType::Jpeg => jpeg_truncation(bytes),
        ImageType::Bmp => bmp_truncation(bytes, w, h),
        ImageType::Pnm => pnm_truncation(bytes, w, h),
        ImageType::Tiff => tiff_truncation(bytes),
        _ => None,
    }
}

/// A JPEG ends with `EOI` (`FF D9`) after its first scan (`FF DA`): the
/// segments before the scan are walked by their lengths (an EXIF thumbnail
/// is a whole JPEG inside one), and inside entropy-coded data every `FF` is
/// followed by `00` or a restart marker.
fn jpeg_truncation(bytes: &[u8]) -> Option<String> {
    let short = |at: usize| {
        Some(format!(
            "the segments before the scan run past the end (byte {at} of {})",
            bytes.len()
        ))
    };
    let mut at = 2usize;
    let sos = loop {
        while bytes.get(at) == Some(&0xFF) && bytes.get(at + 1) == Some(&0xFF) {
            at += 1; // fill bytes
        }
        let (Some(0xFF), Some(&marker)) = (bytes.get(at), bytes.get(at + 1)) else {
            return short(at);
        };
        match marker {
            0xDA => break at,
            0x01 | 0xD0..=0xD8 => at += 2,
            _ => {
                let (Some(&hi), Some(&lo)) = (bytes.get(at + 2), bytes.get(at + 3)) else {
                    return short(at);
                };
                at += 2 + usize::from(u16::from_be_bytes([hi, lo]));
            }
        }
    };
    if bytes[sos..].windows(2).any(|p| p == [0xFF, 0xD9]) {
        None
    } else {
        Some(format!(
            "no end-of-image marker after the scan that starts at byte {sos} (the file ends at {})",
            bytes.len()
        ))
    }
}

/// An uncompressed BMP holds `h` rows of `w` pixels, each row padded to 4 bytes.
fn bmp_truncation(bytes: &[u8], w: u64, h: u64) -> Option<String> {
    let le32 = |at: usize| -> Option<u32> {
        bytes
            .get(at..at + 4)
            .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
    };
    if le32(14)? < 40 {
        return None; // an OS/2 core header: other field offsets, the decoder's business.
    }
    let offset = u64::from(le32(10)?);
    let bpp = u64::from(u16::from_le_bytes([*bytes.get(28)?, *bytes.get(29)?]));
    let compression = le32(30)?;
    if compression != 0 || bpp == 0 {
        return None; // RLE and bit fields: the decoder's business.
    }
    let row = (w * bpp).div_ceil(32) * 4;
    let need = offset + row * h;
    (need > bytes.len() as u64)
        .then(|| format!("its pixels need {need} bytes, the file has {}", bytes.len()))
}

/// A TIFF's first image: every strip (or tile) its directory lists must lie
/// inside the file (libtiff decodes what it finds and leaves the rest blank).
fn tiff_truncation(bytes: &[u8]) -> Option<String> {
    let little = match bytes.get(..2)? {
        b"II" => true,
        b"MM" => false,
        _ => return None,
    };
    let u16_at = |at: usize| -> Option<u64> {
        let b = bytes.get(at..at + 2)?;
        Some(u64::from(if little {
            u16::from_le_bytes([b[0], b[1]])
        } else {
            u16::from_be_bytes([b[0], b[1]])
        }))
    };
    let u32_at = |at: usize| -> Option<u64> {
        let b = bytes.get(at..at + 4)?;
        Some(u64::from(if little {
            u32::from_le_bytes([b[0], b[1], b[2], b[3]])
        } else {
            u32::from_be_bytes([b[0], b[1], b[2], b[3]])
        }))
    };
    let short = |what: &str| {
        Some(format!(
            "its {what} lies past the end of the file ({} bytes)",
            bytes.len()
        ))
    };
    if u16_at(2)? != 42 {
        return None; // BigTIFF: 64-bit offsets, the decoder's business.
    }
    let ifd = usize::try_from(u32_at(4)?).ok()?;
    let Some(entries) = u16_at(ifd) else {
        return short("image directory");
    };
    // The directory ends with the offset of the next one.
    if u32_at(ifd + 2 + 12 * entries as usize).is_none() {
        return short("image directory");
    }
    // The strip (or tile) offsets and byte counts, inline or where the entry points.
    let mut offsets = None;
    let mut counts = None;
    for k in 0..entries as usize {
        let e = ifd + 2 + 12 * k;
        let (Some(tag), Some(typ), Some(n)) = (u16_at(e), u16_at(e + 2), u32_at(e + 4)) else {
            return short("image directory");
        };
        let size = match typ {
            3 => 2,
            4 => 4,
            _ => continue,
        };
        let values_at = if n * size <= 4 {
            e + 8
        } else {
            usize::try_from(u32_at(e + 8)?).ok()?
        };
        let read = |i: usize| {
            if size == 2 {
                u16_at(values_at + 2 * i)
            } else {
                u32_at(values_at + 4 * i)
            }
        };
        let values: Option<Vec<u64>> = (0..n.min(1 << 20) as usize).map(read).collect();
        match (tag, values) {
            (273 | 324, Some(v)) => offsets = Some(v),
            (279 | 325, Some(v)) => counts = Some(v),
            (273 | 324 | 279 | 325, None) => return short("strip table"),
            _ => {}
        }
    }
    let (offsets, counts) = (offsets?, counts?);
    let end = offsets.iter().zip(&counts).map(|(o, c)| o + c).max()?;
    (end > bytes.len() as u64).then(|| {
        format!(
            "its pixel data ends at byte {end}, the file has {}",
            bytes.len()
        )
    })
}

/// Binary PNM (`P4`, `P5`, `P6`): the header, then exactly the pixels.
fn pnm_truncation(bytes: &[u8], w: u64, h: u64) -> Option<String> {
    let magic = bytes.get(..2)?;
    let channels = match magic {
        b"P4" => 0,
        b"P5" => 1,
        b"P6" => 3,
        _ => return None, // ASCII variants: the decoder reports short ones.
    };
    // Header fields: magic, width, height and (except P4) maxval, separated by
    // whitespace and comments, then one whitespace byte.
    let fields = if channels == 0 { 3 } else { 4 };
    let (mut at, mut seen) = (0usize, 0);
    let mut maxval = 255u64;
    while seen < fields {
        while at < bytes.len() && (bytes[at].is_ascii_whitespace() || bytes[at] == b'#') {
            if bytes[at] == b'#' {
                while at < bytes.len() && bytes[at] != b'\n' {
                    at += 1;
                }
            }
            // A comment may run to the end of the file: never past it.
            at = (at + 1).min(bytes.len());
        }
        let start = at;
        while at < bytes.len() && !bytes[at].is_ascii_whitespace() {
            at += 1;
        }
        if seen == 3 {
            maxval = std::str::from_utf8(&bytes[start..at]).ok()?.parse().ok()?;
        }
        seen += 1;
    }
    let header = at as u64 + 1;
    let need = header
        + if channels == 0 {
            w.div_ceil(8) * h
        } else {
            w * h * channels * if maxval > 255 { 2 } else { 1 }
        };
    (need > bytes.len() as u64)
        .then(|| format!("its pixels need {need} bytes, the file has {}", bytes.len()))
}

#[cfg(test)]
mod tests {
    /// Found by `fuzz_image`'s random bytes (session 39): a header comment
    /// that runs to the end of the file walked one byte past it and
    /// panicked on the slice; it is no truncation to report (the decoder
    /// then refuses the header).
    #[test]
    fn a_pnm_header_comment_to_the_end_of_the_file_is_not_a_panic() {
        for bytes in [&b"P5 #"[..], b"P5 4 #", b"P6 4 4 #x", b"P5\n#"] {
            assert_eq!(pnm_truncation(bytes, 4, 4), None, "{bytes:?}");
        }
        // P4 has no maxval to parse: its fields run out and the pixels it
        // needs are reported missing.
        assert_eq!(
            pnm_truncation(b"P4 #\n#", 4, 4).as_deref(),
            Some("its pixels need 11 bytes, the file has 6")
        );
        assert!(pnm_truncation(b"P5 4 4 255 ", 4, 4).is_some());
    }

    use super::*;
    use opencv::core::{Scalar, CV_16UC1};

    fn encode(ext: &str, m: &Mat) -> Vec<u8> {
        let mut buf = Vector::<u8>::new();
        assert!(imgcodecs::imencode(ext, m, &mut buf, &Vector::new()).unwrap());
        buf.to_vec()
    }

    fn ramp() -> Mat {
        let mut m = Mat::new_rows_cols_with_default(48, 64, CV_8UC1, Scalar::all(0.0)).unwrap();
        for y in 0..48 {
            for x in 0..64 {
                *m.at_2d_mut::<u8>(y, x).unwrap() = (x * 4) as u8;
            }
        }
        m
    }

    #[test]
    fn whole_files_of_each_checked_format_are_read() {
        for ext in [".png", ".jpg", ".bmp", ".pgm", ".tif"] {
            let bytes = encode(ext, &ramp());
            let g = decode_gray(ext, &bytes, MAX_IMAGE_PIXELS).unwrap();
            assert_eq!((g.gray.cols(), g.gray.rows()), (64, 48), "{ext}");
            assert!(g.notes.is_empty(), "{ext}: {:?}", g.notes);
        }
    }

    #[test]
    fn a_file_cut_short_is_truncated_not_a_grey_bottomed_picture() {
        for ext in [".png", ".jpg", ".bmp", ".pgm", ".tif"] {
            let bytes = encode(ext, &ramp());
            let cut = &bytes[..bytes.len() * 3 / 4];
            let e = decode_gray("f", cut, MAX_IMAGE_PIXELS).unwrap_err();
            assert!(matches!(e, ImageError::Truncated { .. }), "{ext}: {e}");
        }
    }

    #[test]
    fn the_header_size_is_checked_before_decoding() {
        let bytes = encode(".png", &ramp());
        let e = decode_gray("f.png", &bytes, 64 * 48 - 1).unwrap_err();
        assert!(e.to_string().contains("64x48"), "{e}");
        assert!(matches!(e, ImageError::TooManyPixels { .. }));
        assert!(decode_gray("f.png", &bytes, 64 * 48).is_ok());
    }

    #[test]
    fn twelve_bit_data_in_a_16_bit_png_keeps_its_contrast() {
        let mut m = Mat::new_rows_cols_with_default(48, 64, CV_16UC1, Scalar::all(0.0)).unwrap();
        for y in 0..48 {
            for x in 0..64 {
                *m.at_2d_mut::<u16>(y, x).unwrap() = (x * 65) as u16; // up to 4095
            }
        }
        let g = decode_gray("f", &encode(".png", &m), MAX_IMAGE_PIXELS).unwrap();
        assert_eq!(*g.gray.at_2d::<u8>(0, 63).unwrap(), 255);
        assert_eq!(*g.gray.at_2d::<u8>(0, 32).unwrap(), 130); // 2080 * 255 / 4095
        assert!(g.notes[0].contains("12 significant bits"), "{:?}", g.notes);
    }

    /// A phone photo's EXIF orientation turns the picture: its width and
    /// height swap against the header's, and that is not damage.
    #[test]
    fn an_exif_rotated_jpeg_is_read_turned() {
        let jpeg = encode(".jpg", &ramp());
        let mut exif =
            b"Exif\0\0II*\0\x08\0\0\0\x01\0\x12\x01\x03\0\x01\0\0\0\x06\0\0\0\0\0\0\0".to_vec();
        let len = (exif.len() + 2) as u16;
        let mut app1 = vec![0xFF, 0xE1];
        app1.extend_from_slice(&len.to_be_bytes());
        app1.append(&mut exif);
        let mut bytes = jpeg[..2].to_vec();
        bytes.extend_from_slice(&app1);
        bytes.extend_from_slice(&jpeg[2..]);
        let g = decode_gray("turned.jpg", &bytes, MAX_IMAGE_PIXELS).unwrap();
        assert_eq!((g.gray.cols(), g.gray.rows()), (48, 64));
    }

    #[test]
    fn garbage_and_empty_files_are_format_errors() {
        for bytes in [&b""[..], b"hello, not an image", &[0u8; 100]] {
            let e = decode_gray("x", bytes, MAX_IMAGE_PIXELS).unwrap_err();
            assert!(matches!(e, ImageError::Format { .. }), "{e}");
        }
    }
}
