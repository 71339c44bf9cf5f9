//! The versioned envelope around every payload (layout in `docs/wire.md`).
//!
//! ```text
//! offset size  field
//!      0    4  magic "SHOL"
//!      4    2  schema version, u16 little-endian (SCHEMA_VERSION)
//!      6    2  message kind, u16 little-endian (MessageKind)
//!      8    4  payload length in bytes, u32 little-endian
//!     12    n  bincode 2 payload: little-endian, fixed-width integers
//! ```
//!
//! Decoding never panics on arbitrary bytes: every failure is a
//! [`DecodeError`] naming what was wrong (see the property tests).

use crate::messages::{MessageKind, WireMessage};
use bincode::config::{Configuration, Fixint, Limit, LittleEndian};

pub const MAGIC: [u8; 4] = *b"SHOL";
/// Bumped on any incompatible change of a message layout.
pub const SCHEMA_VERSION: u16 = 5;
/// Oldest schema version still decoded, so logs written by older builds stay
/// readable: a message whose layout changed since is read through its old
/// layout ([`WireMessage::decode_older`]); today's builds only write
/// [`SCHEMA_VERSION`]. Version 5 changed `NodeStatus` and `CameraFrame` (its camera's lens model).
pub const OLDEST_READABLE_VERSION: u16 = 4;
pub const HEADER_LEN: usize = 12;
/// Largest payload accepted: a 4096x4096 RGB frame plus slack.
pub const MAX_PAYLOAD: usize = 64 << 20;

type WireConfig = Configuration<LittleEndian, Fixint, Limit<MAX_PAYLOAD>>;

fn config() -> WireConfig {
    bincode::config::standard()
        .with_little_endian()
        .with_fixed_int_encoding()
        .with_limit::<MAX_PAYLOAD>()
}

/// Why bytes could not be turned into a message.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum DecodeError {
    #[error("message too short: {len} bytes, the header alone is {HEADER_LEN}")]
    Truncated { len: usize },
    #[error("bad magic {found:02x?}: not a shoal message")]
    BadMagic { found: [u8; 4] },
    #[error("schema version {found} from peer, this build speaks {SCHEMA_VERSION} (and reads back to {OLDEST_READABLE_VERSION}): upgrade the older side")]
    VersionMismatch { found: u16 },
    #[error("unknown message kind {found}")]
    UnknownKind { found: u16 },
    #[error("expected a {expected:?} message, got {found:?}")]
    WrongKind {
        expected: MessageKind,
        found: MessageKind,
    },
    #[error("header says {declared} payload bytes, {actual} present")]
    LengthMismatch { declared: usize, actual: usize },
    #[error("payload of {len} bytes exceeds the {MAX_PAYLOAD}-byte limit")]
    Oversized { len: usize },
    #[error("{kind:?} payload is malformed: {reason}")]
    Malformed { kind: MessageKind, reason: String },
    #[error("{kind:?} payload has {extra} trailing bytes")]
    TrailingBytes { kind: MessageKind, extra: usize },
    #[error("{kind:?} field `{field}` is invalid: {reason}")]
    Invalid {
        kind: MessageKind,
        field: &'static str,
        reason: String,
    },
}

/// Why a message could not be encoded.
#[derive(Debug, thiserror::Error)]
pub enum EncodeError {
    #[error("{kind:?} payload is {len} bytes, over the {MAX_PAYLOAD}-byte limit")]
    Oversized { kind: MessageKind, len: usize },
    #[error("{kind:?} could not be serialized: {reason}")]
    Serialize { kind: MessageKind, reason: String },
}

/// The parsed fixed header of an envelope.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Header {
    pub version: u16,
    pub kind: MessageKind,
    pub payload_len: usize,
}

/// Encode a message into an envelope.
pub fn encode<M: WireMessage>(msg: &M) -> Result<Vec<u8>, EncodeError> {
    let payload =
        bincode::serde::encode_to_vec(msg, config()).map_err(|e| EncodeError::Serialize {
            kind: M::KIND,
            reason: e.to_string(),
        })?;
    if payload.len() > MAX_PAYLOAD {
        return Err(EncodeError::Oversized {
            kind: M::KIND,
            len: payload.len(),
        });
    }
    let mut out = Vec::with_capacity(HEADER_LEN + payload.len());
    out.extend_from_slice(&MAGIC);
    out.extend_from_slice(&SCHEMA_VERSION.to_le_bytes());
    out.extend_from_slice(&(M::KIND as u16).to_le_bytes());
    out.extend_from_slice(&(payload.len() as u32).to_le_bytes());
    out.extend_from_slice(&payload);
    Ok(out)
}

/// Parse and check the header; the payload is `bytes[HEADER_LEN..]`.
pub fn peek_header(bytes: &[u8]) -> Result<Header, DecodeError> {
    if bytes.len() < HEADER_LEN {
        return Err(DecodeError::Truncated { len: bytes.len() });
    }
    let magic = [bytes[0], bytes[1], bytes[2], bytes[3]];
    if magic != MAGIC {
        return Err(DecodeError::BadMagic { found: magic });
    }
    let version = u16::from_le_bytes([bytes[4], bytes[5]]);
    if !(OLDEST_READABLE_VERSION..=SCHEMA_VERSION).contains(&version) {
        return Err(DecodeError::VersionMismatch { found: version });
    }
    let raw_kind = u16::from_le_bytes([bytes[6], bytes[7]]);
    let kind =
        MessageKind::from_u16(raw_kind).ok_or(DecodeError::UnknownKind { found: raw_kind })?;
    let declared = u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize;
    if declared > MAX_PAYLOAD {
        return Err(DecodeError::Oversized { len: declared });
    }
    let actual = bytes.len() - HEADER_LEN;
    if declared != actual {
        return Err(DecodeError::LengthMismatch { declared, actual });
    }
    Ok(Header {
        version,
        kind,
        payload_len: declared,
    })
}

/// Decode an envelope holding a message of type `M`, then validate it.
pub fn decode<M: WireMessage>(bytes: &[u8]) -> Result<M, DecodeError> {
    let header = peek_header(bytes)?;
    if header.kind != M::KIND {
        return Err(DecodeError::WrongKind {
            expected: M::KIND,
            found: header.kind,
        });
    }
    let payload = &bytes[HEADER_LEN..];
    let older = if header.version < SCHEMA_VERSION {
        M::decode_older(header.version, payload)
    } else {
        None
    };
    let msg = match older {
        Some(decoded) => decoded?,
        None => decode_payload::<M>(M::KIND, payload)?,
    };
    msg.validate()
        .map_err(|(field, reason)| DecodeError::Invalid {
            kind: M::KIND,
            field,
            reason,
        })?;
    Ok(msg)
}

/// Decode a bincode payload of a `kind` message that must end exactly at the
/// end of `payload` (today's layout, or an older one's in
/// [`WireMessage::decode_older`]).
pub fn decode_payload<T: serde::de::DeserializeOwned>(
    kind: MessageKind,
    payload: &[u8],
) -> Result<T, DecodeError> {
    let (msg, used): (T, usize) =
        bincode::serde::decode_from_slice(payload, config()).map_err(|e| {
            DecodeError::Malformed {
                kind,
                reason: e.to_string(),
            }
        })?;
    if used != payload.len() {
        return Err(DecodeError::TrailingBytes {
            kind,
            extra: payload.len() - used,
        });
    }
    Ok(msg)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::messages::*;
    use crate::samples;
    use proptest::prelude::*;

    fn round_trip<M: WireMessage + PartialEq + std::fmt::Debug>(m: &M) {
        let bytes = encode(m).unwrap();
        let back: M = decode(&bytes).unwrap();
        assert_eq!(&back, m);
    }

    #[test]
    fn every_message_kind_round_trips() {
        round_trip(&samples::observation());
        round_trip(&samples::camera_frame());
        round_trip(&samples::fleet_map());
        round_trip(&samples::sim_truth());
        round_trip(&samples::node_status());
        round_trip(&samples::vehicle_command());
        // A NaN chi2 (not computed) survives the trip.
        let mut map = samples::fleet_map();
        map.edges[0].chi2 = f64::NAN;
        let back: FleetMap = decode(&encode(&map).unwrap()).unwrap();
        assert!(back.edges[0].chi2.is_nan());
    }

    #[test]
    fn header_errors_are_specific() {
        let bytes = encode(&samples::observation()).unwrap();
        assert_eq!(
            decode::<Observation>(&bytes[..5]),
            Err(DecodeError::Truncated { len: 5 })
        );
        let mut wrong_version = bytes.clone();
        wrong_version[4] = 9;
        assert_eq!(
            decode::<Observation>(&wrong_version),
            Err(DecodeError::VersionMismatch { found: 9 })
        );
        assert!(matches!(
            decode::<FleetMap>(&bytes),
            Err(DecodeError::WrongKind { .. })
        ));
        assert!(matches!(
            decode::<Observation>(&bytes[..bytes.len() - 1]),
            Err(DecodeError::LengthMismatch { .. })
        ));
    }

    /// A version-4 envelope: `bytes` with the version field set to 4 and the
    /// payload replaced by `payload`.
    fn as_version_4(bytes: &[u8], payload: &[u8]) -> Vec<u8> {
        let mut b = bytes[..HEADER_LEN].to_vec();
        b[4..6].copy_from_slice(&4u16.to_le_bytes());
        b[8..12].copy_from_slice(&(payload.len() as u32).to_le_bytes());
        b.extend_from_slice(payload);
        b
    }

    #[test]
    fn version_4_messages_still_decode() {
        // Unchanged layouts decode as today's.
        let obs = samples::observation();
        let bytes = encode(&obs).unwrap();
        let old = as_version_4(&bytes, &bytes[HEADER_LEN..]);
        assert_eq!(decode::<Observation>(&old), Ok(obs));
        // A version-4 NodeStatus lacks each camera's stamp source, missed
        // frames and reconnects (4 + 8 + 8 bytes at the end of the one
        // camera) and the clock (1 byte, None, at the very end).
        let mut status = samples::node_status();
        status.clock = None;
        let bytes = encode(&status).unwrap();
        let p = &bytes[HEADER_LEN..bytes.len() - 1];
        let tail = p.len() - 16; // observations_sent, messages_rejected
        let v4: Vec<u8> = [&p[..tail - 20], &p[tail..]].concat();
        let back = decode::<NodeStatus>(&as_version_4(&bytes, &v4)).unwrap();
        let mut expected = status.clone();
        expected.cameras[0].stamp_source = StampSource::Unknown;
        expected.cameras[0].frames_missed = 0;
        expected.cameras[0].reconnects = 0;
        assert_eq!(back, expected);
        // A version-4 CameraFrame: its lens is 5 plumb-bob coefficients with
        // no variant tag (the u32 after width, height, fx, fy, cx, cy).
        let frame = samples::camera_frame();
        assert!(matches!(
            frame.info.model.distortion,
            crate::camera::Distortion::PlumbBob(_)
        ));
        let frame_bytes = encode(&frame).unwrap();
        let fp = &frame_bytes[HEADER_LEN..];
        let tag = 4 + 1 + 8 + 8 + 2 * 4 + 4 * 8;
        let frame_v4: Vec<u8> = [&fp[..tag], &fp[tag + 4..]].concat();
        assert_eq!(
            decode::<CameraFrame>(&as_version_4(&frame_bytes, &frame_v4)),
            Ok(frame)
        );
        // Today's NodeStatus under a version-4 header is refused, not misread.
        assert!(matches!(
            decode::<NodeStatus>(&as_version_4(&bytes, &bytes[HEADER_LEN..])),
            Err(DecodeError::TrailingBytes { .. } | DecodeError::Malformed { .. })
        ));
        let mut v3 = bytes.clone();
        v3[4] = 3;
        assert_eq!(
            decode::<NodeStatus>(&v3),
            Err(DecodeError::VersionMismatch { found: 3 })
        );
    }

    #[test]
    fn nan_pose_is_rejected_with_field_name() {
        let mut obs = samples::observation();
        obs.observer_from_target.translation.vector.x = f64::NAN;
        let bytes = encode(&obs).unwrap();
        match decode::<Observation>(&bytes) {
            Err(DecodeError::Invalid { field, .. }) => assert_eq!(field, "observer_from_target"),
            other => panic!("expected Invalid, got {other:?}"),
        }
    }

    #[test]
    fn frame_of_wrong_size_is_rejected() {
        let mut f = samples::camera_frame();
        f.data.pop();
        let bytes = encode(&f).unwrap();
        assert!(matches!(
            decode::<CameraFrame>(&bytes),
            Err(DecodeError::Invalid { field: "data", .. })
        ));
    }

    proptest! {
        #![proptest_config(ProptestConfig { cases: 2000, ..ProptestConfig::default() })]

        #[test]
        fn arbitrary_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..512)) {
            let _ = decode::<Observation>(&bytes);
            let _ = decode::<FleetMap>(&bytes);
            let _ = decode::<CameraFrame>(&bytes);
            let _ = decode::<SimTruth>(&bytes);
            let _ = decode::<NodeStatus>(&bytes);
            let _ = decode::<VehicleCommand>(&bytes);
        }

        #[test]
        fn corrupted_valid_messages_never_panic(
            flips in proptest::collection::vec((any::<usize>(), any::<u8>()), 1..8),
            cut in any::<usize>(),
        ) {
            let mut bytes = encode(&samples::observation()).unwrap();
            for (at, v) in flips {
                let i = HEADER_LEN + at % (bytes.len() - HEADER_LEN);
                bytes[i] ^= v;
            }
            let _ = decode::<Observation>(&bytes);
            // Also with a consistent header but a truncated payload.
            let keep = HEADER_LEN + cut % (bytes.len() - HEADER_LEN);
            let mut cut_bytes = bytes[..keep].to_vec();
            let len = (keep - HEADER_LEN) as u32;
            cut_bytes[8..12].copy_from_slice(&len.to_le_bytes());
            let _ = decode::<Observation>(&cut_bytes);
        }
    }
}

#[cfg(test)]
mod layout_tests {
    //! Pins the byte layout documented in `docs/wire.md`, so the document cannot drift.
    use super::*;
    use crate::geometry::{pose_from_xyz_rpy, Cov6};
    use crate::messages::VehicleCommand;

    fn payload_of<T: serde::Serialize>(v: &T) -> Vec<u8> {
        bincode::serde::encode_to_vec(v, config()).unwrap()
    }

    #[test]
    fn pose_is_quaternion_xyzw_then_translation_as_seven_f64() {
        let p = pose_from_xyz_rpy([1.0, 2.0, 3.0], [0.0, 0.0, 0.5]);
        let b = payload_of(&p);
        assert_eq!(b.len(), 7 * 8);
        let f = |i: usize| f64::from_le_bytes(b[i * 8..i * 8 + 8].try_into().unwrap());
        let q = p.rotation.quaternion();
        assert_eq!([f(0), f(1), f(2), f(3)], [q.i, q.j, q.k, q.w]);
        assert_eq!([f(4), f(5), f(6)], [1.0, 2.0, 3.0]);
    }

    #[test]
    fn covariance_is_36_f64_column_major_without_length() {
        let mut c = Cov6::zeros();
        c[(1, 0)] = 7.0; // row 1, column 0: second value in column-major order
        let b = payload_of(&c);
        assert_eq!(b.len(), 36 * 8);
        assert_eq!(f64::from_le_bytes(b[8..16].try_into().unwrap()), 7.0);
    }

    #[test]
    fn envelope_header_and_a_small_message_byte_for_byte() {
        let cmd = VehicleCommand {
            vehicle: 15,
            stamp_ns: 2,
            velocity_body: [0.5, 0.0, -0.25],
            yaw_rate: 1.0,
        };
        let b = encode(&cmd).unwrap();
        assert_eq!(&b[0..4], b"SHOL");
        assert_eq!(u16::from_le_bytes([b[4], b[5]]), SCHEMA_VERSION);
        assert_eq!(u16::from_le_bytes([b[6], b[7]]), 6);
        assert_eq!(
            u32::from_le_bytes([b[8], b[9], b[10], b[11]]),
            4 + 8 + 24 + 8
        );
        assert_eq!(u32::from_le_bytes([b[12], b[13], b[14], b[15]]), 15);
        assert_eq!(u64::from_le_bytes(b[16..24].try_into().unwrap()), 2);
        assert_eq!(f64::from_le_bytes(b[24..32].try_into().unwrap()), 0.5);
        assert_eq!(f64::from_le_bytes(b[40..48].try_into().unwrap()), -0.25);
    }

    #[test]
    fn option_vec_string_and_enum_prefixes() {
        assert_eq!(payload_of(&Option::<u8>::None), vec![0]);
        assert_eq!(payload_of(&Some(3u8)), vec![1, 3]);
        assert_eq!(payload_of(&vec![9u8]), vec![1, 0, 0, 0, 0, 0, 0, 0, 9]);
        assert_eq!(
            payload_of(&"ab".to_string()),
            vec![2, 0, 0, 0, 0, 0, 0, 0, b'a', b'b']
        );
        assert_eq!(
            payload_of(&crate::CodeSet::AprilTag36h11),
            vec![14, 0, 0, 0]
        );
    }
}
