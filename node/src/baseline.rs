//! Baseline detectors behind [`crate::detect::MarkerDetector`]: OpenCV's ArUco
//! detector and AprilTag 3 (Debian's libapriltag).

pub mod apriltag_ffi;
