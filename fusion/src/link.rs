//! Sending a vehicle's observations over a link of hundreds to thousands of
//! bits per second (an acoustic modem; issue #22).
//!
//! - [`TokenBucket`]: a bit budget per second with a burst allowance (the
//!   relay's bandwidth cap uses it too).
//! - [`LinkQueue`]: what to send next. Each (camera, marker) track's frames
//!   since it was last sent are kept; the track to go next is the one of
//!   highest priority — its newest frame's information (inverse
//!   translational standard deviation) times how long its vehicle pair has
//!   waited since it was last sent — so fresh, precise observations of pairs
//!   the others have not heard about go first, and no pair starves. What is
//!   sent is the track's **summary**: the information-weighted mean of its
//!   frames that agree with the newest one (χ² gate; a frame from before the
//!   vehicles moved is left out), stamped with the newest frame's time, with
//!   the summed information as its covariance. Each frame is summarized
//!   once (the track's frames are cleared when it is sent), so a receiver
//!   never counts a frame twice; one 53-byte packet then carries what
//!   several frames measured. Frames older than [`LinkQueue::max_age_ns`]
//!   are dropped (counted): the receivers' fusion window would refuse them.
//!
//! - [`NavSpanner`]: the vehicle's own navigation, gathered between the
//!   compact navigation spans ([`proto::compact::NavSpan`]) it sends every
//!   [`nav_span_period_ns`], so that the receivers can settle planar flips
//!   by both vehicles' gravity as a fusion fed in full does.
//!
//! All are plain state machines over injected time (nanoseconds), so the
//! same code runs in the relay, a vehicle's sender and the link evaluation.

use proto::compact::{NavSpan, MAX_SPAN_NS, NAV_SPAN_LEN};
use proto::geometry::{difference, perturb, Cov6};
use proto::nav::NavState;
use proto::Observation;
use std::collections::{BTreeMap, VecDeque};

/// One-way latency of an acoustic modem link (the evaluation's and the
/// link sender's assumption).
pub const MODEM_LATENCY_NS: u64 = 1_000_000_000;
/// Bytes a modem adds to every packet (sync, address, CRC).
pub const MODEM_OVERHEAD_BYTES: usize = 8;
/// A fusion fed over such a link keeps this much time in its window: what
/// crosses the link arrives 1 s old or more, so the default 2 s window would
/// keep little of it. Chosen from the link's latency and the modem's packet
/// time before any run; 3 s and 4 s were tried after (seeds 1–2, 4 s also
/// 11–15): better when manoeuvring, worse when holding station
/// (`docs/results.md`, "links").
pub const LINK_WINDOW_S: f64 = 8.0;

/// How long a packet of `payload` bytes occupies a modem of `rate_bps`
/// that adds `overhead_bytes` of framing, ns (rounded up).
pub fn airtime_ns(payload: usize, overhead_bytes: usize, rate_bps: f64) -> u64 {
    (((payload + overhead_bytes) * 8) as f64 / rate_bps * 1e9).ceil() as u64
}

/// Share of a modem's airtime the navigation spans take at most.
pub const NAV_SPAN_AIRTIME_SHARE: f64 = 0.15;
/// Shortest time between two navigation spans.
pub const MIN_NAV_SPAN_PERIOD_NS: u64 = 1_000_000_000;

/// How often a vehicle's link sender sends a navigation span on a modem of
/// `rate_bps` adding `overhead_bytes` a packet: rarely enough to leave the
/// observations 1 − [`NAV_SPAN_AIRTIME_SHARE`] of the airtime, at least every
/// second, and at most half the link window apart (a frame waits for the span
/// that covers it, then for the modem's latency, and the receivers keep what
/// crossed the link for [`LINK_WINDOW_S`]), which on the slowest links takes
/// more than the share: at 8 bytes of framing 4 s and 23 % at 300 bit/s,
/// 1.9 s and 15 % at 1 000, 1 s from ~1 900 bit/s on. Chosen from the
/// airtime before any run, not tuned.
pub fn nav_span_period_ns(rate_bps: f64, overhead_bytes: usize) -> u64 {
    let share = airtime_ns(NAV_SPAN_LEN, overhead_bytes, rate_bps) as f64 / NAV_SPAN_AIRTIME_SHARE;
    (share as u64).clamp(MIN_NAV_SPAN_PERIOD_NS, LINK_WINDOW_NS / 2)
}

const LINK_WINDOW_NS: u64 = (LINK_WINDOW_S * 1e9) as u64;

/// A vehicle's own navigation samples since the last span it sent
/// ([`NavSpan`]). Each span runs from the newest sample of the one before
/// (shared, so the spans meet and every instant between is bounded by samples
/// on both sides) to the newest sample offered; a gap in the nav longer than
/// `2 · period` starts the next span afresh (nothing is claimed over it).
#[derive(Debug, Clone)]
pub struct NavSpanner {
    period_ns: u64,
    vehicle: proto::VehicleId,
    /// The previous span's last sample.
    boundary: Option<NavState>,
    pending: Vec<NavState>,
    refused: u64,
}

impl NavSpanner {
    /// Spans of `vehicle`'s nav every `period_ns` (at least 1 ms, at most [`MAX_SPAN_NS`]).
    pub fn new(vehicle: proto::VehicleId, period_ns: u64) -> Self {
        Self {
            period_ns: period_ns.clamp(1_000_000, MAX_SPAN_NS / 2),
            vehicle,
            boundary: None,
            pending: Vec::new(),
            refused: 0,
        }
    }

    /// Take one sample; another vehicle's, or one not newer than the last
    /// taken, is refused and counted.
    pub fn offer(&mut self, nav: NavState) {
        let newest = self
            .pending
            .last()
            .or(self.boundary.as_ref())
            .map(|n| n.stamp_ns);
        if nav.vehicle != self.vehicle || newest.is_some_and(|t| nav.stamp_ns <= t) {
            self.refused += 1;
            return;
        }
        self.pending.push(nav);
    }

    /// Samples refused by [`NavSpanner::offer`].
    pub fn refused(&self) -> u64 {
        self.refused
    }

    /// The span to send now, once the samples since the last one cover a
    /// period (or the newest is a period old at `now_ns`).
    pub fn due(&mut self, now_ns: u64) -> Option<NavSpan> {
        let newest = self.pending.last()?.stamp_ns;
        let first = self.pending[0].stamp_ns;
        if self
            .boundary
            .is_some_and(|b| first - b.stamp_ns > 2 * self.period_ns)
        {
            self.boundary = None;
        }
        if newest - self.boundary.map_or(first, |b| b.stamp_ns) > MAX_SPAN_NS / 2 {
            // Not sent for a long while (a modem held by others): only the
            // newest period's samples are summarized.
            self.boundary = None;
            self.pending
                .retain(|n| n.stamp_ns + self.period_ns >= newest);
        }
        let first = self.pending[0].stamp_ns;
        let start = self.boundary.map_or(first, |b| b.stamp_ns);
        if newest - start < self.period_ns && now_ns.saturating_sub(start) < 2 * self.period_ns {
            return None;
        }
        let mut samples: Vec<NavState> = self.boundary.into_iter().collect();
        samples.append(&mut self.pending);
        self.boundary = samples.last().copied();
        NavSpan::summarize(&samples, start, newest)
    }
}

/// A token bucket of bits: `rate_bps` tokens a second, at most `burst_bits` saved.
#[derive(Debug, Clone)]
pub struct TokenBucket {
    rate_bps: f64,
    burst_bits: f64,
    tokens: f64,
    last_ns: u64,
}

impl TokenBucket {
    /// A full bucket at time `now_ns`. The rate must be positive and finite,
    /// the burst at least one bit.
    pub fn new(rate_bps: f64, burst_bits: f64, now_ns: u64) -> Result<Self, String> {
        if !(rate_bps.is_finite() && rate_bps > 0.0) {
            return Err(format!("rate {rate_bps} bit/s is not a positive number"));
        }
        if !(burst_bits.is_finite() && burst_bits >= 1.0) {
            return Err(format!("burst {burst_bits} bits is not at least one bit"));
        }
        Ok(Self {
            rate_bps,
            burst_bits,
            tokens: burst_bits,
            last_ns: now_ns,
        })
    }

    pub fn rate_bps(&self) -> f64 {
        self.rate_bps
    }

    fn refill(&mut self, now_ns: u64) {
        if now_ns > self.last_ns {
            let dt = (now_ns - self.last_ns) as f64 * 1e-9;
            self.tokens = (self.tokens + dt * self.rate_bps).min(self.burst_bits);
            self.last_ns = now_ns;
        }
    }

    /// Take `bits` at `now_ns` if the bucket holds them.
    pub fn try_take(&mut self, bits: f64, now_ns: u64) -> bool {
        self.refill(now_ns);
        if self.tokens >= bits {
            self.tokens -= bits;
            true
        } else {
            false
        }
    }

    /// How long after `now_ns` the bucket will hold `bits` (0 when it does;
    /// `None` when `bits` exceeds the burst and never will).
    pub fn wait_ns(&mut self, bits: f64, now_ns: u64) -> Option<u64> {
        if bits > self.burst_bits {
            return None;
        }
        self.refill(now_ns);
        let missing = (bits - self.tokens).max(0.0);
        Some((missing / self.rate_bps * 1e9).ceil() as u64)
    }
}

/// A track: one camera's view of one marker (code set by name: ordered keys
/// keep the choice among equal priorities deterministic).
type Track = (u8, &'static str, u32);
/// A vehicle pair as the link sees it: the marker seen (the observer is this vehicle).
type Pair = (&'static str, u32);

/// What a [`LinkQueue`] did with what it was offered.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct LinkQueueStats {
    pub offered: u64,
    pub sent: u64,
    /// Frames folded into a summary with others (or left out of it by the gate).
    pub superseded: u64,
    /// Frames left out of a summary because they disagreed with the newest.
    pub gated: u64,
    /// Older than the age limit when their turn came.
    pub expired: u64,
}

/// Each track's frames since it was sent; summaries sent highest priority first (module docs).
#[derive(Debug, Clone)]
pub struct LinkQueue {
    pending: BTreeMap<Track, VecDeque<Observation>>,
    last_sent: BTreeMap<Pair, u64>,
    /// Frames older than this (capture to sending) are dropped.
    pub max_age_ns: u64,
    stats: LinkQueueStats,
}

/// Priority of a pair never sent: as if last sent this long ago.
const NEVER_SENT_NS: u64 = 60_000_000_000;
/// Frames kept per track at most (the oldest go first).
const MAX_FRAMES_PER_TRACK: usize = 64;
/// χ²₆ at 99.9 %: a frame further than this from the newest (under their
/// summed covariances) is from another pose, not more of the same.
const SUMMARY_GATE: f64 = 22.46;

impl LinkQueue {
    pub fn new(max_age_ns: u64) -> Self {
        Self {
            pending: BTreeMap::new(),
            last_sent: BTreeMap::new(),
            max_age_ns,
            stats: LinkQueueStats::default(),
        }
    }

    pub fn stats(&self) -> LinkQueueStats {
        self.stats
    }

    /// Tracks with something to send.
    pub fn len(&self) -> usize {
        self.pending.len()
    }

    pub fn is_empty(&self) -> bool {
        self.pending.is_empty()
    }

    /// Queue a frame of its track (kept in capture order).
    pub fn offer(&mut self, obs: Observation) {
        self.stats.offered += 1;
        let track = (obs.camera, obs.codes.name(), obs.target_marker);
        let frames = self.pending.entry(track).or_default();
        let at = frames.partition_point(|o| o.stamp_ns <= obs.stamp_ns);
        frames.insert(at, obs);
        if frames.len() > MAX_FRAMES_PER_TRACK {
            frames.pop_front();
            self.stats.expired += 1;
        }
    }

    /// The summary to send at `now_ns`; its track's frames leave the queue.
    pub fn next(&mut self, now_ns: u64) -> Option<Observation> {
        let max_age = self.max_age_ns;
        let mut expired = 0u64;
        self.pending.retain(|_, frames| {
            let before = frames.len();
            frames.retain(|o| now_ns.saturating_sub(o.stamp_ns) <= max_age);
            expired += (before - frames.len()) as u64;
            !frames.is_empty()
        });
        self.stats.expired += expired;
        let (track, _) = self
            .pending
            .iter()
            .filter_map(|(t, f)| f.back().map(|o| (*t, self.priority(o, now_ns))))
            .max_by(|a, b| a.1.total_cmp(&b.1))?;
        let frames = self.pending.remove(&track)?;
        let (summary, folded, gated) = summarize(&frames)?;
        self.stats.superseded += folded;
        self.stats.gated += gated;
        self.last_sent
            .insert((summary.codes.name(), summary.target_marker), now_ns);
        self.stats.sent += 1;
        Some(summary)
    }

    /// Information (1 / translational σ, per metre) x the pair's wait (s).
    fn priority(&self, obs: &Observation, now_ns: u64) -> f64 {
        let waited = self
            .last_sent
            .get(&(obs.codes.name(), obs.target_marker))
            .map_or(NEVER_SENT_NS, |t| now_ns.saturating_sub(*t));
        let var_t = (0..3).map(|i| obs.covariance[(i, i)]).sum::<f64>();
        let info = 1.0 / var_t.max(1e-12).sqrt();
        info * (waited as f64 * 1e-9 + 0.1)
    }
}

/// The newest frame with every frame that agrees with it averaged in
/// (information-weighted, in the tangent space at the newest pose); also
/// how many frames were folded in and how many the gate left out.
fn summarize(frames: &VecDeque<Observation>) -> Option<(Observation, u64, u64)> {
    let newest = frames.back()?;
    let mut info_sum = Cov6::zeros();
    let mut weighted = nalgebra::Vector6::zeros();
    let (mut folded, mut gated) = (0u64, 0u64);
    for o in frames {
        let xi = difference(&o.observer_from_target, &newest.observer_from_target);
        let joint = o.covariance + newest.covariance;
        let is_newest = std::ptr::eq(o, newest);
        let agrees = is_newest
            || joint
                .try_inverse()
                .is_some_and(|inv| (xi.transpose() * inv * xi)[0] <= SUMMARY_GATE);
        let Some(info) = o.covariance.try_inverse().filter(|_| agrees) else {
            gated += 1;
            continue;
        };
        info_sum += info;
        weighted += info * xi;
        folded += u64::from(!is_newest);
    }
    let mut out = newest.clone();
    if let Some(cov) = info_sum.try_inverse() {
        let cov = (cov + cov.transpose()) * 0.5;
        if cov.cholesky().is_some() {
            out.observer_from_target = perturb(&newest.observer_from_target, &(cov * weighted));
            out.covariance = cov;
        }
    }
    Some((out, folded, gated))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_packet_holds_the_modem_for_its_bits_and_framing() {
        // 53 + 8 bytes at 1 000 bit/s: 488 ms; at 300 bit/s 1.627 s (rounded up).
        assert_eq!(airtime_ns(53, 8, 1000.0), 488_000_000);
        assert_eq!(airtime_ns(53, 8, 300.0), 1_626_666_667);
        assert_eq!(airtime_ns(66, 0, 1000.0), 528_000_000);
    }
    use proto::geometry::Cov6;
    use proto::{CodeSet, ImageQuality, Pose};

    fn obs(camera: u8, marker: u32, stamp_s: f64, std_m: f64) -> Observation {
        Observation {
            observer: 10,
            camera,
            codes: CodeSet::Shoal,
            target_marker: marker,
            target_vehicle: Some(marker),
            stamp_ns: (stamp_s * 1e9) as u64,
            frame_seq: 0,
            observer_from_target: Pose::identity(),
            covariance: Cov6::identity() * std_m * std_m,
            reprojection_rms_px: 0.2,
            alternative: None,
            corner_count: 12,
            corners_px: Vec::new(),
            quality: ImageQuality::default(),
            predicted: false,
        }
    }

    #[test]
    fn the_bucket_passes_its_rate_and_no_more() {
        let mut b = TokenBucket::new(1000.0, 500.0, 0).unwrap();
        let mut sent = 0.0;
        // 10 s in 1 ms steps, 424-bit packets (53 bytes).
        for ms in 0..10_000u64 {
            while b.try_take(424.0, ms * 1_000_000) {
                sent += 424.0;
            }
        }
        // The 500-bit burst plus 1 000 bit/s for 10 s, less what did not fill a packet.
        assert!(
            sent <= 500.0 + 10_000.0 && sent > 10_000.0 - 424.0,
            "{sent}"
        );
        assert_eq!(b.wait_ns(501.0, 0), None);
        assert!(TokenBucket::new(0.0, 10.0, 0).is_err());
        assert!(TokenBucket::new(f64::INFINITY, 10.0, 0).is_err());
        assert!(TokenBucket::new(100.0, 0.5, 0).is_err());
    }

    #[test]
    fn a_track_is_sent_as_one_summary_and_no_pair_starves() {
        let mut q = LinkQueue::new(5_000_000_000);
        // Track (0, 15): three frames of one pose, σ 1 cm each.
        for k in 0..3 {
            q.offer(obs(0, 15, 1.0 + k as f64 * 0.1, 0.01));
        }
        // A less precise observation of 17.
        q.offer(obs(1, 17, 1.2, 0.03));
        assert_eq!(q.len(), 2);
        let first = q.next(1_300_000_000).unwrap();
        assert_eq!((first.target_marker, first.stamp_ns), (15, 1_200_000_000));
        // Three frames' information: variance a third of one frame's.
        assert!(
            (first.covariance[(0, 0)] - 1e-4 / 3.0).abs() < 1e-9,
            "{}",
            first.covariance
        );
        assert_eq!(q.stats().superseded, 2);
        // 15 again, fresh and precise; but 17 has waited longer since last sent.
        q.offer(obs(0, 15, 1.4, 0.01));
        let second = q.next(1_500_000_000).unwrap();
        assert_eq!(second.target_marker, 17);
        // 15's new frame is sent alone: the earlier ones are not counted twice.
        let third = q.next(1_600_000_000).unwrap();
        assert!((third.covariance[(0, 0)] - 1e-4).abs() < 1e-9);
        // A frame older than the age limit is dropped, not sent.
        q.offer(obs(0, 15, 1.4, 0.01));
        assert!(q.next(7_000_000_000).is_none());
        assert_eq!(q.stats().expired, 1);
    }

    #[test]
    fn frames_from_before_a_move_are_left_out_of_the_summary() {
        let mut q = LinkQueue::new(5_000_000_000);
        let mut before = obs(0, 15, 1.0, 0.001);
        before.observer_from_target.translation.vector.x = 0.05; // 50 σ away
        q.offer(before);
        q.offer(obs(0, 15, 1.5, 0.001));
        let s = q.next(1_600_000_000).unwrap();
        assert_eq!(s.observer_from_target.translation.vector.x, 0.0);
        assert!((s.covariance[(0, 0)] - 1e-6).abs() < 1e-12);
        assert_eq!(q.stats().gated, 1);
    }

    fn nav(vehicle: u32, stamp_ns: u64, roll_rad: f64) -> NavState {
        NavState {
            vehicle,
            stamp_ns,
            depth: None,
            tilt: Some(proto::nav::Tilt {
                roll_rad,
                pitch_rad: 0.0,
                covariance: [[1e-6, 0.0], [0.0, 1e-6]],
            }),
            heading: None,
            velocity: None,
        }
    }

    #[test]
    fn nav_spans_meet_cover_a_period_each_and_skip_a_gap() {
        const S: u64 = 1_000_000_000;
        let mut sp = NavSpanner::new(7, 2 * S);
        let mut spans = Vec::new();
        // 10 Hz for 6.05 s, then nothing for 10 s, then 10 Hz again for 3 s.
        let stamps = (0..=60u64)
            .map(|k| k * S / 10)
            .chain((0..=30).map(|k| 16 * S + k * S / 10));
        for t in stamps {
            sp.offer(nav(7, t, 0.01 * (t as f64 * 1e-9).sin()));
            spans.extend(sp.due(t));
        }
        let ranges: Vec<(u64, u64)> = spans.iter().map(|s| (s.from_ns, s.to_ns)).collect();
        assert_eq!(
            ranges,
            vec![(0, 2 * S), (2 * S, 4 * S), (4 * S, 6 * S), (16 * S, 18 * S)],
            "{ranges:?}"
        );
        // The samples at 6.0–6.05 s wait for the next span; with nothing newer,
        // it goes once two periods have passed since its start.
        assert!(sp.due(18 * S + S / 2).is_none());
        let last = sp.due(22 * S).unwrap();
        assert_eq!((last.from_ns, last.to_ns), (18 * S, 19 * S));
        // Every span's roll bounds each sample it covers.
        for s in &spans {
            let t = s.tilt.unwrap();
            for k in (s.from_ns / (S / 10))..=(s.to_ns / (S / 10)) {
                let x = 0.01 * ((k * S / 10) as f64 * 1e-9).sin();
                assert!((x - t.roll_rad).abs() <= t.covariance[0][0].sqrt() + 1e-12);
            }
        }
        // Another vehicle's samples, and stale ones, are refused.
        sp.offer(nav(8, 30 * S, 0.0));
        sp.offer(nav(7, 10 * S, 0.0));
        assert_eq!(sp.refused(), 2);
    }

    #[test]
    fn the_nav_span_period_leaves_the_observations_most_of_the_airtime() {
        for rate in [300.0, 1000.0, 5000.0] {
            let p = nav_span_period_ns(rate, MODEM_OVERHEAD_BYTES);
            let share = airtime_ns(NAV_SPAN_LEN, MODEM_OVERHEAD_BYTES, rate) as f64 / p as f64;
            let cap = if rate < 450.0 {
                0.25
            } else {
                NAV_SPAN_AIRTIME_SHARE
            };
            assert!(share <= cap + 1e-9, "{rate}: {share}");
            assert!((MIN_NAV_SPAN_PERIOD_NS..=LINK_WINDOW_NS / 2).contains(&p));
        }
        assert_eq!(nav_span_period_ns(300.0, 8), LINK_WINDOW_NS / 2);
        assert_eq!(nav_span_period_ns(5000.0, 8), MIN_NAV_SPAN_PERIOD_NS);
        let p = nav_span_period_ns(1000.0, 8) as f64 * 1e-9;
        assert!((1.8..2.0).contains(&p), "{p}");
    }
}
