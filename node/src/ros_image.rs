//! ROS 2 camera images (`sensor_msgs/msg/Image`, `CompressedImage`) as the
//! 8-bit grey frames the pipeline reads (a node's `ros2:TOPIC` source).
//!
//! Raw encodings read: `mono8`, `8UC1`, `rgb8`, `bgr8`, `rgba8`, `bgra8`
//! (luma, BT.601 weights), `mono16` / `16UC1` (the high byte, either byte
//! order). Compressed: whatever [`crate::image_file::decode_gray`] reads
//! (JPEG, PNG, …; image_transport's `"bgr8; jpeg compressed bgr8"` formats
//! included), with the same pixel limit as image files.

use crate::image_file::{decode_gray, MAX_IMAGE_PIXELS};
use crate::mat::mat_to_gray;
use shoal_proto::ros2::msgs::{CompressedImage, Image};
use shoal_proto::GrayImage;

/// Why a ROS image is not a frame.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("ROS image on {topic}: {reason}")]
pub struct RosImageError {
    pub topic: String,
    pub reason: String,
}

/// One pixel's bytes (and whether they are big-endian) to grey.
type ToGrey = fn(&[u8], bool) -> u8;

/// Bytes per pixel and how to turn one pixel into grey.
fn layout(encoding: &str) -> Option<(usize, ToGrey)> {
    fn luma(r: u8, g: u8, b: u8) -> u8 {
        ((299 * r as u32 + 587 * g as u32 + 114 * b as u32 + 500) / 1000) as u8
    }
    Some(match encoding {
        "mono8" | "8UC1" => (1, |p, _| p[0]),
        "rgb8" => (3, |p, _| luma(p[0], p[1], p[2])),
        "bgr8" => (3, |p, _| luma(p[2], p[1], p[0])),
        "rgba8" => (4, |p, _| luma(p[0], p[1], p[2])),
        "bgra8" => (4, |p, _| luma(p[2], p[1], p[0])),
        "mono16" | "16UC1" => (2, |p, big| if big { p[0] } else { p[1] }),
        _ => return None,
    })
}

/// A raw ROS image as 8-bit grey.
pub fn gray_of_image(topic: &str, img: &Image) -> Result<GrayImage, RosImageError> {
    let err = |reason: String| RosImageError {
        topic: topic.to_string(),
        reason,
    };
    let (bpp, grey) = layout(&img.encoding).ok_or_else(|| {
        err(format!(
            "encoding {:?} is not read (mono8, rgb8, bgr8, rgba8, bgra8, mono16)",
            img.encoding
        ))
    })?;
    let (w, h) = (img.width as usize, img.height as usize);
    if w == 0 || h == 0 || (w as u64) * (h as u64) > MAX_IMAGE_PIXELS {
        return Err(err(format!("{w}x{h} pixels")));
    }
    let step = img.step as usize;
    if step < w * bpp || img.data.len() < step * (h - 1) + w * bpp {
        return Err(err(format!(
            "{} bytes with step {step} cannot hold {w}x{h} {}",
            img.data.len(),
            img.encoding
        )));
    }
    let big = img.is_bigendian != 0;
    let mut data = Vec::with_capacity(w * h);
    for row in img.data.chunks(step).take(h) {
        data.extend(row[..w * bpp].chunks_exact(bpp).map(|p| grey(p, big)));
    }
    Ok(GrayImage {
        width: w as u32,
        height: h as u32,
        data,
    })
}

/// A compressed ROS image as 8-bit grey.
pub fn gray_of_compressed(topic: &str, img: &CompressedImage) -> Result<GrayImage, RosImageError> {
    let err = |reason: String| RosImageError {
        topic: topic.to_string(),
        reason,
    };
    let file = decode_gray(topic, &img.data, MAX_IMAGE_PIXELS)
        .map_err(|e| err(format!("{:?}: {e}", img.format)))?;
    mat_to_gray(&file.gray).map_err(|e| err(e.to_string()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use shoal_proto::ros2::msgs::Header;

    fn image(encoding: &str, w: u32, h: u32, step: u32, data: Vec<u8>) -> Image {
        Image {
            header: Header::new(0, "cam"),
            height: h,
            width: w,
            encoding: encoding.into(),
            is_bigendian: 0,
            step,
            data,
        }
    }

    #[test]
    fn raw_encodings_become_grey_and_row_padding_is_skipped() {
        // 2x2 mono8 with 2 bytes of padding per row.
        let g = gray_of_image("t", &image("mono8", 2, 2, 4, vec![1, 2, 0, 0, 3, 4, 0, 0])).unwrap();
        assert_eq!(g.data, vec![1, 2, 3, 4]);
        // Pure red, green, blue in rgb8 and bgr8.
        let rgb = vec![255, 0, 0, 0, 255, 0, 0, 0, 255];
        let g = gray_of_image("t", &image("rgb8", 3, 1, 9, rgb.clone())).unwrap();
        assert_eq!(g.data, vec![76, 150, 29]);
        let bgr: Vec<u8> = rgb.chunks(3).flat_map(|p| [p[2], p[1], p[0]]).collect();
        assert_eq!(
            gray_of_image("t", &image("bgr8", 3, 1, 9, bgr))
                .unwrap()
                .data,
            vec![76, 150, 29]
        );
        // mono16 little-endian: the high byte.
        let g = gray_of_image("t", &image("mono16", 1, 1, 2, vec![0x34, 0x12])).unwrap();
        assert_eq!(g.data, vec![0x12]);
    }

    #[test]
    fn bad_images_are_errors_naming_the_topic() {
        for (img, what) in [
            (image("yuv422", 2, 2, 4, vec![0; 8]), "encoding"),
            (image("mono8", 4, 4, 4, vec![0; 15]), "cannot hold"),
            (image("mono8", 0, 4, 0, vec![]), "0x4"),
        ] {
            let e = gray_of_image("/cam/image_raw", &img)
                .unwrap_err()
                .to_string();
            assert!(e.contains("/cam/image_raw") && e.contains(what), "{e}");
        }
        let junk = CompressedImage {
            header: Header::new(0, "cam"),
            format: "jpeg".into(),
            data: vec![1, 2, 3],
        };
        let e = gray_of_compressed("/cam/compressed", &junk)
            .unwrap_err()
            .to_string();
        assert!(e.contains("/cam/compressed"), "{e}");
    }
}
