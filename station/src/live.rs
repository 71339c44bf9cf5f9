//! Foxglove's live WebSocket protocol (the `foxglove` crate's server), with
//! the **same channels, schemas and JSON messages as the MCAP logs**: every
//! message goes through `shoal_record::foxglove` (the functions the
//! recorder writes its Foxglove channels with), and each channel declares
//! the recorder's JSON schema (`message_encoding = "json"`, schema encoding
//! `jsonschema`). A layout made for a log works on the live swarm unchanged.
//!
//! Not forwarded: camera images (the station does not subscribe to frames;
//! at 1.5 MB each they would dominate the link to the vessel).

use crate::StationError;
use foxglove::{Context, RawChannel, Schema, WebSocketServer, WebSocketServerHandle};
use shoal_record::foxglove::{FoxgloveMessage, FoxgloveSchema};
use std::collections::HashMap;
use std::sync::Arc;

/// The live Foxglove server and its channels (created on first use per topic).
pub struct FoxgloveLive {
    ctx: Arc<Context>,
    server: Option<WebSocketServerHandle>,
    port: u16,
    channels: HashMap<String, Arc<RawChannel>>,
    schemas: HashMap<FoxgloveSchema, Vec<u8>>,
}

impl std::fmt::Debug for FoxgloveLive {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FoxgloveLive")
            .field("port", &self.port)
            .field("channels", &self.channels.len())
            .finish()
    }
}

impl FoxgloveLive {
    /// Start the server on `host:port` (port 0: any free port). Its own
    /// context, so several stations in one process stay apart.
    pub fn start(host: &str, port: u16) -> Result<FoxgloveLive, StationError> {
        let ctx = Context::new();
        let server = WebSocketServer::new()
            .name("shoal station")
            .bind(host, port)
            .context(&ctx)
            .start_blocking()
            .map_err(|e| StationError::Foxglove {
                addr: format!("{host}:{port}"),
                reason: e.to_string(),
            })?;
        let port = server.port();
        Ok(FoxgloveLive {
            ctx,
            server: Some(server),
            port,
            channels: HashMap::new(),
            schemas: HashMap::new(),
        })
    }

    /// The port the server listens on.
    pub fn port(&self) -> u16 {
        self.port
    }

    /// Foxglove clients connected now.
    pub fn clients(&self) -> usize {
        self.server.as_ref().map_or(0, |s| s.client_count())
    }

    /// Send messages (as built by `shoal_record::foxglove`) to subscribed clients.
    /// Log time is the arrival time at the station (Foxglove's default); the
    /// messages carry their own `stamp_ns` timestamps, as in the logs.
    pub fn send(&mut self, messages: Vec<FoxgloveMessage>) {
        for m in messages {
            let Some(channel) = self.channel(&m.topic, m.schema) else {
                continue;
            };
            match serde_json::to_vec(&m.value) {
                Ok(bytes) => channel.log(&bytes),
                Err(e) => tracing::warn!("station: foxglove {}: {e}", m.topic),
            }
        }
    }

    fn channel(&mut self, topic: &str, schema: FoxgloveSchema) -> Option<Arc<RawChannel>> {
        if let Some(c) = self.channels.get(topic) {
            return Some(c.clone());
        }
        let data = self
            .schemas
            .entry(schema)
            .or_insert_with(|| serde_json::to_vec(&schema.json_schema()).unwrap_or_default())
            .clone();
        match self
            .ctx
            .channel_builder(topic)
            .message_encoding("json")
            .schema(Schema::new(schema.name(), "jsonschema", data))
            .build_raw()
        {
            Ok(c) => {
                self.channels.insert(topic.to_string(), c.clone());
                Some(c)
            }
            Err(e) => {
                tracing::warn!("station: foxglove channel {topic}: {e}");
                None
            }
        }
    }

    /// Stop the server and wait for its tasks.
    pub fn stop(mut self) {
        self.shutdown();
    }

    fn shutdown(&mut self) {
        if let Some(s) = self.server.take() {
            s.stop().wait_blocking();
        }
    }
}

impl Drop for FoxgloveLive {
    fn drop(&mut self) {
        self.shutdown();
    }
}
