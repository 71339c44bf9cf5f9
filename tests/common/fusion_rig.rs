//! A fusion service on an in-process Zenoh router, driven by a manual clock,
//! and one observation publisher per vehicle: the setup of the tests that
//! feed synthesized observations to fusion over Zenoh.

#![allow(dead_code)] // each test binary uses a different part

use shoal_bus::{client_of, free_port, Bus, Connect, Publisher};
use shoal_fusion::FusionParams;
use shoal_proto::clock::ManualClock;
use shoal_proto::config::Fleet;
use shoal_proto::messages::Observation;
use shoal_proto::VehicleId;
use shoal_services::fusion::{FusionConfig, FusionHandle, Placement};
use std::collections::BTreeMap;
use std::sync::Arc;

pub struct Rig {
    pub port: u16,
    pub clock: Arc<ManualClock>,
    pub fleet: Arc<Fleet>,
    _router: Bus,
}

impl Rig {
    pub fn new(fleet: Arc<Fleet>) -> Rig {
        let port = free_port().unwrap();
        let router = Bus::open(&Connect::Router { port }).unwrap();
        Rig {
            port,
            clock: Arc::new(ManualClock::new(0)),
            fleet,
            _router: router,
        }
    }

    /// A new client session on the rig's router.
    pub fn session(&self) -> Bus {
        Bus::open(&client_of(self.port)).unwrap()
    }

    /// A fusion service on its own session, at 10 Hz on the rig's clock.
    pub fn fusion(
        &self,
        placement: Placement,
        params: FusionParams,
        queue_capacity: usize,
    ) -> FusionHandle {
        shoal_services::fusion::spawn(
            &self.session(),
            FusionConfig {
                fleet: self.fleet.clone(),
                params,
                placement,
                rate_hz: 10.0,
                queue_capacity,
                link: false,
            },
            self.clock.clone(),
        )
        .unwrap()
    }

    /// One observation publisher per vehicle, on `bus`, under its own key.
    pub fn observation_publishers(&self, bus: &Bus) -> BTreeMap<VehicleId, Publisher<Observation>> {
        let keys = self.fleet.keys();
        self.fleet
            .vehicles
            .iter()
            .map(|v| (v.id, bus.publisher(keys.observations(v.id)).unwrap()))
            .collect()
    }
}
