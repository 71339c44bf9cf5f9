//! Fuzzing the wire decoder (issue #10, "hostile and broken input") with
//! proptest, for every message kind. `proto/src/codec.rs` already throws
//! arbitrary bytes and corrupted observations at the decoder; this adds the
//! other five kinds, headers that lie, payloads of random bytes under a
//! correct header, and the property that anything the decoder accepts is a
//! message it would itself have sent (it re-encodes to the same bytes and
//! passes validation), so nothing is misread.
//!
//! Cases per property: `SHOAL_FUZZ_CASES` (default 1000, well under a second).
//! Longer on demand: `SHOAL_FUZZ_CASES=100000 cargo test -p shoal-proto --test fuzz_wire`.

use proptest::prelude::*;
use proptest::test_runner::Config as ProptestConfig;
use shoal_proto::codec::{
    decode, encode, peek_header, DecodeError, HEADER_LEN, MAX_PAYLOAD, OLDEST_READABLE_VERSION,
    SCHEMA_VERSION,
};
use shoal_proto::compact::LinkPacket;
use shoal_proto::messages::*;
use shoal_proto::nav::NavState;
use shoal_proto::samples::*;

/// Failures print the minimal input; no regression files in the source tree.
fn fuzz_config(default_cases: u32) -> ProptestConfig {
    ProptestConfig {
        failure_persistence: None,
        ..ProptestConfig::with_cases(shoal_proto::samples::fuzz_cases(default_cases))
    }
}

/// Decode as `M`; an accepted message must be one this build would send:
/// valid, and re-encoding to exactly the bytes received.
fn accepted_means_canonical<M: WireMessage + std::fmt::Debug>(
    bytes: &[u8],
) -> Result<(), DecodeError> {
    let msg = decode::<M>(bytes)?;
    assert!(
        msg.validate().is_ok(),
        "decoder accepted an invalid {:?}: {msg:?}",
        M::KIND
    );
    let mut again = encode(&msg).expect("an accepted message re-encodes");
    // An older version's message is re-encoded in today's version; a layout
    // that changed since is pinned by the codec's own tests.
    if bytes.len() >= HEADER_LEN && bytes[4..6] != SCHEMA_VERSION.to_le_bytes() {
        if M::decode_older(
            u16::from_le_bytes([bytes[4], bytes[5]]),
            &bytes[HEADER_LEN..],
        )
        .is_some()
        {
            return Ok(());
        }
        again[4..6].copy_from_slice(&bytes[4..6]);
    }
    assert_eq!(
        again,
        bytes,
        "accepted {:?} does not re-encode to the bytes received",
        M::KIND
    );
    Ok(())
}

/// Decode `bytes` as every kind; returns how many kinds accepted it.
fn decode_as_every_kind(bytes: &[u8]) -> usize {
    [
        accepted_means_canonical::<Observation>(bytes).is_ok(),
        accepted_means_canonical::<FleetMap>(bytes).is_ok(),
        accepted_means_canonical::<CameraFrame>(bytes).is_ok(),
        accepted_means_canonical::<SimTruth>(bytes).is_ok(),
        accepted_means_canonical::<NodeStatus>(bytes).is_ok(),
        accepted_means_canonical::<VehicleCommand>(bytes).is_ok(),
        accepted_means_canonical::<NavState>(bytes).is_ok(),
        accepted_means_canonical::<LinkPacket>(bytes).is_ok(),
    ]
    .iter()
    .filter(|ok| **ok)
    .count()
}

fn with_header(version: u16, kind: u16, declared: u32, payload: &[u8]) -> Vec<u8> {
    let mut b = Vec::with_capacity(HEADER_LEN + payload.len());
    b.extend_from_slice(b"SHOL");
    b.extend_from_slice(&version.to_le_bytes());
    b.extend_from_slice(&kind.to_le_bytes());
    b.extend_from_slice(&declared.to_le_bytes());
    b.extend_from_slice(payload);
    b
}

#[test]
fn every_sample_is_accepted_by_exactly_its_own_kind() {
    for bytes in samples() {
        assert_eq!(decode_as_every_kind(&bytes), 1);
    }
}

#[test]
fn oversized_declared_length_is_refused_before_reading_the_payload() {
    let b = with_header(SCHEMA_VERSION, 1, (MAX_PAYLOAD + 1) as u32, &[0; 16]);
    assert_eq!(
        decode::<Observation>(&b),
        Err(DecodeError::Oversized {
            len: MAX_PAYLOAD + 1
        })
    );
    let b = with_header(SCHEMA_VERSION, 3, u32::MAX, &[]);
    assert!(matches!(
        decode::<CameraFrame>(&b),
        Err(DecodeError::Oversized { .. })
    ));
}

#[test]
fn vec_length_prefix_larger_than_the_message_is_refused_without_allocating() {
    // A CameraFrame whose `data` length prefix claims 2^60 bytes: bincode's
    // limit must refuse it before trying to allocate.
    let mut bytes = encode(&camera_frame()).unwrap();
    let data_len_at = bytes.len() - 32 - 8;
    assert_eq!(
        u64::from_le_bytes(bytes[data_len_at..data_len_at + 8].try_into().unwrap()),
        32
    );
    bytes[data_len_at..data_len_at + 8].copy_from_slice(&(1u64 << 60).to_le_bytes());
    assert!(matches!(
        decode::<CameraFrame>(&bytes),
        Err(DecodeError::Malformed { .. })
    ));
}

proptest! {
    #![proptest_config(fuzz_config(1000))]

    /// A correct header of any kind over random payload bytes.
    #[test]
    fn random_payload_under_a_valid_header_never_panics(
        kind in 1u16..=8,
        payload in proptest::collection::vec(any::<u8>(), 0..2048),
    ) {
        let b = with_header(SCHEMA_VERSION, kind, payload.len() as u32, &payload);
        prop_assert!(decode_as_every_kind(&b) <= 1);
    }

    /// Every kind's valid message with bytes flipped, cut, or extended.
    #[test]
    fn corrupted_messages_of_every_kind_are_rejected_or_read_exactly(
        which in 0usize..8,
        flips in proptest::collection::vec((any::<usize>(), any::<u8>()), 0..6),
        cut in proptest::option::of(any::<usize>()),
        extra in proptest::collection::vec(any::<u8>(), 0..8),
        fix_length in any::<bool>(),
    ) {
        let mut b = samples().swap_remove(which);
        for (at, v) in flips {
            let i = HEADER_LEN + at % (b.len() - HEADER_LEN);
            b[i] ^= v;
        }
        if let Some(c) = cut {
            b.truncate(HEADER_LEN + c % (b.len() - HEADER_LEN + 1));
        }
        b.extend_from_slice(&extra);
        if fix_length {
            let n = (b.len() - HEADER_LEN) as u32;
            b[8..12].copy_from_slice(&n.to_le_bytes());
        }
        prop_assert!(decode_as_every_kind(&b) <= 1);
    }

    /// Headers that lie: any version, kind or length in front of a valid payload.
    #[test]
    fn lying_headers_are_rejected_with_the_matching_error(
        which in 0usize..8,
        version in any::<u16>(),
        kind in any::<u16>(),
        declared in any::<u32>(),
    ) {
        let sample = samples().swap_remove(which);
        let payload = &sample[HEADER_LEN..];
        let b = with_header(version, kind, declared, payload);
        let accepted = decode_as_every_kind(&b);
        match peek_header(&b) {
            Ok(h) => {
                prop_assert!((OLDEST_READABLE_VERSION..=SCHEMA_VERSION).contains(&h.version));
                prop_assert_eq!(h.payload_len, payload.len());
                prop_assert!(accepted <= 1);
            }
            Err(DecodeError::VersionMismatch { found }) => {
                prop_assert!(!(OLDEST_READABLE_VERSION..=SCHEMA_VERSION).contains(&found));
                prop_assert_eq!(accepted, 0);
            }
            Err(DecodeError::UnknownKind { found }) => {
                prop_assert!(MessageKind::from_u16(found).is_none());
                prop_assert_eq!(accepted, 0);
            }
            Err(DecodeError::Oversized { len }) => {
                prop_assert!(len > MAX_PAYLOAD);
                prop_assert_eq!(accepted, 0);
            }
            Err(DecodeError::LengthMismatch { declared: d, actual }) => {
                prop_assert_eq!(d, declared as usize);
                prop_assert_eq!(actual, payload.len());
                prop_assert_eq!(accepted, 0);
            }
            Err(other) => prop_assert!(false, "unexpected header error {other:?}"),
        }
    }

    /// Observations with NaN / infinite / non-unit poses and absurd covariances
    /// are refused by validation, naming the field.
    #[test]
    fn non_finite_poses_and_absurd_covariances_name_the_field(
        slot in 0usize..7,
        bad in prop_oneof![
            Just(f64::NAN), Just(f64::INFINITY), Just(f64::NEG_INFINITY), Just(1e300), Just(-2.0)
        ],
        cov_scale in prop_oneof![Just(-1.0), Just(0.0), Just(1e7), Just(f64::INFINITY), Just(f64::NAN)],
        which in 0usize..3,
    ) {
        let mut obs = observation();
        let field = match which {
            0 => {
                if slot < 4 {
                    obs.observer_from_target.rotation.as_mut_unchecked().coords[slot] = bad;
                } else {
                    obs.observer_from_target.translation.vector[slot - 4] = bad;
                }
                "observer_from_target"
            }
            1 => {
                obs.covariance[(slot % 6, slot % 6)] *= cov_scale;
                "covariance"
            }
            _ => {
                obs.reprojection_rms_px = if bad == 1e300 { -1.0 } else { bad };
                "reprojection_rms_px"
            }
        };
        // Finite but far translations, and a 31 m standard deviation, are
        // well-formed on the wire: fusion judges those (`RejectReason::Invalid`
        // above its `max_std`), see tests/hostile_input.rs.
        let well_formed = (which == 0 && slot >= 4 && bad.is_finite())
            || (which == 1 && cov_scale == 1e7);
        let b = encode(&obs).unwrap();
        match decode::<Observation>(&b) {
            Err(DecodeError::Invalid { field: f, .. }) => {
                prop_assert!(!well_formed);
                prop_assert_eq!(f, field);
            }
            Ok(_) => {
                prop_assert!(well_formed, "accepted a bad {}: slot {}, value {}, scale {}", field, slot, bad, cov_scale);
                accepted_means_canonical::<Observation>(&b).unwrap();
            }
            Err(other) => prop_assert!(false, "expected Invalid {field}, got {other:?}"),
        }
    }

    /// Camera frames whose pixel buffer disagrees with width x height x channels.
    #[test]
    fn frames_of_the_wrong_size_or_format_are_refused(
        width in 0u32..40,
        height in 0u32..40,
        rgb in any::<bool>(),
        len in 0usize..5000,
    ) {
        let mut f = camera_frame();
        f.info.model.width = width;
        f.info.model.height = height;
        f.format = if rgb { PixelFormat::Rgb8 } else { PixelFormat::Mono8 };
        f.data = vec![7; len];
        let want = width as usize * height as usize * if rgb { 3 } else { 1 };
        let b = encode(&f).unwrap();
        match decode::<CameraFrame>(&b) {
            Ok(back) => {
                prop_assert!(width > 0 && height > 0 && len == want);
                prop_assert_eq!(back, f);
            }
            Err(DecodeError::Invalid { field, .. }) => {
                prop_assert!(width == 0 || height == 0 || len != want);
                prop_assert!(field == "data" || field == "info.model", "{}", field);
            }
            Err(other) => prop_assert!(false, "unexpected {other:?}"),
        }
    }
}
