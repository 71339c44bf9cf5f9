//! shoal's processes over Zenoh: each module is one process of the system,
//! moving an algorithm crate's data over the bus (`shoal-bus`), so that the
//! algorithm crates themselves (`shoal-node`, `shoal-fusion`,
//! `shoal-sim-bridge`, `shoal-record`) know nothing of Zenoh.
//!
//! - [`node`]: the vehicle node (`shoal node`): camera frames from Zenoh or a
//!   local source → `shoal_node`'s camera threads → observations, status and
//!   liveliness on the vehicle's keys;
//! - [`fusion`]: the fusion service (`shoal fusion`): every vehicle's
//!   observations and liveliness → `shoal_fusion::Fusion` → the fleet map,
//!   published and served to late joiners; [`fusion::MapClient`] for controllers;
//! - [`link`]: the link sender (`shoal link`): a vehicle's observations →
//!   compact packets at an acoustic modem's rate; `fusion` reads them with
//!   `FusionConfig::link`;
//! - [`sim`]: the simulator's bridge (`shoal sim`): `shoal_sim_bridge`'s world
//!   and renderer → frames, ground truth; vehicle commands back;
//! - [`recorder`]: the recorder (`shoal record`): the fleet's keys →
//!   `shoal_record::Recording` (MCAP);
//! - [`replay`]: replay (`shoal replay`): a log → its keys, byte for byte;
//! - [`ros2`]: shoal as a ROS 2 node over `rmw_zenoh` (`--ros2`): maps,
//!   observations and health republished as ROS 2 topics, CDR-encoded;
//! - [`relay`]: the fault-injecting TCP relay between two routers
//!   (`shoal relay`, the link-fault tests), and message-level faults.
//!
//! The ground station (`shoal-station`) is its own crate over `shoal-bus`.

// A library reports failures as errors; an `unwrap()` that cannot fail says why with `expect`.
#![warn(clippy::unwrap_used)]

pub mod fusion;
pub mod link;
pub mod node;
pub mod recorder;
pub mod relay;
pub mod replay;
pub mod ros2;
pub mod sim;
