//! The per-vehicle pipeline of shoal (paper §4–§5): camera frames →
//! HOIRM restoration → enhanced-marker detection → PnP with covariance →
//! `observer_from_target` observations, on each camera's thread. No Zenoh:
//! the node service that feeds it from the bus is `shoal_services::node`.
//!
//! - [`restore`]: HOIRM (paper §4) and the baselines (none, CLAHE, DCP, UDCP);
//! - [`metrics`]: SSIM, PSNR, CNR for scoring restoration;
//! - [`detect`]: contour/quad detection, grid code reading, 12 sub-pixel corners;
//! - [`pose`]: IPPE-initialized iterative PnP keeping both planar hypotheses, with covariance;
//! - [`baseline`]: OpenCV's ArUco detector and AprilTag 3 behind the same interface;
//! - [`image_file`]: the one bounded reader of image files (size, pixel and truncation checks, 16-bit scaling);
//! - [`print`]: printable markers (SVG, PNG);
//! - [`mat`]: zero-fuss conversions between `GrayImage` and `cv::Mat`;
//! - [`pipeline`]: one camera's chain, restore → detect → PnP → body-frame observations;
//! - [`track`]: constant-velocity SE(3) tracking that bridges short occlusions;
//! - [`vehicle`]: the vehicle's camera threads, fed from any [`vehicle::FrameInput`], and their counters;
//! - [`source`]: local frame sources (a folder of images, a video, a camera: V4L2, a GStreamer pipeline), with capture stamps, missed frames and reconnection;
//! - [`clock`]: the machine's clocks as capture stamps and the status need them (wall, monotonic offset, the kernel's NTP/PTP state).

// A library reports failures as errors; an `unwrap()` that cannot fail says why with `expect`.
#![warn(clippy::unwrap_used)]

pub mod baseline;
pub mod board;
pub mod calibrate;
pub mod clock;
pub mod detect;
pub mod image_file;
pub mod mat;
pub mod metrics;
pub mod pipeline;
pub mod pose;
pub mod print;
pub mod restore;
pub mod ros_image;
pub mod source;
pub mod track;
pub mod vehicle;
