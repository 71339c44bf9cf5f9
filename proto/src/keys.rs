//! Zenoh key expressions: the only place in shoal where keys are built or parsed.
//!
//! ```text
//! shoal/<fleet>/<vehicle>/obs              observations published by a vehicle node
//! shoal/<fleet>/<vehicle>/cam/<k>/frame    camera frames (simulator or camera driver)
//! shoal/<fleet>/<vehicle>/status           node diagnostics
//! shoal/<fleet>/<vehicle>/alive            liveliness token of a node
//! shoal/<fleet>/<vehicle>/cmd              velocity commands to a vehicle
//! shoal/<fleet>/<vehicle>/nav              the vehicle's own navigation (depth, roll/pitch, velocity)
//! shoal/<fleet>/<vehicle>/link             compact observations for an acoustic-rate link (`LinkPacket`)
//! shoal/<fleet>/map                        fused fleet map (put) and its queryable
//! shoal/<fleet>/map/<producer>             a decentralized fusion instance's map
//! shoal/<fleet>/sim/truth                  simulator ground truth
//! ```
//!
//! These are plain strings; this crate knows nothing of Zenoh itself.

use crate::messages::VehicleId;

/// What a concrete key refers to.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum KeyKind {
    Observations { vehicle: VehicleId },
    Frame { vehicle: VehicleId, camera: u8 },
    Status { vehicle: VehicleId },
    Alive { vehicle: VehicleId },
    Command { vehicle: VehicleId },
    Nav { vehicle: VehicleId },
    Link { vehicle: VehicleId },
    Map { producer: Option<String> },
    Truth,
}

#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum KeyError {
    #[error("fleet name {0:?} must be 1-64 characters of [A-Za-z0-9_-]")]
    BadFleetName(String),
    #[error("key {0:?} is not a shoal key of this fleet")]
    NotShoalKey(String),
}

/// Key builder for one fleet.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Keys {
    fleet: String,
}

impl Keys {
    pub fn new(fleet: &str) -> Result<Keys, KeyError> {
        let ok = !fleet.is_empty()
            && fleet.len() <= 64
            && fleet
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-');
        if ok {
            Ok(Keys {
                fleet: fleet.to_string(),
            })
        } else {
            Err(KeyError::BadFleetName(fleet.to_string()))
        }
    }

    pub fn fleet(&self) -> &str {
        &self.fleet
    }

    fn vehicle(&self, v: VehicleId, tail: &str) -> String {
        format!("shoal/{}/{}/{}", self.fleet, v, tail)
    }

    pub fn observations(&self, v: VehicleId) -> String {
        self.vehicle(v, "obs")
    }
    pub fn frame(&self, v: VehicleId, camera: u8) -> String {
        self.vehicle(v, &format!("cam/{camera}/frame"))
    }
    pub fn status(&self, v: VehicleId) -> String {
        self.vehicle(v, "status")
    }
    pub fn alive(&self, v: VehicleId) -> String {
        self.vehicle(v, "alive")
    }
    pub fn command(&self, v: VehicleId) -> String {
        self.vehicle(v, "cmd")
    }
    pub fn nav(&self, v: VehicleId) -> String {
        self.vehicle(v, "nav")
    }
    pub fn link(&self, v: VehicleId) -> String {
        self.vehicle(v, "link")
    }
    pub fn map(&self) -> String {
        format!("shoal/{}/map", self.fleet)
    }
    pub fn map_of(&self, producer: &str) -> String {
        format!("shoal/{}/map/{}", self.fleet, producer)
    }
    pub fn truth(&self) -> String {
        format!("shoal/{}/sim/truth", self.fleet)
    }

    /// Wildcards for subscribers.
    pub fn all_observations(&self) -> String {
        self.vehicle_wild("obs")
    }
    pub fn all_frames_of(&self, v: VehicleId) -> String {
        self.vehicle(v, "cam/*/frame")
    }
    /// The literal prefix every camera key of `v` starts with (for filtering
    /// recorded topics, which are plain strings, not key expressions).
    pub fn camera_prefix(&self, v: VehicleId) -> String {
        self.vehicle(v, "cam/")
    }
    pub fn all_frames(&self) -> String {
        self.vehicle_wild("cam/*/frame")
    }
    pub fn all_status(&self) -> String {
        self.vehicle_wild("status")
    }
    pub fn all_alive(&self) -> String {
        self.vehicle_wild("alive")
    }
    pub fn all_commands(&self) -> String {
        self.vehicle_wild("cmd")
    }
    pub fn all_nav(&self) -> String {
        self.vehicle_wild("nav")
    }
    pub fn all_links(&self) -> String {
        self.vehicle_wild("link")
    }
    pub fn all_maps(&self) -> String {
        format!("shoal/{}/map/**", self.fleet)
    }
    /// Everything under vehicle `v`'s own keys (what its access rule allows it to publish).
    pub fn vehicle_all(&self, v: VehicleId) -> String {
        self.vehicle(v, "**")
    }
    /// Everything of this fleet (the recorder's subscription).
    pub fn everything(&self) -> String {
        format!("shoal/{}/**", self.fleet)
    }

    fn vehicle_wild(&self, tail: &str) -> String {
        format!("shoal/{}/*/{}", self.fleet, tail)
    }

    /// Classify a concrete key of this fleet.
    pub fn parse(&self, key: &str) -> Result<KeyKind, KeyError> {
        let bad = || KeyError::NotShoalKey(key.to_string());
        let parts: Vec<&str> = key.split('/').collect();
        if parts.len() < 3 || parts[0] != "shoal" || parts[1] != self.fleet {
            return Err(bad());
        }
        match &parts[2..] {
            ["map"] => Ok(KeyKind::Map { producer: None }),
            ["map", p] => Ok(KeyKind::Map {
                producer: Some(p.to_string()),
            }),
            ["sim", "truth"] => Ok(KeyKind::Truth),
            [v, rest @ ..] => {
                let vehicle: VehicleId = v.parse().map_err(|_| bad())?;
                match rest {
                    ["obs"] => Ok(KeyKind::Observations { vehicle }),
                    ["status"] => Ok(KeyKind::Status { vehicle }),
                    ["alive"] => Ok(KeyKind::Alive { vehicle }),
                    ["cmd"] => Ok(KeyKind::Command { vehicle }),
                    ["nav"] => Ok(KeyKind::Nav { vehicle }),
                    ["link"] => Ok(KeyKind::Link { vehicle }),
                    ["cam", k, "frame"] => Ok(KeyKind::Frame {
                        vehicle,
                        camera: k.parse().map_err(|_| bad())?,
                    }),
                    _ => Err(bad()),
                }
            }
            _ => Err(bad()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_parse_back_to_what_built_them() {
        let k = Keys::new("paper").unwrap();
        assert_eq!(
            k.parse(&k.observations(15)).unwrap(),
            KeyKind::Observations { vehicle: 15 }
        );
        assert_eq!(
            k.parse(&k.frame(10, 3)).unwrap(),
            KeyKind::Frame {
                vehicle: 10,
                camera: 3
            }
        );
        assert_eq!(
            k.parse(&k.alive(17)).unwrap(),
            KeyKind::Alive { vehicle: 17 }
        );
        assert_eq!(k.parse(&k.nav(10)).unwrap(), KeyKind::Nav { vehicle: 10 });
        assert_eq!(k.parse(&k.link(17)).unwrap(), KeyKind::Link { vehicle: 17 });
        assert_eq!(k.parse(&k.map()).unwrap(), KeyKind::Map { producer: None });
        assert_eq!(k.parse(&k.truth()).unwrap(), KeyKind::Truth);
        assert!(k.parse("shoal/other/15/obs").is_err());
        assert!(k.parse("shoal/paper/x/obs").is_err());
    }

    #[test]
    fn fleet_names_with_key_syntax_are_refused() {
        for bad in ["", "a/b", "a*", "$x", "with space"] {
            assert!(Keys::new(bad).is_err(), "{bad:?}");
        }
    }
}
