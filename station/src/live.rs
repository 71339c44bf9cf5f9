//! Foxglove's live WebSocket protocol (the `foxglove` crate's server), with
//! the **same channels, schema records and protobuf bytes as the MCAP logs**:
//! every message is built by `shoal_record::foxglove` (the functions the
//! recorder writes its Foxglove channels with) and encoded once by
//! `FoxgloveMessage::encode`; each channel declares
//! `FoxgloveSchema::schema` (the `foxglove` crate's descriptor). A layout
//! made for a log works on the live swarm unchanged.
//!
//! `--foxglove-mcap FILE` adds the `foxglove` crate's MCAP writer as a second
//! sink of the **same `foxglove::Context`**: the file holds exactly what the
//! live clients were sent (the station's view of a trial, Foxglove channels
//! only; a full log with the wire channels is `shoal record`'s).
//!
//! Not forwarded: camera images (the station does not subscribe to frames;
//! at 1.5 MB each they would dominate the link to the vessel).

use crate::StationError;
use foxglove::{
    Context, McapWriteOptions, McapWriter, McapWriterHandle, RawChannel, WebSocketServer,
    WebSocketServerHandle,
};
use shoal_record::foxglove::{FoxgloveMessage, FoxgloveSchema};
use std::collections::HashMap;
use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// The live Foxglove server and its channels (created on first use per topic).
pub struct FoxgloveLive {
    ctx: Arc<Context>,
    server: Option<WebSocketServerHandle>,
    port: u16,
    channels: HashMap<String, Arc<RawChannel>>,
    mcap: Option<(PathBuf, McapWriterHandle<BufWriter<File>>)>,
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
            mcap: None,
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

    /// Also write every message sent from now on to an MCAP file (the
    /// `foxglove` crate's writer, a second sink of this server's context).
    pub fn record(&mut self, path: &Path) -> Result<(), StationError> {
        let handle = McapWriter::with_options(McapWriteOptions::new().profile(""))
            .context(&self.ctx)
            .create_new_buffered_file(path)
            .map_err(|e| StationError::FoxgloveMcap {
                path: path.to_path_buf(),
                reason: e.to_string(),
            })?;
        self.mcap = Some((path.to_path_buf(), handle));
        Ok(())
    }

    /// Send messages (as built by `shoal_record::foxglove`) to subscribed
    /// clients and the MCAP sink. Log time is the time of sending (Foxglove's
    /// default); the messages carry their own stamps, as in the logs.
    pub fn send(&mut self, messages: Vec<FoxgloveMessage>) {
        for m in messages {
            let Some(channel) = self.channel(&m.topic, m.schema()) else {
                continue;
            };
            match m.encode() {
                Ok(bytes) => channel.log(&bytes),
                Err(e) => tracing::warn!("station: {e}"),
            }
        }
    }

    fn channel(&mut self, topic: &str, schema: FoxgloveSchema) -> Option<Arc<RawChannel>> {
        if let Some(c) = self.channels.get(topic) {
            return Some(c.clone());
        }
        match self
            .ctx
            .channel_builder(topic)
            .message_encoding(schema.message_encoding())
            .schema(schema.schema())
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
        if let Some((path, w)) = self.mcap.take() {
            if let Err(e) = w.close() {
                tracing::error!("station: closing {}: {e}", path.display());
            }
        }
    }
}

impl Drop for FoxgloveLive {
    fn drop(&mut self) {
        self.shutdown();
    }
}
