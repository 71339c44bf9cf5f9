//! The per-vehicle pipeline of shoal (paper §4–§5): camera frames →
//! HOIRM restoration → enhanced-marker detection → PnP with covariance →
//! `observer_from_target` observations, and the Zenoh node service around it.
//!
//! - [`restore`]: HOIRM (paper §4) and the baselines (none, CLAHE, DCP, UDCP);
//! - [`metrics`]: SSIM, PSNR, CNR for scoring restoration;
//! - [`detect`]: contour/quad detection, grid code reading, 12 sub-pixel corners;
//! - [`pose`]: IPPE-initialized iterative PnP keeping both planar hypotheses, with covariance;
//! - [`baseline`]: OpenCV's ArUco detector and AprilTag 3 behind the same interface;
//! - [`print`]: printable markers (SVG, PNG);
//! - [`mat`]: zero-fuss conversions between `GrayImage` and `cv::Mat`;
//! - [`pipeline`]: one camera's chain, restore → detect → PnP → body-frame observations;
//! - [`track`]: constant-velocity SE(3) tracking that bridges short occlusions;
//! - [`service`], [`source`]: the Zenoh node service and its frame sources.

pub mod baseline;
pub mod detect;
pub mod mat;
pub mod metrics;
pub mod pipeline;
pub mod pose;
pub mod print;
pub mod restore;
pub mod service;
pub mod source;
pub mod track;
