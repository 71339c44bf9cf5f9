//! shoal's underwater world without a pool: a physically based image
//! synthesizer (see `docs/water-model.md`), a swarm world with ground truth,
//! an observation-level synthesizer for fusion at scale, and the Zenoh bridge
//! that publishes it all as a real fleet would.

pub mod bridge;
pub mod error;
pub mod obs_synth;
pub mod render;
pub mod water;
pub mod world;

pub use error::SimError;
