//! shoal as a ROS 2 node over `rmw_zenoh` (issue #20), no bridge process:
//! on the same Zenoh session as the service hosting it (`shoal fusion
//! --ros2`, `shoal demo --ros2`), it announces a ROS 2 node and its
//! publishers with `rmw_zenoh`'s liveliness tokens and republishes, CDR-encoded
//! with the attachment ROS 2 subscriptions require:
//!
//! - each fleet map as `geometry_msgs/msg/PoseWithCovarianceStamped` per
//!   localized vehicle on `/shoal/<fleet>/auv<ID>/pose`, and as
//!   `tf2_msgs/msg/TFMessage` on `/tf`;
//! - each observation as `PoseWithCovarianceStamped` on
//!   `/shoal/<fleet>/observations/auv<O>/auv<T>`;
//! - node health (`NodeStatus`) and the map's vehicle states as
//!   `diagnostic_msgs/msg/DiagnosticArray` on `/diagnostics`.
//!
//! Names, frames and conventions: `shoal_proto::ros2`; what a ROS 2 user
//! types: `docs/ros2.md`. A ROS 2 router (`rmw_zenohd`) and shoal's must be
//! the same Zenoh network (connect one to the other, or run shoal's services
//! with `--zenoh-config` pointing at the ROS 2 router).

use crate::fusion::Placement;
use shoal_bus::{Bus, BusError, RawPublisher, Subscription, Token, Worker};
use shoal_proto::config::Fleet;
use shoal_proto::ros2::msgs::{
    DiagnosticArray, PoseWithCovarianceStamped, RosMessage, RosType, TfMessage,
};
use shoal_proto::ros2::rmw::{self, Attachment, EntityKind, Qos, RosNode};
use shoal_proto::ros2::{self as ros, Ros2Names};
use shoal_proto::{FleetMap, NodeStatus, Observation};
use std::collections::HashMap;
use std::sync::atomic::Ordering;
use std::sync::{Arc, Mutex};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

/// The ROS 2 domain of `ROS_DOMAIN_ID`, else 0; a value that is not a
/// number in 0–232 is an error naming it.
pub fn domain_from_env() -> Result<u32, String> {
    match std::env::var("ROS_DOMAIN_ID") {
        Err(_) => Ok(0),
        Ok(s) if s.trim().is_empty() => Ok(0),
        Ok(s) => parse_domain(&s).map_err(|e| format!("ROS_DOMAIN_ID={s:?}: {e}")),
    }
}

/// A ROS 2 domain ID: 0–232 (what DDS port mapping allows; `rmw_zenoh` takes the same range).
pub fn parse_domain(s: &str) -> Result<u32, String> {
    match s.trim().parse::<u32>() {
        Ok(d) if d <= 232 => Ok(d),
        _ => Err("a ROS 2 domain ID is a whole number from 0 to 232".into()),
    }
}

/// What to republish, and as which ROS 2 node.
#[derive(Debug, Clone)]
pub struct Ros2Config {
    pub fleet: Arc<Fleet>,
    pub domain: u32,
    /// The ROS 2 node's name (`ros2 node list` shows `/<name>`).
    pub node_name: String,
    /// The shoal key of the fleet map to republish (`Keys::map` or `map_of`).
    pub map_key: String,
    /// Republish every vehicle's observations.
    pub observations: bool,
    /// Republish node health and map states on `/diagnostics`.
    pub diagnostics: bool,
}

impl Ros2Config {
    /// The map of fusion at `placement`, observations and diagnostics, as
    /// node `shoal_fusion` (`shoal_fusion_auv<V>` on vehicle `V`).
    pub fn for_fusion(fleet: Arc<Fleet>, domain: u32, placement: Placement) -> Self {
        let (_, map_key) = placement.producer_and_key(&fleet.keys());
        let node_name = match placement {
            Placement::Central => "shoal_fusion".to_string(),
            Placement::OnVehicle(v) => format!("shoal_fusion_auv{v}"),
        };
        Self {
            fleet,
            domain,
            node_name,
            map_key,
            observations: true,
            diagnostics: true,
        }
    }
}

/// Samples published per ROS 2 type so far.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Ros2Stats {
    pub maps: u64,
    pub poses: u64,
    pub tf: u64,
    pub observations: u64,
    pub diagnostics: u64,
    /// Samples that could not be put (the reason is logged).
    pub failed: u64,
}

/// One ROS 2 publisher: its Zenoh publisher, liveliness token and sequence.
struct Endpoint {
    publisher: RawPublisher,
    _token: Token,
    gid: [u8; 16],
    sequence: i64,
}

/// The ROS 2 node: its token and its publishers, made on first use.
struct Node {
    bus: Bus,
    node: RosNode,
    _token: Token,
    endpoints: HashMap<String, Endpoint>,
    next_id: u64,
}

impl Node {
    fn announce(bus: &Bus, domain: u32, name: &str) -> Result<Node, BusError> {
        let node = RosNode {
            domain,
            zid: bus.zid(),
            id: 0,
            namespace: "/".into(),
            name: name.to_string(),
        };
        let token = bus.liveliness_token(node.token())?;
        Ok(Node {
            bus: bus.clone(),
            node,
            _token: token,
            endpoints: HashMap::new(),
            next_id: 1,
        })
    }

    fn publish<M: RosMessage>(&mut self, topic: &str, msg: &M, qos: Qos) -> Result<(), BusError> {
        let endpoint = match self.endpoints.get_mut(topic) {
            Some(e) => e,
            None => {
                let e = self.declare(topic, &M::TYPE, qos)?;
                self.endpoints.entry(topic.to_string()).or_insert(e)
            }
        };
        let now_ns = SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos() as i64);
        let attachment = Attachment {
            sequence: endpoint.sequence,
            source_time_ns: now_ns,
            gid: endpoint.gid,
        };
        endpoint.sequence += 1;
        endpoint
            .publisher
            .put(msg.to_cdr(), Some(attachment.to_bytes().to_vec()))
    }

    fn declare(&mut self, topic: &str, ty: &RosType, qos: Qos) -> Result<Endpoint, BusError> {
        let id = self.next_id;
        self.next_id += 1;
        let token_key = self
            .node
            .endpoint_token(EntityKind::Publisher, id, topic, ty, qos);
        let publisher = self
            .bus
            .raw_publisher(rmw::topic_key(self.node.domain, topic, ty))?;
        let token = self.bus.liveliness_token(token_key.clone())?;
        Ok(Endpoint {
            publisher,
            _token: token,
            gid: rmw::gid_of(&token_key),
            sequence: 1,
        })
    }
}

/// A running ROS 2 publisher.
pub struct Ros2Handle {
    worker: Worker,
    stats: Arc<Mutex<Ros2Stats>>,
    node_token: String,
}

impl std::fmt::Debug for Ros2Handle {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Ros2Handle")
            .field("node", &self.node_token)
            .field("stats", &self.stats())
            .finish()
    }
}

impl Ros2Handle {
    pub fn stats(&self) -> Ros2Stats {
        self.stats.lock().map(|g| g.clone()).unwrap_or_default()
    }
    /// The ROS 2 node's liveliness token (what `ros2 node list` discovers).
    pub fn node_token(&self) -> &str {
        &self.node_token
    }
    pub fn stop(self) {
        self.worker.stop();
    }
}

/// What the worker reads.
struct Feeds {
    maps: Subscription<FleetMap>,
    observations: Option<Subscription<Observation>>,
    statuses: Option<Subscription<NodeStatus>>,
}

/// Start republishing on `bus` as ROS 2 node `cfg.node_name`.
pub fn spawn(bus: &Bus, cfg: Ros2Config) -> Result<Ros2Handle, BusError> {
    if !rmw::valid_topic(&format!("/{}", cfg.node_name)) {
        return Err(BusError::ConfigValue(format!(
            "ROS 2 node name {:?}: letters, digits and '_' only, not starting with a digit",
            cfg.node_name
        )));
    }
    let keys = cfg.fleet.keys();
    let feeds = Feeds {
        maps: bus.subscribe(&cfg.map_key, 16)?,
        observations: cfg
            .observations
            .then(|| bus.subscribe(&keys.all_observations(), 1024))
            .transpose()?,
        statuses: cfg
            .diagnostics
            .then(|| bus.subscribe(&keys.all_status(), 256))
            .transpose()?,
    };
    let mut node = Node::announce(bus, cfg.domain, &cfg.node_name)?;
    let node_token = node.node.token();
    let names = Ros2Names::new(&cfg.fleet.name);
    let stats: Arc<Mutex<Ros2Stats>> = Arc::default();
    let shared = stats.clone();
    let worker = Worker::spawn("ros2", move |stop| {
        let mut local = Ros2Stats::default();
        while !stop.load(Ordering::Relaxed) {
            let first = feeds.maps.recv_timeout(Duration::from_millis(20));
            for r in first.into_iter().chain(feeds.maps.drain()) {
                publish_map(&mut node, &names, &r.msg, cfg.diagnostics, &mut local);
            }
            for r in feeds.observations.iter().flat_map(|s| s.drain()) {
                if let Some((topic, msg)) = ros::observation_pose(&r.msg, &names) {
                    count(
                        node.publish(&topic, &msg, Qos::DEFAULT),
                        &mut local.observations,
                        &mut local.failed,
                    );
                }
            }
            for r in feeds.statuses.iter().flat_map(|s| s.drain()) {
                let msg = ros::node_diagnostics(&r.msg);
                count(
                    node.publish(Ros2Names::DIAGNOSTICS, &msg, Qos::DEFAULT),
                    &mut local.diagnostics,
                    &mut local.failed,
                );
            }
            if let Ok(mut g) = shared.lock() {
                *g = local.clone();
            }
        }
    })
    .map_err(|source| BusError::Thread {
        what: "ros2",
        source,
    })?;
    Ok(Ros2Handle {
        worker,
        stats,
        node_token,
    })
}

fn count(result: Result<(), BusError>, ok: &mut u64, failed: &mut u64) {
    match result {
        Ok(()) => *ok += 1,
        Err(e) => {
            *failed += 1;
            if failed.is_power_of_two() {
                tracing::warn!("ROS 2 publication #{failed} failed: {e}");
            }
        }
    }
}

fn publish_map(
    node: &mut Node,
    names: &Ros2Names,
    map: &FleetMap,
    diagnostics: bool,
    stats: &mut Ros2Stats,
) {
    stats.maps += 1;
    for (topic, msg) in ros::map_poses(map, names) {
        let r = node.publish::<PoseWithCovarianceStamped>(&topic, &msg, Qos::DEFAULT);
        count(r, &mut stats.poses, &mut stats.failed);
    }
    let tf = ros::map_tf(map);
    if !tf.transforms.is_empty() {
        let r = node.publish::<TfMessage>(Ros2Names::TF, &tf, Qos::TF);
        count(r, &mut stats.tf, &mut stats.failed);
    }
    if diagnostics {
        let r = node.publish::<DiagnosticArray>(
            Ros2Names::DIAGNOSTICS,
            &ros::map_diagnostics(map),
            Qos::DEFAULT,
        );
        count(r, &mut stats.diagnostics, &mut stats.failed);
    }
}

/// A node camera fed from a ROS 2 image topic (`shoal node --source ros2:TOPIC`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Ros2ImageSource {
    pub domain: u32,
    /// Fully qualified topic of `sensor_msgs/msg/Image` or `CompressedImage`.
    pub topic: String,
    /// Which of the vehicle's cameras it is (index in the fleet file).
    pub camera: u8,
}

/// Frames of one camera from a ROS 2 image topic: every sample on the topic's
/// keys (`<domain>/<topic>/<type>/<hash>`, either image type), decoded to
/// 8-bit grey; the capture stamp is the header's (arrival time when it is
/// zero). Samples that are not images, or not readable ones, are counted
/// and logged, never passed on.
pub struct Ros2Frames {
    queue: shoal_bus::RawQueue,
    _subscription: shoal_bus::Declaration,
    _tokens: [Token; 2],
    vehicle: shoal_proto::VehicleId,
    camera: u8,
    info: shoal_proto::CameraInfo,
    topic: String,
    seq: std::sync::atomic::AtomicU64,
    rejected: std::sync::atomic::AtomicU64,
}

impl std::fmt::Debug for Ros2Frames {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Ros2Frames")
            .field("topic", &self.topic)
            .finish()
    }
}

impl Ros2Frames {
    /// Subscribe to `src.topic` for `vehicle`'s camera `info`, and announce
    /// the subscription as ROS 2 node `shoal_node_auv<vehicle>`.
    pub fn subscribe(
        bus: &Bus,
        src: &Ros2ImageSource,
        vehicle: shoal_proto::VehicleId,
        info: shoal_proto::CameraInfo,
        capacity: usize,
    ) -> Result<Ros2Frames, BusError> {
        if !rmw::valid_topic(&src.topic) {
            return Err(BusError::ConfigValue(format!(
                "ROS 2 topic {:?}: expected a fully qualified name such as /camera/image_raw",
                src.topic
            )));
        }
        let stripped = src.topic.trim_start_matches('/');
        let (queue, subscription) =
            bus.subscribe_raw(&format!("{}/{stripped}/*/*", src.domain), capacity)?;
        let node = RosNode {
            domain: src.domain,
            zid: bus.zid(),
            id: 0,
            namespace: "/".into(),
            name: format!("shoal_node_auv{vehicle}"),
        };
        // image_transport names compressed topics `…/compressed`.
        let ty = if src.topic.ends_with("/compressed") {
            shoal_proto::ros2::msgs::COMPRESSED_IMAGE
        } else {
            shoal_proto::ros2::msgs::IMAGE
        };
        let tokens = [
            bus.liveliness_token(node.token())?,
            bus.liveliness_token(node.endpoint_token(
                EntityKind::Subscription,
                1,
                &src.topic,
                &ty,
                Qos::SENSOR_DATA,
            ))?,
        ];
        Ok(Ros2Frames {
            queue,
            _subscription: subscription,
            _tokens: tokens,
            vehicle,
            camera: src.camera,
            info,
            topic: src.topic.clone(),
            seq: Default::default(),
            rejected: Default::default(),
        })
    }

    /// The grey image and capture stamp of one sample on `key`.
    fn decode(&self, key: &str, bytes: &[u8]) -> Result<(shoal_proto::GrayImage, u64), String> {
        use shoal_node::ros_image::{gray_of_compressed, gray_of_image};
        use shoal_proto::ros2::msgs::{CompressedImage, Image, COMPRESSED_IMAGE, IMAGE};
        let mut chunks = key.rsplit('/');
        let (hash, dds) = (chunks.next().unwrap_or(""), chunks.next().unwrap_or(""));
        let at = |e: shoal_proto::ros2::cdr::CdrError| format!("{key}: {e}");
        let (gray, stamp) = if dds == IMAGE.dds_name() && hash == IMAGE.hash {
            let img = Image::from_cdr(bytes).map_err(at)?;
            (gray_of_image(&self.topic, &img), img.header.stamp)
        } else if dds == COMPRESSED_IMAGE.dds_name() && hash == COMPRESSED_IMAGE.hash {
            let img = CompressedImage::from_cdr(bytes).map_err(at)?;
            (gray_of_compressed(&self.topic, &img), img.header.stamp)
        } else {
            return Err(format!(
                "{key}: not a sensor_msgs/msg/Image or CompressedImage of ROS 2 Jazzy"
            ));
        };
        let stamp_ns = stamp.to_ns().filter(|&t| t > 0).unwrap_or_else(|| {
            SystemTime::now()
                .duration_since(UNIX_EPOCH)
                .map_or(0, |d| d.as_nanos() as u64)
        });
        Ok((gray.map_err(|e| e.to_string())?, stamp_ns))
    }
}

impl shoal_node::vehicle::FrameInput for Ros2Frames {
    fn next(&self, timeout: Duration) -> Option<shoal_proto::CameraFrame> {
        let (key, bytes) = self.queue.pop_timeout(timeout).ok()?;
        match self.decode(&key, &bytes) {
            Ok((g, stamp_ns)) => {
                let mut info = self.info;
                info.model.width = g.width;
                info.model.height = g.height;
                Some(shoal_proto::CameraFrame {
                    vehicle: self.vehicle,
                    camera: self.camera,
                    seq: self.seq.fetch_add(1, Ordering::Relaxed),
                    stamp_ns,
                    info,
                    format: shoal_proto::PixelFormat::Mono8,
                    data: g.data,
                })
            }
            Err(e) => {
                let n = self.rejected.fetch_add(1, Ordering::Relaxed) + 1;
                if n.is_power_of_two() {
                    tracing::warn!("ROS 2 image #{n} refused: {e}");
                }
                None
            }
        }
    }
    fn dropped(&self) -> u64 {
        self.queue.dropped()
    }
    fn rejected(&self) -> u64 {
        self.rejected.load(Ordering::Relaxed)
    }
    fn messages_rejected(&self) -> u64 {
        0
    }
}
