//! The `shoal` application layer: compositions of the library crates that
//! the command-line tool and the end-to-end tests share (the demo).

pub mod demo;
pub mod eval;
pub mod rerun;
