//! Camera frames: read in place from their envelope and written as PNG
//! `CompressedImage` messages.

use super::{camera_frame, camera_topic, msg, t, FoxgloveMessage, FoxgloveValue};
use foxglove::messages::CompressedImage;
use proto::config::Fleet;
use proto::{PixelFormat, VehicleId};

/// The fields of a `CameraFrame` envelope the recorder needs, read in place
/// at the offsets pinned by `docs/wire.md` (no copy of the pixels; decoding
/// the whole frame through serde costs more than encoding its PNG).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FrameView<'a> {
    pub vehicle: VehicleId,
    pub camera: u8,
    pub seq: u64,
    pub stamp_ns: u64,
    pub width: u32,
    pub height: u32,
    pub format: PixelFormat,
    pub data: &'a [u8],
}

impl<'a> FrameView<'a> {
    /// Byte offset in the payload (after the 12-byte envelope header) of the
    /// camera model's lens: its variant (u32), then its coefficients.
    const LENS_AT: usize = 4 + 1 + 8 + 8 + 2 * 4 + 4 * 8;

    /// `None` unless `envelope` is a well-formed `CameraFrame` whose pixel count agrees with its size.
    pub fn parse(envelope: &'a [u8]) -> Option<FrameView<'a>> {
        let header = proto::codec::peek_header(envelope).ok()?;
        if header.kind != proto::MessageKind::CameraFrame {
            return None;
        }
        let p = envelope.get(proto::codec::HEADER_LEN..)?;
        let u32_at = |o: usize| {
            p.get(o..o + 4)
                .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        };
        let u64_at = |o: usize| {
            p.get(o..o + 8)
                .map(|b| u64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]]))
        };
        // `Distortion`: a u32 variant, then plumb-bob 5, rational 8 or
        // equidistant 4 coefficients; schema 4 had 5 coefficients, no variant.
        let lens_len = if header.version == 4 {
            5 * 8
        } else {
            4 + 8 * match u32_at(Self::LENS_AT)? {
                0 => 5,
                1 => 8,
                2 => 4,
                _ => return None,
            }
        };
        let format_at = Self::LENS_AT + lens_len + 7 * 8;
        let data_at = format_at + 4 + 8;
        let format = match u32_at(format_at)? {
            0 => PixelFormat::Mono8,
            1 => PixelFormat::Rgb8,
            _ => return None,
        };
        let (width, height) = (u32_at(21)?, u32_at(25)?);
        let len = usize::try_from(u64_at(format_at + 4)?).ok()?;
        let want = (width as usize)
            .checked_mul(height as usize)?
            .checked_mul(format.channels())?;
        if len != want || p.len() != data_at + len {
            return None;
        }
        Some(FrameView {
            vehicle: u32_at(0)?,
            camera: p[4],
            seq: u64_at(5)?,
            stamp_ns: u64_at(13)?,
            width,
            height,
            format,
            data: &p[data_at..],
        })
    }
}

/// A camera frame as a PNG `CompressedImage` (Foxglove decodes PNG in the browser).
pub fn camera_image(
    fleet: &Fleet,
    f: &FrameView<'_>,
) -> Result<FoxgloveMessage, image::ImageError> {
    let color = match f.format {
        PixelFormat::Mono8 => image::ExtendedColorType::L8,
        PixelFormat::Rgb8 => image::ExtendedColorType::Rgb8,
    };
    let mut png = Vec::with_capacity(f.data.len() / 2);
    // Fast deflate: frames arrive at camera rate; zstd on the chunk does the rest.
    let encoder = image::codecs::png::PngEncoder::new_with_quality(
        &mut png,
        image::codecs::png::CompressionType::Fast,
        image::codecs::png::FilterType::Sub,
    );
    image::ImageEncoder::write_image(encoder, f.data, f.width, f.height, color)?;
    Ok(msg(
        format!("{}/image", camera_topic(fleet, f.vehicle, f.camera)),
        FoxgloveValue::CompressedImage(CompressedImage {
            timestamp: t(f.stamp_ns),
            frame_id: camera_frame(fleet, f.vehicle, f.camera),
            data: foxglove::bytes::Bytes::from(png),
            format: "png".into(),
        }),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use proto::geometry::Pose;

    #[test]
    fn frame_view_reads_what_the_codec_wrote() {
        use proto::Distortion;
        for lens in [
            Distortion::PlumbBob([0.1; 5]),
            Distortion::Rational([0.1; 8]),
            Distortion::Equidistant([0.1; 4]),
        ] {
            frame_view_reads_a_frame_with(lens);
        }
    }

    fn frame_view_reads_a_frame_with(lens: proto::Distortion) {
        let f = proto::CameraFrame {
            vehicle: 15,
            camera: 3,
            seq: 9,
            stamp_ns: 123_456,
            info: proto::CameraInfo {
                model: proto::CameraModel {
                    width: 4,
                    height: 2,
                    fx: 5.0,
                    fy: 5.0,
                    cx: 2.0,
                    cy: 1.0,
                    distortion: lens,
                },
                body_from_camera: Pose::identity(),
            },
            format: PixelFormat::Rgb8,
            data: (0..24).collect(),
        };
        let bytes = proto::encode(&f).unwrap();
        let v = FrameView::parse(&bytes).unwrap();
        assert_eq!(
            (v.vehicle, v.camera, v.seq, v.stamp_ns, v.width, v.height, v.format),
            (15, 3, 9, 123_456, 4, 2, PixelFormat::Rgb8)
        );
        assert_eq!(v.data, &f.data[..]);
        assert!(FrameView::parse(&bytes[..bytes.len() - 1]).is_none());
        if let proto::Distortion::PlumbBob(_) = lens {
            // Schema 4 (older logs): 5 coefficients and no variant tag.
            let h = proto::codec::HEADER_LEN;
            let tag = h + FrameView::LENS_AT;
            let mut v4 = [&bytes[..tag], &bytes[tag + 4..]].concat();
            v4[4..6].copy_from_slice(&4u16.to_le_bytes());
            let len = (v4.len() - h) as u32;
            v4[8..12].copy_from_slice(&len.to_le_bytes());
            let old = FrameView::parse(&v4).expect("a schema-4 frame");
            assert_eq!((old.seq, old.width, old.data), (9, 4, &f.data[..]));
        }
        let obs_like = proto::encode(&proto::VehicleCommand {
            vehicle: 1,
            stamp_ns: 2,
            velocity_body: [0.0; 3],
            yaw_rate: 0.0,
        })
        .unwrap();
        assert!(FrameView::parse(&obs_like).is_none());
    }
}
