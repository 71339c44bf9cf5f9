//! A plain owned 8-bit grey image: the hand-off between the simulator (which
//! knows no OpenCV) and the node (which wraps it in a `cv::Mat` without copying).

use serde::{Deserialize, Serialize};

/// Row-major 8-bit grey pixels, no padding.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct GrayImage {
    pub width: u32,
    pub height: u32,
    pub data: Vec<u8>,
}

impl GrayImage {
    /// A `width`x`height` image filled with `value`.
    pub fn filled(width: u32, height: u32, value: u8) -> GrayImage {
        GrayImage {
            width,
            height,
            data: vec![value; width as usize * height as usize],
        }
    }

    /// Wrap pixels; `None` when the length does not match the size.
    pub fn from_vec(width: u32, height: u32, data: Vec<u8>) -> Option<GrayImage> {
        (data.len() == width as usize * height as usize).then_some(GrayImage {
            width,
            height,
            data,
        })
    }

    pub fn get(&self, x: u32, y: u32) -> u8 {
        self.data[y as usize * self.width as usize + x as usize]
    }
}
