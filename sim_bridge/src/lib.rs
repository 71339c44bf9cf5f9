//! shoal's underwater world without a pool: a physically based image
//! synthesizer (see `docs/water-model.md`), a swarm world with ground truth,
//! and an observation-level synthesizer for fusion at scale. No Zenoh: the
//! bridge that publishes it all as a real fleet would is `shoal_services::sim`.

// A library reports failures as errors; an `unwrap()` that cannot fail says why with `expect`.
#![warn(clippy::unwrap_used)]

pub mod error;
pub mod nav;
pub mod obs_synth;
pub mod profile;
pub mod render;
pub mod water;
pub mod world;

pub use error::SimError;
