//! One module per subcommand: argument types and a `run` that calls the libraries.

pub mod args;
pub mod calib;
pub mod config;
pub mod demo;
pub mod eval;
pub mod log;
pub mod net;
pub mod relay;
pub mod services;
pub mod sim_render;
pub mod soak;
pub mod station;
pub mod tools;
