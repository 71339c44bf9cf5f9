//! A node whose camera is a ROS 2 image topic (`shoal node --source
//! ros2:TOPIC`, issue #20): a rendered frame of vehicle 15's port camera is
//! wrapped by Python `rosbags` (an independent CDR writer) as a raw `rgb8`
//! `sensor_msgs/msg/Image` and as a PNG `CompressedImage`. Both are put on
//! `rmw_zenoh`'s keys with the 33-byte attachment, and the node must detect the
//! neighbour in each, stamped with the header's time. A sample that is not
//! an image is counted as invalid and nothing else happens.

use shoal_bus::{client_of, free_port, Bus, Connect, Subscription};
use shoal_node::pipeline::PipelineParams;
use shoal_proto::messages::Observation;
use shoal_proto::ros2::msgs::{RosType, COMPRESSED_IMAGE, IMAGE};
use shoal_proto::ros2::rmw::{self, Attachment};
use shoal_services::node::{NodeConfig, Source};
use shoal_services::ros2::Ros2ImageSource;
use shoal_sim_bridge::render::{render_fleet_view, Renderer};
use shoal_sim_bridge::water::WaterPresets;
use shoal_sim_bridge::world::{Formation, SwarmWorld};
use std::process::Command;
use std::sync::Arc;
use std::time::{Duration, Instant};

const DOMAIN: u32 = 9;
const WRAP: &str = r#"
import sys
from rosbags.typesys import Stores, get_typestore
ts = get_typestore(Stores.ROS2_JAZZY)
Image = ts.types["sensor_msgs/msg/Image"]
CompressedImage = ts.types["sensor_msgs/msg/CompressedImage"]
Header = ts.types["std_msgs/msg/Header"]
Time = ts.types["builtin_interfaces/msg/Time"]
import numpy as np
kind, w, h, sec, src, dst = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4]), sys.argv[5], sys.argv[6]
data = open(src, "rb").read()
header = Header(stamp=Time(sec=sec, nanosec=250000000), frame_id="auv15/port_optical")
if kind == "raw":
    grey = np.frombuffer(data, dtype=np.uint8)
    rgb = np.repeat(grey, 3)
    msg = Image(header=header, height=h, width=w, encoding="rgb8", is_bigendian=0, step=3 * w, data=rgb)
    typename = "sensor_msgs/msg/Image"
else:
    msg = CompressedImage(header=header, format="png", data=np.frombuffer(data, dtype=np.uint8))
    typename = "sensor_msgs/msg/CompressedImage"
open(dst, "wb").write(bytes(ts.serialize_cdr(msg, typename)))
"#;

/// CDR bytes of an image message made by rosbags.
fn wrap(kind: &str, w: u32, h: u32, sec: i32, src: &std::path::Path) -> Vec<u8> {
    let dst = src.with_extension(format!("{kind}.cdr"));
    let out = Command::new("python3")
        .args(["-c", WRAP, kind])
        .args([w.to_string(), h.to_string(), sec.to_string()])
        .arg(src)
        .arg(&dst)
        .output()
        .expect("python3");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    std::fs::read(&dst).unwrap()
}

#[test]
fn a_node_reads_its_camera_from_a_ros2_image_topic() {
    let fleet = Arc::new(
        shoal_proto::config::Fleet::load(std::path::Path::new(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/configs/fleets/paper.toml"
        )))
        .unwrap(),
    );
    let camera = fleet
        .vehicle(15)
        .unwrap()
        .cameras
        .iter()
        .find(|c| c.name == "port")
        .unwrap()
        .index;
    let world = SwarmWorld::new(&fleet, Formation::Line, 1.75, 7).unwrap();
    let water = WaterPresets::builtin().get(0.5).unwrap();
    let frame = render_fleet_view(
        &mut Renderer::new(),
        &fleet,
        &world.truth(),
        15,
        camera,
        &water,
        0.0,
        0,
        7,
    )
    .unwrap();
    let seen = frame
        .visible
        .first()
        .expect("the port camera sees a neighbour")
        .target_vehicle;
    let dir = std::env::temp_dir().join(format!("shoal-ros2-camera-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let raw_path = dir.join("frame.gray");
    std::fs::write(&raw_path, &frame.image.data).unwrap();
    let png_path = dir.join("frame.png");
    let (w, h) = (frame.image.width, frame.image.height);
    image::save_buffer(
        &png_path,
        &frame.image.data,
        w,
        h,
        image::ExtendedColorType::L8,
    )
    .unwrap();
    let raw = wrap("raw", w, h, 100, &raw_path);
    let png = wrap("png", w, h, 200, &png_path);

    let port = free_port().unwrap();
    let _router = Bus::open(&Connect::Router { port }).unwrap();
    let bus = Bus::open(&client_of(port)).unwrap();
    let topic = "/auv15/port/image_raw";
    let node = shoal_services::node::spawn(
        &bus,
        NodeConfig {
            fleet: fleet.clone(),
            vehicle: 15,
            params: PipelineParams::default(),
            source: Source::Ros2(Ros2ImageSource {
                domain: DOMAIN,
                topic: topic.into(),
                camera,
            }),
            queue_capacity: 4,
            status_period: Duration::from_secs(1),
        },
    )
    .unwrap();
    let obs: Subscription<Observation> = bus.subscribe(&fleet.keys().observations(15), 64).unwrap();
    std::thread::sleep(Duration::from_millis(300));
    let put = |ty: &RosType, bytes: &[u8], seq: i64| {
        let p = bus
            .raw_publisher(rmw::topic_key(DOMAIN, topic, ty))
            .unwrap();
        let a = Attachment {
            sequence: seq,
            source_time_ns: 1,
            gid: rmw::gid_of(topic),
        };
        p.put(bytes.to_vec(), Some(a.to_bytes().to_vec())).unwrap();
    };
    put(&IMAGE, &raw, 1);
    put(&IMAGE, b"\x00\x01\x00\x00not an image", 2);
    put(&COMPRESSED_IMAGE, &png, 1);
    let mut stamps = Vec::new();
    let deadline = Instant::now() + Duration::from_secs(60);
    while stamps.len() < 2 && Instant::now() < deadline {
        if let Some(r) = obs.recv_timeout(Duration::from_millis(200)) {
            if r.msg.target_vehicle == Some(seen) && !stamps.contains(&r.msg.stamp_ns) {
                stamps.push(r.msg.stamp_ns);
            }
        }
    }
    stamps.sort_unstable();
    assert_eq!(
        stamps,
        vec![100_250_000_000, 200_250_000_000],
        "observations of vehicle {seen} at the two headers' stamps"
    );
    assert_eq!(
        node.stats().frames_invalid(),
        1,
        "the sample that is not an image"
    );
    node.stop();
    let _ = std::fs::remove_dir_all(&dir);
}
