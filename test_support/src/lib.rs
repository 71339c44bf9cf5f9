//! Fixtures shared by shoal's tests and benchmarks that production code does
//! not use, kept out of the product crates. Only ever a dev-dependency
//! (`publish = false`).
//!
//! - [`synthetic`]: degraded frames of an enhanced-marker-like pattern, with
//!   their clean twin and cell masks, for restoration tests and benches that
//!   must not depend on the simulator.

// A library reports failures as errors; an `unwrap()` that cannot fail says why with `expect`.
#![warn(clippy::unwrap_used)]

pub mod synthetic;
