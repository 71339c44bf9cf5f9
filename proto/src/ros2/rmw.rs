//! `rmw_zenoh`'s conventions (ROS 2 Jazzy and later, `rmw_zenoh_cpp` ≥ 0.6):
//! the key a topic's samples are put on, the liveliness tokens its graph
//! cache discovers nodes and publishers by, the QoS string inside them and
//! the 33-byte attachment every sample carries. Strings and bytes only: the
//! Zenoh calls are `shoal_bus`'s.
//!
//! - data key: `<domain>/<topic without its leading and trailing '/'>/<dds type>/<type hash>`;
//! - node token: `@ros2_lv/<domain>/<zid>/<nid>/<nid>/NN/<enclave>/<namespace>/<node>`;
//! - publisher token: `@ros2_lv/<domain>/<zid>/<nid>/<id>/MP/<enclave>/<namespace>/<node>/<topic>/<dds type>/<type hash>/<qos>`,
//!   every `/` inside a name replaced by `%` and an empty name written `%`;
//! - attachment: sequence number (`i64` LE, from 1), source time (`i64` LE,
//!   ns since the epoch), `0x10`, the publisher's 16-byte GID.

use super::msgs::RosType;

/// The Zenoh key prefix of every `rmw_zenoh` liveliness token.
pub const ADMIN_SPACE: &str = "@ros2_lv";
/// Size of a sample's attachment.
pub const ATTACHMENT_LEN: usize = 33;

/// `/` → `%`; an empty name is `%`.
pub fn mangle(name: &str) -> String {
    if name.is_empty() {
        "%".into()
    } else {
        name.replace('/', "%")
    }
}

/// Is `name` a valid fully-qualified ROS 2 topic name (`/a/b_c`, tokens of
/// letters, digits and `_`, none starting with a digit, no `__`)?
pub fn valid_topic(name: &str) -> bool {
    let Some(rest) = name.strip_prefix('/') else {
        return false;
    };
    !rest.is_empty()
        && !rest.contains("__")
        && rest.split('/').all(|token| {
            !token.is_empty()
                && !token.starts_with(|c: char| c.is_ascii_digit())
                && token.chars().all(|c| c.is_ascii_alphanumeric() || c == '_')
        })
}

/// The data key of `topic` (fully qualified) carrying `ty` in `domain`.
pub fn topic_key(domain: u32, topic: &str, ty: &RosType) -> String {
    let stripped = topic.strip_prefix('/').unwrap_or(topic);
    let stripped = stripped.strip_suffix('/').unwrap_or(stripped);
    format!("{domain}/{stripped}/{}/{}", ty.dds_name(), ty.hash)
}

/// The few QoS settings shoal uses (`rmw_qos_profile_t`'s others stay at
/// their defaults: volatile, keep-last, infinite deadline/lifespan/lease,
/// automatic liveliness).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Qos {
    pub reliable: bool,
    pub depth: u32,
}

impl Qos {
    /// ROS 2's default profile: reliable, keep last 10.
    pub const DEFAULT: Qos = Qos {
        reliable: true,
        depth: 10,
    };
    /// tf2's publisher profile: reliable, keep last 100.
    pub const TF: Qos = Qos {
        reliable: true,
        depth: 100,
    };
    /// The sensor-data profile: best effort, keep last 5.
    pub const SENSOR_DATA: Qos = Qos {
        reliable: false,
        depth: 5,
    };

    /// `rmw_zenoh`'s QoS chunk: `<reliability>:<durability>:<history>,<depth>:<deadline>:<lifespan>:<liveliness>`,
    /// each component empty when it is `rmw_zenoh`'s default (reliable,
    /// volatile, keep-last, depth 42, infinite durations, automatic).
    pub fn keyexpr(&self) -> String {
        let reliability = if self.reliable { "" } else { "2" };
        let depth = if self.depth == 42 {
            String::new()
        } else {
            self.depth.to_string()
        };
        format!("{reliability}::,{depth}:,:,:,,")
    }
}

/// Entity kinds in a liveliness token.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum EntityKind {
    Publisher,
    Subscription,
}

impl EntityKind {
    fn code(self) -> &'static str {
        match self {
            EntityKind::Publisher => "MP",
            EntityKind::Subscription => "MS",
        }
    }
}

/// One ROS 2 node as `rmw_zenoh` announces it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RosNode {
    pub domain: u32,
    /// The Zenoh session's ID as Zenoh prints it (lowercase hex).
    pub zid: String,
    /// The node's entity ID within the session.
    pub id: u64,
    /// Namespace, `/` for none.
    pub namespace: String,
    pub name: String,
}

impl RosNode {
    /// The node's own liveliness token.
    pub fn token(&self) -> String {
        format!(
            "{ADMIN_SPACE}/{}/{}/{}/{}/NN/%/{}/{}",
            self.domain,
            self.zid,
            self.id,
            self.id,
            self.namespace_chunk(),
            mangle(&self.name)
        )
    }

    fn namespace_chunk(&self) -> String {
        if self.namespace == "/" {
            "%".into()
        } else {
            mangle(&self.namespace)
        }
    }

    /// The liveliness token of entity `id` (a publisher or subscription) on `topic`.
    pub fn endpoint_token(
        &self,
        kind: EntityKind,
        id: u64,
        topic: &str,
        ty: &RosType,
        qos: Qos,
    ) -> String {
        format!(
            "{ADMIN_SPACE}/{}/{}/{}/{id}/{}/%/{}/{}/{}/{}/{}/{}",
            self.domain,
            self.zid,
            self.id,
            kind.code(),
            self.namespace_chunk(),
            mangle(&self.name),
            mangle(topic),
            ty.dds_name(),
            ty.hash,
            qos.keyexpr()
        )
    }
}

/// A publisher's 16-byte GID from its liveliness token. (`rmw_zenoh_cpp`
/// takes XXH3-128 of the token; a GID is only compared for identity, so any
/// stable 128-bit digest of the token serves.)
pub fn gid_of(token: &str) -> [u8; 16] {
    let mut halves = [0xCBF2_9CE4_8422_2325u64, 0x8422_2325_CBF2_9CE4u64];
    for (i, h) in halves.iter_mut().enumerate() {
        for &b in token.as_bytes() {
            *h ^= u64::from(b) + i as u64;
            *h = h.wrapping_mul(0x0000_0100_0000_01B3);
        }
        let mut mix = crate::splitmix::SplitMix64::new(*h);
        *h = mix.next_u64();
    }
    let mut gid = [0u8; 16];
    gid[..8].copy_from_slice(&halves[0].to_le_bytes());
    gid[8..].copy_from_slice(&halves[1].to_le_bytes());
    gid
}

/// The attachment of a sample: what a ROS 2 subscription in `rmw_zenoh`
/// requires (it drops samples without one).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Attachment {
    /// Per publisher, from 1.
    pub sequence: i64,
    /// Publication time, ns since the epoch.
    pub source_time_ns: i64,
    pub gid: [u8; 16],
}

impl Attachment {
    pub fn to_bytes(&self) -> [u8; ATTACHMENT_LEN] {
        let mut b = [0u8; ATTACHMENT_LEN];
        b[..8].copy_from_slice(&self.sequence.to_le_bytes());
        b[8..16].copy_from_slice(&self.source_time_ns.to_le_bytes());
        b[16] = 16;
        b[17..].copy_from_slice(&self.gid);
        b
    }

    /// `None` unless `bytes` is exactly the 33-byte layout.
    pub fn parse(bytes: &[u8]) -> Option<Self> {
        if bytes.len() != ATTACHMENT_LEN || bytes[16] != 16 {
            return None;
        }
        let i64_at = |at: usize| {
            let mut a = [0u8; 8];
            a.copy_from_slice(&bytes[at..at + 8]);
            i64::from_le_bytes(a)
        };
        let mut gid = [0u8; 16];
        gid.copy_from_slice(&bytes[17..]);
        Some(Self {
            sequence: i64_at(0),
            source_time_ns: i64_at(8),
            gid,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ros2::msgs::RosType;

    const STRING: RosType = RosType {
        name: "std_msgs/msg/String",
        hash: "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18",
    };

    /// The examples in `rmw_zenoh`'s `docs/design.md` (Jazzy).
    #[test]
    fn keys_and_tokens_match_the_rmw_zenoh_design_examples() {
        assert_eq!(
            topic_key(0, "/chatter", &STRING),
            format!("0/chatter/std_msgs::msg::dds_::String_/{}", STRING.hash)
        );
        let talker = RosNode {
            domain: 0,
            zid: "8b20917502ee955ac4476e0266340d5c".into(),
            id: 0,
            namespace: "/".into(),
            name: "talker".into(),
        };
        assert_eq!(
            talker.token(),
            "@ros2_lv/0/8b20917502ee955ac4476e0266340d5c/0/0/NN/%/%/talker"
        );
        assert_eq!(
            talker.endpoint_token(
                EntityKind::Publisher,
                10,
                "/chatter",
                &STRING,
                Qos {
                    reliable: true,
                    depth: 7
                }
            ),
            format!(
                "@ros2_lv/0/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/std_msgs::msg::dds_::String_/{}/::,7:,:,:,,",
                STRING.hash
            )
        );
        assert_eq!(Qos::SENSOR_DATA.keyexpr(), "2::,5:,:,:,,");
        assert_eq!(
            Qos {
                reliable: true,
                depth: 42
            }
            .keyexpr(),
            "::,:,:,:,,"
        );
    }

    #[test]
    fn topic_names_are_checked() {
        for good in ["/tf", "/shoal/fleet_a/auv10/pose", "/a1/b_2"] {
            assert!(valid_topic(good), "{good}");
        }
        for bad in ["tf", "/", "/shoal/10/pose", "/a//b", "/a-b", "/a__b", "/a/"] {
            assert!(!valid_topic(bad), "{bad}");
        }
    }

    #[test]
    fn attachment_round_trips_and_odd_sizes_are_refused() {
        let a = Attachment {
            sequence: 1,
            source_time_ns: 1_700_000_000_000_000_000,
            gid: gid_of("@ros2_lv/0/abc/0/1/MP/%/%/n/%t/T_/RIHS01_x/::,10:,:,:,,"),
        };
        let b = a.to_bytes();
        assert_eq!(b[16], 16);
        assert_eq!(&b[..8], &1i64.to_le_bytes());
        assert_eq!(Attachment::parse(&b), Some(a));
        assert_eq!(Attachment::parse(&b[..32]), None);
        assert_ne!(gid_of("a"), gid_of("b"));
        assert_eq!(gid_of("a"), gid_of("a"));
    }
}
