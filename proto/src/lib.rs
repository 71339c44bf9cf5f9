//! shoal's shared vocabulary: everything two shoal processes must agree on,
//! and nothing about how bytes move (no Zenoh) or how pixels are processed
//! (no OpenCV).
//!
//! - [`messages`]: the wire types (observations, fleet map, camera frames,
//!   ground truth, node status, vehicle commands);
//! - [`codec`]: the versioned envelope around their bincode 2 payloads
//!   (layout in `docs/wire.md`);
//! - [`keys`]: every Zenoh key expression, built and parsed in one place;
//! - [`geometry`]: SE(3) poses and the 6x6 covariance convention;
//! - [`camera`]: the pinhole + distortion camera model shared by simulator
//!   and detector;
//! - [`marker`]: code sets (enhanced marker, ArUco, AprilTag) and their layouts;
//! - [`config`]: fleet files and camera calibrations;
//! - [`compact`]: the 53-byte observation for acoustic-rate links (versioned, quantized);
//! - [`files`]: the bounded reader of every small input file and the output that appears only when complete;
//! - [`queue`]: the bounded drop-oldest queue every shoal queue is;
//! - [`clock`]: injected clocks (wall time, or simulation and replay time).
//! - [`ros2`]: ROS 2 messages in CDR and `rmw_zenoh`'s keys and tokens (no Zenoh here either).

// A library reports failures as errors; an `unwrap()` that cannot fail says why with `expect`.
#![warn(clippy::unwrap_used)]

pub mod camera;
pub mod clock;
pub mod codec;
pub mod compact;
pub mod config;
pub mod files;
pub mod geometry;
pub mod image;
pub mod keys;
pub mod marker;
pub mod messages;
pub mod nav;
pub mod port;
pub mod queue;
pub mod ros2;
pub mod samples;
pub mod splitmix;

pub use camera::{CalibrationSigma, CameraModel, Distortion};
pub use codec::{decode, encode, DecodeError, EncodeError};
pub use geometry::{Cov6, Pose, PoseWithCovariance};
pub use image::GrayImage;
pub use keys::{KeyKind, Keys};
pub use marker::{CodeSet, MarkerId};
pub use messages::*;
pub use nav::NavState;
pub use port::FlatPort;
