//! The `shoal` application layer: compositions of the library crates that
//! the command-line tool and the end-to-end tests share (the demo).

// A library reports failures as errors; an `unwrap()` that cannot fail says why with `expect`.
#![warn(clippy::unwrap_used)]

pub mod stdout;

pub mod demo;
pub mod eval;
pub mod redetect;
pub mod soak;
