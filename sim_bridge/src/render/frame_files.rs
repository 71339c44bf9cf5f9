//! Rendered frames as PNG files (`shoal sim render`).

use super::RenderOutput;
use crate::error::SimError;
use shoal_proto::GrayImage;
use std::path::Path;

/// Where [`write_frame_pair`] puts the clean twin of `path`: `frame.png` → `frame_clean.png`.
pub fn clean_twin_path(path: &Path) -> std::path::PathBuf {
    let stem = path
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "frame".into());
    let ext = path
        .extension()
        .map(|e| e.to_string_lossy().into_owned())
        .unwrap_or_else(|| "png".into());
    path.with_file_name(format!("{stem}_clean.{ext}"))
}

/// Write a frame to `path` and its clean twin next to it
/// ([`clean_twin_path`]); returns the twin's path. What `shoal sim render` does.
pub fn write_frame_pair(out: &RenderOutput, path: &Path) -> Result<std::path::PathBuf, SimError> {
    write_png(&out.image, path)?;
    let twin = clean_twin_path(path);
    write_png(&out.clean, &twin)?;
    Ok(twin)
}

/// Write an 8-bit grey image as PNG.
pub fn write_png(img: &GrayImage, path: &Path) -> Result<(), SimError> {
    let buf =
        image::GrayImage::from_raw(img.width, img.height, img.data.clone()).ok_or_else(|| {
            SimError::ImageWrite {
                path: path.to_path_buf(),
                message: format!("{} bytes for {}x{}", img.data.len(), img.width, img.height),
            }
        })?;
    buf.save(path).map_err(|e| SimError::ImageWrite {
        path: path.to_path_buf(),
        message: e.to_string(),
    })
}
