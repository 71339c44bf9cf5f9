//! The compact observation: an [`Observation`] in 53 bytes (66 with the
//! planar flip) for links of hundreds to thousands of bits per second, such
//! as an acoustic modem (issue #22). The full message (bincode in the
//! envelope) is ~700 bytes: its corner list, image-quality figures and two
//! 6x6 covariances of `f64` are for the station and the log, not for fusion.
//!
//! Layout (version 1, little-endian), every field quantized:
//!
//! | bytes | field |
//! |---|---|
//! | 1 | version (`1`) |
//! | 1 | flags: bit 0 alternative present, bit 1 predicted; bits 2–3 the dropped quaternion component of the pose, bits 4–5 of the alternative |
//! | 2 | observer vehicle ID (`u16`) |
//! | 2 | target vehicle ID (`u16`, `0xFFFF` none) |
//! | 1 | camera index |
//! | 1 | code set (index in [`CodeSet::all`]) |
//! | 2 | marker ID |
//! | 6 | capture time, whole milliseconds (`u48`) |
//! | 2 | frame sequence number, low 16 bits |
//! | 6 | translation, 3 × `i16`, [`TRANSLATION_STEP_M`] (±32.7 m) |
//! | 6 | rotation, the three smallest quaternion components × `i16` |
//! | 6 | standard deviations, 6 × `u8` on a log scale, rounded up ([`std_from_code`]) |
//! | 15 | correlations, 15 × `i8`, ρ = v / 127 |
//! | 1 | reprojection RMS, `u8` log scale |
//! | 1 | corner count |
//! | 12 + 1 | alternative (when flagged): translation, rotation, its RMS; its covariance is the best one's |
//!
//! What is lost: the corner list and image quality (empty / zero after
//! decoding), the alternative's own covariance, sub-millimetre and
//! sub-1e-4 rad detail, frame sequence numbers above 16 bits. Standard
//! deviations are rounded *up* (at most one 7.5 % step), so a decoded
//! covariance never claims more certainty than the original.

use crate::geometry::{Cov6, Pose};
use crate::marker::CodeSet;
use crate::messages::{
    ImageQuality, MessageKind, Observation, PoseHypothesis, VehicleId, WireMessage,
};
use nalgebra::{Quaternion, Translation3, UnitQuaternion};

mod nav;
pub use nav::{
    decode_nav_span, encode_nav_span, NavSpan, ANGLE_STEP_RAD, DEPTH_STEP_M, MAX_SPAN_NS,
    NAV_SPAN_LEN, NAV_SPAN_TAG,
};

/// The version this module writes and reads.
pub const VERSION: u8 = 1;
/// Size of an observation without the planar flip.
pub const BASE_LEN: usize = 53;
/// Size with the planar flip.
pub const WITH_ALTERNATIVE_LEN: usize = BASE_LEN + 13;
/// Quantization step of a translation, metres.
pub const TRANSLATION_STEP_M: f64 = 0.001;
/// Standard deviations encodable: 10^-6 … 10^2 (metres or radians).
const LOG_STD_MIN: f64 = -6.0;
const LOG_STD_SPAN: f64 = 8.0;
/// Reprojection RMS encodable: 10^-3 … 10^2 px.
const LOG_RMS_MIN: f64 = -3.0;
const LOG_RMS_SPAN: f64 = 5.0;

/// Why an observation cannot be written compactly, or bytes cannot be read as one.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CompactError {
    #[error("compact link payload: {field} = {value} does not fit ({limit})")]
    OutOfRange {
        field: &'static str,
        value: String,
        limit: &'static str,
    },
    #[error("compact link payload: version {0} is not known (this build reads observations of version {VERSION} and navigation spans, tag 0x81)")]
    Version(u8),
    #[error("compact link payload: {got} bytes, expected {expected}")]
    Length { got: usize, expected: usize },
    #[error("compact link payload: {field}: {reason}")]
    Invalid { field: &'static str, reason: String },
}

fn out_of_range(field: &'static str, value: impl ToString, limit: &'static str) -> CompactError {
    CompactError::OutOfRange {
        field,
        value: value.to_string(),
        limit,
    }
}

/// Encode `obs` (see the module docs for what is kept).
pub fn encode(obs: &Observation) -> Result<Vec<u8>, CompactError> {
    let mut out = Vec::with_capacity(WITH_ALTERNATIVE_LEN);
    let observer = u16::try_from(obs.observer)
        .ok()
        .filter(|v| *v != u16::MAX)
        .ok_or_else(|| out_of_range("observer", obs.observer, "IDs 0..65534"))?;
    let target = match obs.target_vehicle {
        None => u16::MAX,
        Some(t) => u16::try_from(t)
            .ok()
            .filter(|v| *v != u16::MAX)
            .ok_or_else(|| out_of_range("target_vehicle", t, "IDs 0..65534"))?,
    };
    let marker = u16::try_from(obs.target_marker)
        .map_err(|_| out_of_range("target_marker", obs.target_marker, "IDs 0..65535"))?;
    let codes = CodeSet::all()
        .iter()
        .position(|c| *c == obs.codes)
        .expect("every code set is in CodeSet::all") as u8;
    let ms = obs.stamp_ns / 1_000_000;
    if ms >= 1 << 48 {
        return Err(out_of_range("stamp_ns", obs.stamp_ns, "2^48 ms"));
    }
    let (t, q, q_drop) = quantize_pose(&obs.observer_from_target, "observer_from_target")?;
    let mut flags = u8::from(obs.predicted) << 1 | q_drop << 2;
    let alt = match &obs.alternative {
        Some(a) => {
            let (at, aq, a_drop) = quantize_pose(&a.observer_from_target, "alternative")?;
            flags |= 1 | a_drop << 4;
            Some((at, aq, a.reprojection_rms_px))
        }
        None => None,
    };
    out.push(VERSION);
    out.push(flags);
    out.extend_from_slice(&observer.to_le_bytes());
    out.extend_from_slice(&target.to_le_bytes());
    out.push(obs.camera);
    out.push(codes);
    out.extend_from_slice(&marker.to_le_bytes());
    out.extend_from_slice(&ms.to_le_bytes()[..6]);
    out.extend_from_slice(&(obs.frame_seq as u16).to_le_bytes());
    push_i16s(&mut out, &t);
    push_i16s(&mut out, &q);
    push_covariance(&mut out, &obs.covariance)?;
    out.push(log_code(obs.reprojection_rms_px, LOG_RMS_MIN, LOG_RMS_SPAN));
    out.push(obs.corner_count);
    if let Some((at, aq, rms)) = alt {
        push_i16s(&mut out, &at);
        push_i16s(&mut out, &aq);
        out.push(log_code(rms, LOG_RMS_MIN, LOG_RMS_SPAN));
    }
    debug_assert_eq!(out.len(), encoded_len(obs.alternative.is_some()));
    Ok(out)
}

/// The encoded size with or without the planar flip.
pub fn encoded_len(with_alternative: bool) -> usize {
    if with_alternative {
        WITH_ALTERNATIVE_LEN
    } else {
        BASE_LEN
    }
}

/// Decode bytes written by [`encode`]; the result passes `Observation::validate`.
pub fn decode(bytes: &[u8]) -> Result<Observation, CompactError> {
    let version = *bytes.first().ok_or(CompactError::Length {
        got: 0,
        expected: BASE_LEN,
    })?;
    if version != VERSION {
        return Err(CompactError::Version(version));
    }
    let flags = *bytes.get(1).ok_or(CompactError::Length {
        got: bytes.len(),
        expected: BASE_LEN,
    })?;
    let has_alt = flags & 1 != 0;
    let expected = encoded_len(has_alt);
    if bytes.len() != expected {
        return Err(CompactError::Length {
            got: bytes.len(),
            expected,
        });
    }
    if flags & 0xC0 != 0 {
        return Err(CompactError::Invalid {
            field: "flags",
            reason: format!("unknown bits in {flags:#04x}"),
        });
    }
    let u16_at = |i: usize| u16::from_le_bytes([bytes[i], bytes[i + 1]]);
    let observer = u32::from(u16_at(2));
    let target = match u16_at(4) {
        u16::MAX => None,
        t => Some(u32::from(t)),
    };
    let codes = *CodeSet::all()
        .get(bytes[7] as usize)
        .ok_or_else(|| CompactError::Invalid {
            field: "codes",
            reason: format!("code set index {} is not known", bytes[7]),
        })?;
    let mut ms = [0u8; 8];
    ms[..6].copy_from_slice(&bytes[10..16]);
    let stamp_ns = u64::from_le_bytes(ms)
        .checked_mul(1_000_000)
        .ok_or_else(|| CompactError::Invalid {
            field: "stamp",
            reason: format!(
                "{} ms is past the end of u64 nanoseconds",
                u64::from_le_bytes(ms)
            ),
        })?;
    let pose = dequantize_pose(
        &i16s(&bytes[18..24]),
        &i16s(&bytes[24..30]),
        (flags >> 2) & 3,
    );
    let covariance = read_covariance(&bytes[30..51])?;
    let alternative = has_alt.then(|| PoseHypothesis {
        observer_from_target: dequantize_pose(
            &i16s(&bytes[53..59]),
            &i16s(&bytes[59..65]),
            (flags >> 4) & 3,
        ),
        covariance,
        reprojection_rms_px: from_log_code(bytes[65], LOG_RMS_MIN, LOG_RMS_SPAN),
    });
    Ok(Observation {
        observer,
        camera: bytes[6],
        codes,
        target_marker: u32::from(u16_at(8)),
        target_vehicle: target,
        stamp_ns,
        frame_seq: u64::from(u16_at(16)),
        observer_from_target: pose,
        covariance,
        reprojection_rms_px: from_log_code(bytes[51], LOG_RMS_MIN, LOG_RMS_SPAN),
        alternative,
        corner_count: bytes[52],
        corners_px: Vec::new(),
        quality: ImageQuality::default(),
        predicted: flags & 2 != 0,
    })
}

fn push_i16s(out: &mut Vec<u8>, v: &[i16; 3]) {
    for x in v {
        out.extend_from_slice(&x.to_le_bytes());
    }
}

fn i16s(b: &[u8]) -> [i16; 3] {
    [0, 1, 2].map(|i| i16::from_le_bytes([b[2 * i], b[2 * i + 1]]))
}

/// Translation in [`TRANSLATION_STEP_M`] and the quaternion's three smallest
/// components scaled by `32767 · √2` (each is at most 1/√2), with which one was dropped.
fn quantize_pose(p: &Pose, field: &'static str) -> Result<([i16; 3], [i16; 3], u8), CompactError> {
    let t = p.translation.vector;
    let mut tq = [0i16; 3];
    for (o, v) in tq.iter_mut().zip(t.iter()) {
        let steps = (v / TRANSLATION_STEP_M).round();
        if steps.is_nan() || steps.abs() > f64::from(i16::MAX) {
            return Err(out_of_range(field, format!("{v} m"), "±32.767 m"));
        }
        *o = steps as i16;
    }
    let c = p.rotation.coords; // [x, y, z, w]
    let drop = (0..4)
        .max_by(|a, b| c[*a].abs().total_cmp(&c[*b].abs()))
        .expect("four components");
    // The dropped component is made positive (q and -q are one rotation).
    let sign = if c[drop] < 0.0 { -1.0 } else { 1.0 };
    let scale = f64::from(i16::MAX) * std::f64::consts::SQRT_2;
    let mut qq = [0i16; 3];
    for (o, i) in qq.iter_mut().zip((0..4).filter(|i| *i != drop)) {
        *o = (sign * c[i] * scale)
            .round()
            .clamp(-f64::from(i16::MAX), f64::from(i16::MAX)) as i16;
    }
    Ok((tq, qq, drop as u8))
}

fn dequantize_pose(t: &[i16; 3], q: &[i16; 3], drop: u8) -> Pose {
    let scale = f64::from(i16::MAX) * std::f64::consts::SQRT_2;
    let small: Vec<f64> = q.iter().map(|v| f64::from(*v) / scale).collect();
    let rest = (1.0 - small.iter().map(|v| v * v).sum::<f64>())
        .max(0.0)
        .sqrt();
    let mut c = [0.0; 4];
    let mut k = 0;
    for (i, slot) in c.iter_mut().enumerate() {
        if i == drop as usize {
            *slot = rest;
        } else {
            *slot = small[k];
            k += 1;
        }
    }
    let rotation = UnitQuaternion::from_quaternion(Quaternion::new(c[3], c[0], c[1], c[2]));
    Pose::from_parts(
        Translation3::new(
            f64::from(t[0]) * TRANSLATION_STEP_M,
            f64::from(t[1]) * TRANSLATION_STEP_M,
            f64::from(t[2]) * TRANSLATION_STEP_M,
        ),
        rotation,
    )
}

/// `v` on a 255-step log scale from `10^min` to `10^(min + span)`, rounded up.
fn log_code(v: f64, min: f64, span: f64) -> u8 {
    if v.is_nan() || v <= 0.0 {
        return 0;
    }
    ((v.log10() - min) / span * 255.0).ceil().clamp(0.0, 255.0) as u8
}

fn from_log_code(c: u8, min: f64, span: f64) -> f64 {
    10f64.powf(min + f64::from(c) / 255.0 * span)
}

/// The standard deviation a code stands for (metres or radians).
pub fn std_from_code(c: u8) -> f64 {
    from_log_code(c, LOG_STD_MIN, LOG_STD_SPAN)
}

fn push_covariance(out: &mut Vec<u8>, cov: &Cov6) -> Result<(), CompactError> {
    let mut std = [0.0; 6];
    for (i, s) in std.iter_mut().enumerate() {
        let var = cov[(i, i)];
        if !(var.is_finite() && var > 0.0) {
            return Err(out_of_range("covariance", var, "finite positive variances"));
        }
        *s = var.sqrt();
        if *s > 10f64.powf(LOG_STD_MIN + LOG_STD_SPAN) {
            return Err(out_of_range("covariance", format!("σ{i} = {s}"), "σ ≤ 100"));
        }
        out.push(log_code(*s, LOG_STD_MIN, LOG_STD_SPAN));
    }
    for i in 0..6 {
        for j in i + 1..6 {
            let rho = (cov[(i, j)] / (std[i] * std[j])).clamp(-1.0, 1.0);
            out.push((rho * 127.0).round() as i8 as u8);
        }
    }
    Ok(())
}

/// The covariance of 6 log-coded deviations and 15 correlations. Rounding
/// can leave a nearly singular correlation matrix indefinite: the
/// correlations are then shrunk towards zero until it is positive definite
/// (which only adds uncertainty).
fn read_covariance(b: &[u8]) -> Result<Cov6, CompactError> {
    let std: Vec<f64> = b[..6].iter().map(|c| std_from_code(*c)).collect();
    let mut rho = Cov6::identity();
    let mut k = 6;
    for i in 0..6 {
        for j in i + 1..6 {
            let r = f64::from(b[k] as i8) / 127.0;
            if b[k] as i8 == i8::MIN {
                return Err(CompactError::Invalid {
                    field: "covariance",
                    reason: "correlation code -128 is not written".into(),
                });
            }
            rho[(i, j)] = r;
            rho[(j, i)] = r;
            k += 1;
        }
    }
    let mut shrink = 1.0;
    for _ in 0..40 {
        let mut r = rho * shrink;
        for i in 0..6 {
            r[(i, i)] = 1.0;
        }
        if r.cholesky().is_some() {
            let s = Cov6::from_diagonal(&nalgebra::Vector6::from_iterator(std.iter().copied()));
            return Ok(s * r * s);
        }
        shrink *= 0.9;
    }
    Err(CompactError::Invalid {
        field: "covariance",
        reason: "the correlations are not a correlation matrix".into(),
    })
}

/// What a vehicle's link sender (`shoal link`) publishes on
/// `shoal/<fleet>/<vehicle>/link`: one compact observation or one compact
/// navigation span of the sender's own, `payload` being exactly the bytes the
/// modem carries (the first byte tells which: an observation's version, `1`,
/// or [`NAV_SPAN_TAG`]). The envelope around it is for the local bus and the
/// log; a modem driver sends `payload` and, on the far side, publishes it
/// again under the sender's key.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct LinkPacket {
    /// The vehicle whose modem sent it (the observation's observer, the span's vehicle).
    pub sender: VehicleId,
    /// Per sender, counting up from 0 when its link sender starts (gaps are packets lost).
    pub seq: u32,
    /// One observation or navigation span in this module's encodings.
    pub payload: Vec<u8>,
}

/// What a [`LinkPacket`] carries.
#[derive(Debug, Clone, PartialEq)]
pub enum LinkContent {
    /// Boxed: ~800 bytes against the span's ~130.
    Observation(Box<Observation>),
    Nav(NavSpan),
}

impl LinkContent {
    /// The capture time of the observation, the end of the span.
    pub fn stamp_ns(&self) -> u64 {
        match self {
            LinkContent::Observation(o) => o.stamp_ns,
            LinkContent::Nav(n) => n.to_ns,
        }
    }
}

impl LinkPacket {
    /// What it carries, checked against its sender.
    pub fn content(&self) -> Result<LinkContent, CompactError> {
        if self.payload.first() == Some(&NAV_SPAN_TAG) {
            let span = decode_nav_span(&self.payload)?;
            if span.vehicle != self.sender {
                return Err(CompactError::Invalid {
                    field: "vehicle",
                    reason: format!(
                        "navigation of vehicle {} in a packet sent by vehicle {}",
                        span.vehicle, self.sender
                    ),
                });
            }
            return Ok(LinkContent::Nav(span));
        }
        let obs = decode(&self.payload)?;
        if obs.observer != self.sender {
            return Err(CompactError::Invalid {
                field: "observer",
                reason: format!(
                    "observation of vehicle {} in a packet sent by vehicle {}",
                    obs.observer, self.sender
                ),
            });
        }
        Ok(LinkContent::Observation(Box::new(obs)))
    }
}

impl WireMessage for LinkPacket {
    const KIND: MessageKind = MessageKind::LinkPacket;
    fn validate(&self) -> Result<(), (&'static str, String)> {
        self.content()
            .map(|_| ())
            .map_err(|e| ("payload", e.to_string()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::difference;
    use crate::messages::WireMessage;
    use nalgebra::Vector3;

    pub(crate) fn sample(alt: bool) -> Observation {
        let pose = Pose::from_parts(
            Translation3::new(1.7512, -0.2034, 0.0521),
            UnitQuaternion::from_euler_angles(0.1, -0.3, 2.9),
        );
        let a = nalgebra::Matrix6::<f64>::from_fn(|i, j| ((i * 7 + j * 3) % 5) as f64 * 0.1);
        let covariance = (a * a.transpose() + Cov6::identity()) * 1e-5;
        Observation {
            observer: 10,
            camera: 3,
            codes: CodeSet::Shoal,
            target_marker: 15,
            target_vehicle: Some(15),
            stamp_ns: 123_456_789_000,
            frame_seq: 77,
            observer_from_target: pose,
            covariance,
            reprojection_rms_px: 0.21,
            alternative: alt.then(|| PoseHypothesis {
                observer_from_target: Pose::from_parts(
                    Translation3::new(1.74, -0.21, 0.06),
                    UnitQuaternion::from_axis_angle(&Vector3::z_axis(), -0.4),
                ),
                covariance,
                reprojection_rms_px: 0.35,
            }),
            corner_count: 12,
            corners_px: vec![[1.0, 2.0]; 12],
            quality: ImageQuality::default(),
            predicted: false,
        }
    }

    #[test]
    fn round_trip_keeps_what_fusion_uses_within_its_quantization() {
        for alt in [false, true] {
            let o = sample(alt);
            let bytes = encode(&o).unwrap();
            assert_eq!(bytes.len(), if alt { 66 } else { 53 });
            let d = decode(&bytes).unwrap();
            d.validate().unwrap();
            assert_eq!(
                (
                    d.observer,
                    d.camera,
                    d.codes,
                    d.target_marker,
                    d.target_vehicle
                ),
                (10, 3, CodeSet::Shoal, 15, Some(15))
            );
            assert_eq!(
                (d.stamp_ns, d.frame_seq, d.corner_count),
                (123_456_000_000, 77, 12)
            );
            let e = difference(&d.observer_from_target, &o.observer_from_target);
            assert!(e.fixed_rows::<3>(0).norm() <= 0.5e-3 * 3f64.sqrt(), "{e}");
            assert!(e.fixed_rows::<3>(3).norm() < 1e-4, "{e}");
            for i in 0..6 {
                let (a, b) = (d.covariance[(i, i)].sqrt(), o.covariance[(i, i)].sqrt());
                assert!(a >= b * 0.999 && a <= b * 1.08, "σ{i}: {a} vs {b}");
            }
            assert!((d.reprojection_rms_px / o.reprojection_rms_px - 1.0).abs() < 0.05);
            assert_eq!(d.alternative.is_some(), alt);
            if let (Some(da), Some(oa)) = (&d.alternative, &o.alternative) {
                let e = difference(&da.observer_from_target, &oa.observer_from_target);
                assert!(e.norm() < 1e-3, "{e}");
            }
        }
    }

    #[test]
    fn every_quaternion_branch_round_trips() {
        // Rotations whose largest component is each of x, y, z, w, with either sign.
        for axis in [Vector3::x_axis(), Vector3::y_axis(), Vector3::z_axis()] {
            for angle in [-3.1, -2.5, 0.0, 0.4, 2.9, std::f64::consts::PI] {
                let mut o = sample(false);
                o.observer_from_target.rotation = UnitQuaternion::from_axis_angle(&axis, angle);
                let d = decode(&encode(&o).unwrap()).unwrap();
                let e = difference(&d.observer_from_target, &o.observer_from_target);
                assert!(e.fixed_rows::<3>(3).norm() < 1e-4, "{angle}: {e}");
            }
        }
    }

    #[test]
    fn what_does_not_fit_is_an_error_naming_the_field() {
        let mut o = sample(false);
        o.observer_from_target.translation.vector.x = 40.0;
        let e = encode(&o).unwrap_err().to_string();
        assert!(
            e.contains("observer_from_target") && e.contains("32.767"),
            "{e}"
        );
        let mut o = sample(false);
        o.observer = 70_000;
        assert!(encode(&o).unwrap_err().to_string().contains("observer"));
        let mut o = sample(false);
        o.covariance[(2, 2)] = f64::NAN;
        assert!(encode(&o).unwrap_err().to_string().contains("covariance"));
    }

    #[test]
    fn damaged_bytes_are_errors_or_valid_observations() {
        let bytes = encode(&sample(true)).unwrap();
        assert_eq!(
            decode(&bytes[..20]).unwrap_err(),
            CompactError::Length {
                got: 20,
                expected: 66
            }
        );
        let mut v2 = bytes.clone();
        v2[0] = 2;
        assert_eq!(decode(&v2).unwrap_err(), CompactError::Version(2));
        // Every byte flipped to every value: never a panic; what decodes validates.
        for i in 0..bytes.len() {
            for v in 0..=255u8 {
                let mut b = bytes.clone();
                b[i] = v;
                if let Ok(o) = decode(&b) {
                    o.validate()
                        .unwrap_or_else(|e| panic!("byte {i} = {v}: {e:?}"));
                }
            }
        }
    }
}
