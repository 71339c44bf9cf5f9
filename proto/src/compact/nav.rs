//! The compact navigation span: what a vehicle's own navigation held over an
//! interval, in 27 bytes, for the same acoustic-rate links as the compact
//! observation (issue #16: fusion over a link settles planar flips by
//! gravity only when both vehicles' roll and pitch cross it).
//!
//! A vehicle's nav runs at tens of hertz; a 1 000 bit/s modem carries about
//! one packet a second. So the link sender does not forward samples: it sends,
//! every few seconds, one span covering the time since its last one. Each part
//! (depth, roll/pitch, heading) is the mean of the span's samples, its variance
//! the mean of theirs plus the square of the largest deviation from the mean
//! seen in the span (per axis), so the span claims no more than held at *every*
//! instant in it. A receiver may then use it for any frame captured within the
//! span ([`NavSpan::state_at`]). Spans follow each other without gaps, so every
//! frame of a vehicle that sends nav is covered once its next span arrives.
//!
//! Layout (little-endian), every field quantized, standard deviations
//! rounded up:
//!
//! | bytes | field |
//! |---|---|
//! | 1 | tag [`NAV_SPAN_TAG`] (`0x81`: navigation span, version 1; an observation's first byte is its version, `1`) |
//! | 1 | flags: bit 0 depth, bit 1 roll/pitch, bit 2 heading present |
//! | 2 | vehicle ID (`u16`) |
//! | 6 | start of the span, whole milliseconds (`u48`, rounded down) |
//! | 2 | length of the span, milliseconds (`u16`, rounded up; at most 65.535 s) |
//! | 4 | depth, `i32` millimetres |
//! | 1 | its standard deviation, log scale as the observation's |
//! | 4 | roll, pitch, `i16` × 10⁻⁴ rad |
//! | 3 | their standard deviations (log scale) and correlation (`i8`, ρ = v / 127) |
//! | 2 | heading, `i16` × 10⁻⁴ rad |
//! | 1 | its standard deviation (log scale) |
//!
//! Absent parts are written as zeros and ignored. Velocity is not carried:
//! odometry between-factors over a link would need every increment, which no
//! acoustic budget holds.

use super::{from_log_code, log_code, out_of_range, CompactError, LOG_STD_MIN, LOG_STD_SPAN};
use crate::geometry::wrap_angle;
use crate::messages::{VehicleId, WireMessage};
use crate::nav::{Depth, Heading, NavState, Tilt};
use std::f64::consts::{FRAC_PI_2, PI};

/// First byte of a compact navigation span.
pub const NAV_SPAN_TAG: u8 = 0x81;
/// Its size.
pub const NAV_SPAN_LEN: usize = 27;
/// Quantization step of roll, pitch and heading, radians.
pub const ANGLE_STEP_RAD: f64 = 1e-4;
/// Quantization step of depth, metres.
pub const DEPTH_STEP_M: f64 = 0.001;
/// Longest span the layout holds.
pub const MAX_SPAN_NS: u64 = 65_535_000_000;

/// What a vehicle's navigation held from `from_ns` to `to_ns` (see the module docs).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NavSpan {
    pub vehicle: VehicleId,
    pub from_ns: u64,
    pub to_ns: u64,
    pub depth: Option<Depth>,
    pub tilt: Option<Tilt>,
    pub heading: Option<Heading>,
}

/// Largest |x − mean| and the mean of `xs` (not empty).
fn mean_and_deviation(xs: impl Iterator<Item = f64> + Clone) -> (f64, f64) {
    let n = xs.clone().count() as f64;
    let mean = xs.clone().sum::<f64>() / n;
    (mean, xs.map(|x| (x - mean).abs()).fold(0.0, f64::max))
}

impl NavSpan {
    /// The span of `samples` (one vehicle's, any order) from `from_ns` to
    /// `to_ns`: a part is summarized when every sample has it. `None` when
    /// there is no sample, or the samples are not all of one vehicle.
    pub fn summarize(samples: &[NavState], from_ns: u64, to_ns: u64) -> Option<NavSpan> {
        let first = samples.first()?;
        if samples.iter().any(|s| s.vehicle != first.vehicle) {
            return None;
        }
        let depth = samples
            .iter()
            .map(|s| s.depth)
            .collect::<Option<Vec<Depth>>>()
            .map(|d| {
                let (mean, dev) = mean_and_deviation(d.iter().map(|x| x.depth_m));
                let var = d.iter().map(|x| x.std_m * x.std_m).sum::<f64>() / d.len() as f64;
                Depth {
                    depth_m: mean,
                    std_m: (var + dev * dev).sqrt(),
                }
            });
        let tilt = samples
            .iter()
            .map(|s| s.tilt)
            .collect::<Option<Vec<Tilt>>>()
            .map(|t| {
                let (roll, dr) = mean_and_deviation(t.iter().map(|x| x.roll_rad));
                let (pitch, dp) = mean_and_deviation(t.iter().map(|x| x.pitch_rad));
                let n = t.len() as f64;
                let mut c = [[0.0; 2]; 2];
                for x in &t {
                    for (i, row) in c.iter_mut().enumerate() {
                        for (j, v) in row.iter_mut().enumerate() {
                            *v += x.covariance[i][j] / n;
                        }
                    }
                }
                c[0][0] += dr * dr;
                c[1][1] += dp * dp;
                Tilt {
                    roll_rad: roll,
                    pitch_rad: pitch,
                    covariance: c,
                }
            });
        let heading = samples
            .iter()
            .map(|s| s.heading)
            .collect::<Option<Vec<Heading>>>()
            .map(|h| {
                let (s, c) = h.iter().fold((0.0, 0.0), |(s, c), x| {
                    (s + x.yaw_rad.sin(), c + x.yaw_rad.cos())
                });
                let mean = s.atan2(c);
                let dev = h
                    .iter()
                    .map(|x| wrap_angle(x.yaw_rad - mean).abs())
                    .fold(0.0, f64::max);
                let var = h.iter().map(|x| x.std_rad * x.std_rad).sum::<f64>() / h.len() as f64;
                Heading {
                    yaw_rad: mean,
                    std_rad: (var + dev * dev).sqrt(),
                }
            });
        Some(NavSpan {
            vehicle: first.vehicle,
            from_ns: from_ns.min(to_ns),
            to_ns: to_ns.max(from_ns),
            depth,
            tilt,
            heading,
        })
    }

    /// The vehicle's nav at `stamp_ns` as this span states it (no velocity).
    pub fn state_at(&self, stamp_ns: u64) -> NavState {
        NavState {
            vehicle: self.vehicle,
            stamp_ns,
            depth: self.depth,
            tilt: self.tilt,
            heading: self.heading,
            velocity: None,
        }
    }

    /// The span's own checks (ordered, not longer than the layout holds) and
    /// those of a [`NavState`] with its parts.
    pub fn validate(&self) -> Result<(), (&'static str, String)> {
        if self.to_ns < self.from_ns {
            return Err((
                "to_ns",
                format!("{} ns is before from_ns {} ns", self.to_ns, self.from_ns),
            ));
        }
        if self.to_ns - self.from_ns > MAX_SPAN_NS {
            return Err((
                "to_ns",
                format!(
                    "the span is {} ms long, above {} ms",
                    (self.to_ns - self.from_ns) / 1_000_000,
                    MAX_SPAN_NS / 1_000_000
                ),
            ));
        }
        self.state_at(self.from_ns).validate()
    }
}

fn angle_code(v: f64, field: &'static str) -> Result<i16, CompactError> {
    let steps = (v / ANGLE_STEP_RAD).round();
    if !steps.is_finite() || steps.abs() > f64::from(i16::MAX) {
        return Err(out_of_range(field, v, "±3.2767 rad"));
    }
    Ok(steps as i16)
}

fn std_code(v: f64, field: &'static str) -> Result<u8, CompactError> {
    if !(v.is_finite() && v > 0.0 && v <= 10f64.powf(LOG_STD_MIN + LOG_STD_SPAN)) {
        return Err(out_of_range(field, v, "a standard deviation in (0, 100]"));
    }
    Ok(log_code(v, LOG_STD_MIN, LOG_STD_SPAN))
}

/// Encode `span` (see the module docs); a span that does not validate is an error naming its field.
pub fn encode_nav_span(span: &NavSpan) -> Result<Vec<u8>, CompactError> {
    span.validate()
        .map_err(|(field, why)| CompactError::Invalid { field, reason: why })?;
    let vehicle = u16::try_from(span.vehicle)
        .ok()
        .filter(|v| *v != u16::MAX)
        .ok_or_else(|| out_of_range("vehicle", span.vehicle, "IDs 0..65534"))?;
    let from_ms = span.from_ns / 1_000_000;
    if from_ms >= 1 << 48 {
        return Err(out_of_range("from_ns", span.from_ns, "2^48 ms"));
    }
    // Rounded up, so the decoded span covers at least the one encoded
    // (validate bounds the length below the field's end).
    let len_ms = (span.to_ns.div_ceil(1_000_000) - from_ms).min(u64::from(u16::MAX)) as u16;
    let mut out = Vec::with_capacity(NAV_SPAN_LEN);
    let flags = u8::from(span.depth.is_some())
        | u8::from(span.tilt.is_some()) << 1
        | u8::from(span.heading.is_some()) << 2;
    out.push(NAV_SPAN_TAG);
    out.push(flags);
    out.extend_from_slice(&vehicle.to_le_bytes());
    out.extend_from_slice(&from_ms.to_le_bytes()[..6]);
    out.extend_from_slice(&len_ms.to_le_bytes());
    match span.depth {
        Some(d) => {
            // Validated: within DEPTH_RANGE_M, so within i32 millimetres.
            out.extend_from_slice(&((d.depth_m / DEPTH_STEP_M).round() as i32).to_le_bytes());
            out.push(std_code(d.std_m, "depth.std_m")?);
        }
        None => out.extend_from_slice(&[0; 5]),
    }
    match span.tilt {
        Some(t) => {
            out.extend_from_slice(&angle_code(t.roll_rad, "tilt.roll_rad")?.to_le_bytes());
            out.extend_from_slice(&angle_code(t.pitch_rad, "tilt.pitch_rad")?.to_le_bytes());
            let [[a, b], [_, d]] = t.covariance;
            let (sr, sp) = (a.sqrt(), d.sqrt());
            out.push(std_code(sr, "tilt.covariance")?);
            out.push(std_code(sp, "tilt.covariance")?);
            let rho = (b / (sr * sp)).clamp(-1.0, 1.0);
            // Shrunk towards zero when rounding, which only adds uncertainty,
            // and at most 126 / 127, so that the decoded matrix stays positive definite.
            out.push((rho * 127.0).trunc().clamp(-126.0, 126.0) as i8 as u8);
        }
        None => out.extend_from_slice(&[0; 7]),
    }
    match span.heading {
        Some(h) => {
            out.extend_from_slice(&angle_code(h.yaw_rad, "heading.yaw_rad")?.to_le_bytes());
            out.push(std_code(h.std_rad, "heading.std_rad")?);
        }
        None => out.extend_from_slice(&[0; 3]),
    }
    debug_assert_eq!(out.len(), NAV_SPAN_LEN);
    Ok(out)
}

/// Decode bytes written by [`encode_nav_span`]; the result validates.
pub fn decode_nav_span(bytes: &[u8]) -> Result<NavSpan, CompactError> {
    if bytes.len() != NAV_SPAN_LEN {
        return Err(CompactError::Length {
            got: bytes.len(),
            expected: NAV_SPAN_LEN,
        });
    }
    if bytes[0] != NAV_SPAN_TAG {
        return Err(CompactError::Invalid {
            field: "tag",
            reason: format!("{:#04x} is not a navigation span", bytes[0]),
        });
    }
    let flags = bytes[1];
    if flags & !7 != 0 {
        return Err(CompactError::Invalid {
            field: "flags",
            reason: format!("unknown bits in {flags:#04x}"),
        });
    }
    let i16_at = |i: usize| f64::from(i16::from_le_bytes([bytes[i], bytes[i + 1]]));
    let mut ms = [0u8; 8];
    ms[..6].copy_from_slice(&bytes[4..10]);
    let from_ms = u64::from_le_bytes(ms);
    let len_ms = u64::from(u16::from_le_bytes([bytes[10], bytes[11]]));
    let from_ns = from_ms
        .checked_mul(1_000_000)
        .and_then(|f| Some((f, (from_ms + len_ms).checked_mul(1_000_000)?)))
        .ok_or_else(|| CompactError::Invalid {
            field: "from",
            reason: format!("{from_ms} ms is past the end of u64 nanoseconds"),
        })?;
    let std = |c: u8| from_log_code(c, LOG_STD_MIN, LOG_STD_SPAN);
    let depth = (flags & 1 != 0).then(|| Depth {
        depth_m: f64::from(i32::from_le_bytes([
            bytes[12], bytes[13], bytes[14], bytes[15],
        ])) * DEPTH_STEP_M,
        std_m: std(bytes[16]),
    });
    let tilt = (flags & 2 != 0).then(|| {
        let (sr, sp) = (std(bytes[21]), std(bytes[22]));
        let rho = f64::from(bytes[23] as i8) / 127.0;
        Tilt {
            // A step's rounding may carry ±π (±π/2) just past itself.
            roll_rad: (i16_at(17) * ANGLE_STEP_RAD).clamp(-PI, PI),
            pitch_rad: (i16_at(19) * ANGLE_STEP_RAD).clamp(-FRAC_PI_2, FRAC_PI_2),
            covariance: [[sr * sr, rho * sr * sp], [rho * sr * sp, sp * sp]],
        }
    });
    let heading = (flags & 4 != 0).then(|| Heading {
        yaw_rad: (i16_at(24) * ANGLE_STEP_RAD).clamp(-PI, PI),
        std_rad: std(bytes[26]),
    });
    let span = NavSpan {
        vehicle: VehicleId::from(u16::from_le_bytes([bytes[2], bytes[3]])),
        from_ns: from_ns.0,
        to_ns: from_ns.1,
        depth,
        tilt,
        heading,
    };
    span.validate()
        .map_err(|(field, why)| CompactError::Invalid { field, reason: why })?;
    Ok(span)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::compact::{LinkContent, LinkPacket};

    /// 2 s of 10 Hz nav of vehicle 15: rolling ±2° and heaving ±5 cm on a 1.3 s cycle.
    fn samples() -> Vec<NavState> {
        (0..20)
            .map(|k| {
                let t = k as f64 * 0.1;
                let w = (t * std::f64::consts::TAU / 1.3).sin();
                NavState {
                    vehicle: 15,
                    stamp_ns: 40_000_000_000 + k * 100_000_000,
                    depth: Some(Depth {
                        depth_m: 4.2 + 0.05 * w,
                        std_m: 0.01,
                    }),
                    tilt: Some(Tilt {
                        roll_rad: 0.05 + 2f64.to_radians() * w,
                        pitch_rad: -0.02,
                        covariance: [[3e-6, 1e-6], [1e-6, 3e-6]],
                    }),
                    heading: Some(Heading {
                        // Across ±π: the mean is near π, not near 0.
                        yaw_rad: wrap_angle(PI - 0.01 + 0.001 * k as f64),
                        std_rad: 0.01,
                    }),
                    velocity: None,
                }
            })
            .collect()
    }

    #[test]
    fn a_span_states_what_held_at_every_sample_in_it() {
        let s = samples();
        let span = NavSpan::summarize(&s, 40_000_000_000, 42_000_000_000).unwrap();
        span.validate().unwrap();
        let (d, t, h) = (
            span.depth.unwrap(),
            span.tilt.unwrap(),
            span.heading.unwrap(),
        );
        // Means; the deviations of a ±2° roll and ±5 cm heave are in the σ.
        let depths: Vec<f64> = s.iter().map(|x| x.depth.unwrap().depth_m).collect();
        let mean = depths.iter().sum::<f64>() / 20.0;
        let dev = depths.iter().map(|x| (x - mean).abs()).fold(0.0, f64::max);
        assert!((d.depth_m - mean).abs() < 1e-12, "{d:?}");
        assert!((d.std_m - (1e-4 + dev * dev).sqrt()).abs() < 1e-12, "{d:?}");
        assert!((t.roll_rad - 0.05).abs() < 0.5f64.to_radians(), "{t:?}");
        assert!((wrap_angle(h.yaw_rad - PI) - 0.0).abs() < 0.01, "{h:?}");
        for x in &s {
            let (xd, xt) = (x.depth.unwrap(), x.tilt.unwrap());
            assert!((xd.depth_m - d.depth_m).abs() <= d.std_m, "{xd:?} vs {d:?}");
            assert!(
                (xt.roll_rad - t.roll_rad).abs() <= t.covariance[0][0].sqrt(),
                "{xt:?} vs {t:?}"
            );
            assert!(wrap_angle(x.heading.unwrap().yaw_rad - h.yaw_rad).abs() <= h.std_rad);
        }
        // Where nothing moved, the samples' own σ.
        assert!((t.covariance[1][1] - 3e-6).abs() < 1e-12);
        assert!(d.std_m < 0.075 && t.covariance[0][0].sqrt() < 2.6f64.to_radians());
        // Any part a sample lacks is left out; other vehicles' samples are refused.
        let mut partial = s.clone();
        partial[3].heading = None;
        let p = NavSpan::summarize(&partial, 0, 1).unwrap();
        assert!(p.heading.is_none() && p.tilt.is_some() && p.depth.is_some());
        let mut mixed = s.clone();
        mixed[0].vehicle = 10;
        assert_eq!(NavSpan::summarize(&mixed, 0, 1), None);
        assert_eq!(NavSpan::summarize(&[], 0, 1), None);
    }

    #[test]
    fn a_span_round_trips_within_its_quantization_and_never_claims_more() {
        let span = NavSpan::summarize(&samples(), 40_000_000_400, 42_000_000_600).unwrap();
        let bytes = encode_nav_span(&span).unwrap();
        assert_eq!(bytes.len(), NAV_SPAN_LEN);
        let back = decode_nav_span(&bytes).unwrap();
        assert_eq!(back.vehicle, 15);
        // The decoded span covers the encoded one, by under a millisecond each side.
        assert!(back.from_ns <= span.from_ns && span.from_ns - back.from_ns < 1_000_000);
        assert!(back.to_ns >= span.to_ns && back.to_ns - span.to_ns < 1_000_000);
        let (a, b) = (back.depth.unwrap(), span.depth.unwrap());
        assert!((a.depth_m - b.depth_m).abs() <= DEPTH_STEP_M / 2.0 + 1e-12);
        assert!(a.std_m >= b.std_m && a.std_m <= b.std_m * 1.08);
        let (a, b) = (back.tilt.unwrap(), span.tilt.unwrap());
        assert!((a.roll_rad - b.roll_rad).abs() <= ANGLE_STEP_RAD / 2.0 + 1e-12);
        assert!((a.pitch_rad - b.pitch_rad).abs() <= ANGLE_STEP_RAD / 2.0 + 1e-12);
        for i in 0..2 {
            let (va, vb) = (a.covariance[i][i], b.covariance[i][i]);
            assert!(va >= vb && va <= vb * 1.08 * 1.08, "{i}: {va} vs {vb}");
        }
        let rho = |c: [[f64; 2]; 2]| c[0][1] / (c[0][0] * c[1][1]).sqrt();
        assert!(rho(a.covariance).abs() <= rho(b.covariance).abs() + 1e-12);
        assert!((rho(a.covariance) - rho(b.covariance)).abs() < 1.0 / 127.0);
        let (a, b) = (back.heading.unwrap(), span.heading.unwrap());
        assert!(wrap_angle(a.yaw_rad - b.yaw_rad).abs() <= ANGLE_STEP_RAD / 2.0 + 1e-12);
        assert!(a.std_rad >= b.std_rad && a.std_rad <= b.std_rad * 1.08);
        // A span without parts round-trips as one.
        let bare = NavSpan {
            depth: None,
            tilt: None,
            heading: None,
            ..span
        };
        let back = decode_nav_span(&encode_nav_span(&bare).unwrap()).unwrap();
        assert_eq!((back.depth, back.tilt, back.heading), (None, None, None));
        // Roll at π stays within ±π when its step rounds past it.
        let mut edge = span;
        edge.tilt.as_mut().unwrap().roll_rad = PI;
        let back = decode_nav_span(&encode_nav_span(&edge).unwrap()).unwrap();
        assert!(back.tilt.unwrap().roll_rad <= PI && back.validate().is_ok());
    }

    #[test]
    fn what_does_not_fit_or_is_not_a_span_is_an_error_naming_it() {
        let span = NavSpan::summarize(&samples(), 0, 1_000).unwrap();
        let mut bad = span;
        bad.tilt.as_mut().unwrap().roll_rad = f64::NAN;
        let e = encode_nav_span(&bad).unwrap_err().to_string();
        assert!(e.contains("tilt.roll_rad"), "{e}");
        let mut long = span;
        long.to_ns = long.from_ns + MAX_SPAN_NS + 1;
        let e = encode_nav_span(&long).unwrap_err().to_string();
        assert!(e.contains("to_ns") && e.contains("65535 ms"), "{e}");
        let mut far = span;
        far.vehicle = 70_000;
        assert!(encode_nav_span(&far)
            .unwrap_err()
            .to_string()
            .contains("vehicle"));
        let bytes = encode_nav_span(&span).unwrap();
        assert_eq!(
            decode_nav_span(&bytes[..10]).unwrap_err(),
            CompactError::Length {
                got: 10,
                expected: NAV_SPAN_LEN
            }
        );
        let mut tag = bytes.clone();
        tag[0] = 1;
        assert!(decode_nav_span(&tag)
            .unwrap_err()
            .to_string()
            .contains("tag"));
        // Every byte set to every value: never a panic; what decodes validates.
        for i in 0..bytes.len() {
            for v in 0..=255u8 {
                let mut b = bytes.clone();
                b[i] = v;
                if let Ok(s) = decode_nav_span(&b) {
                    s.validate()
                        .unwrap_or_else(|e| panic!("byte {i} = {v}: {e:?}"));
                }
            }
        }
    }

    #[test]
    fn a_link_packet_carries_a_span_of_its_sender_only() {
        let span = NavSpan::summarize(&samples(), 0, 1_000).unwrap();
        let packet = LinkPacket {
            sender: 15,
            seq: 0,
            payload: encode_nav_span(&span).unwrap(),
        };
        packet.validate().unwrap();
        match packet.content().unwrap() {
            LinkContent::Nav(n) => assert_eq!(n.vehicle, 15),
            other => panic!("{other:?}"),
        }
        let forged = LinkPacket {
            sender: 10,
            ..packet
        };
        let (field, why) = forged.validate().unwrap_err();
        assert_eq!(field, "payload");
        assert!(
            why.contains("vehicle 15") && why.contains("vehicle 10"),
            "{why}"
        );
    }
}
