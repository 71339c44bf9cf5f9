//! `links`: decentralized fusion of the paper's three vehicles across
//! acoustic-rate links (issue #22). Each vehicle runs its own fusion on its
//! own observations and on what the others send it over a link of 300,
//! 1 000 or 5 000 bit/s per vehicle, ~1 s latency and 10 % packet loss;
//! the result is compared, every second, with the full-rate map (one fusion
//! fed every observation at once, no link).
//!
//! Two ways of using the link:
//! - **compact**: [`shoal_proto::compact`] observations (53–66 bytes) from a
//!   [`shoal_fusion::link::LinkQueue`] (newest per track, most informative
//!   and longest-waiting pair first);
//! - **compact + nav**: the same, and every vehicle's own navigation
//!   (simulated sensors, `sim_bridge::nav` defaults: depth, IMU roll/pitch,
//!   compass, 10 Hz) as compact navigation spans
//!   ([`shoal_fusion::link::NavSpanner`], one every
//!   [`shoal_fusion::link::nav_span_period_ns`]) ahead of the next
//!   observation; each vehicle's fusion also takes its own nav in full, and
//!   the full-rate map it is compared with every vehicle's;
//! - **full**: today's messages (the bincode envelope, ~700 bytes) in
//!   arrival order through a 16-message queue that drops new messages when
//!   full (what a Zenoh publisher with `CongestionControl::Drop` does).
//!
//! Observations are synthesized from ground truth (`obs_synth`, default
//! noise, visibility and outlier models) at 2 Hz per camera. The formation
//! is the paper's line abreast 1.75 m apart, either holding station or
//! manoeuvring (each vehicle drifting ±0.3 m and ±5° of yaw around its slot
//! on a 60 s cycle, so a map built from old news is wrong by what moved
//! since). Each map is also scored against the truth. Assumed modem: 8 bytes of framing
//! per packet (sync, address, CRC), one packet at a time per vehicle (TDMA
//! slots give each vehicle its rate), a packet lost independently per receiver.

use super::table::{quantile, Csv};
use super::{EvalError, EvalOptions};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde_json::{json, Map, Value};
use shoal_fusion::link::{
    airtime_ns, nav_span_period_ns, LinkQueue, NavSpanner, LINK_WINDOW_S, MODEM_LATENCY_NS,
    MODEM_OVERHEAD_BYTES,
};
use shoal_fusion::{Fusion, FusionParams};
use shoal_proto::compact::LinkContent;
use shoal_proto::config::Fleet;
use shoal_proto::{FleetMap, Observation, Pose, VehicleId, VehicleState, VehicleTruth};
use shoal_sim_bridge::nav::{NavSensorParams, NavSensors};
use shoal_sim_bridge::obs_synth::{drifting_line_abreast, ObsSynth, ObsSynthParams};
use std::collections::{BTreeMap, VecDeque};
use std::path::Path;

/// The formations: holding station (each vehicle on its slot) and
/// manoeuvring (drifting ±0.3 m and ±5° around it on a 60 s cycle).
pub const FORMATIONS: [(&str, f64); 2] = [("holding", 0.0), ("manoeuvring", 0.3)];
/// Link rates of the full run, bit/s per vehicle.
pub const RATES_BPS: [f64; 3] = [300.0, 1000.0, 5000.0];
/// One-way latency of the modem link.
pub const LATENCY_NS: u64 = MODEM_LATENCY_NS;
/// Probability that a packet is lost on the way to one receiver.
pub const LOSS: f64 = 0.1;
const FRAME_NS: u64 = 500_000_000;
/// The vehicles' nav rate with `compact + nav` (10 Hz).
const NAV_NS: u64 = 100_000_000;
const STEP_NS: u64 = 50_000_000;
const SPACING_M: f64 = 1.75;
/// Seconds before the maps are compared (the windows fill).
const WARMUP_S: u64 = 15;
/// The full encoding's queue.
const FULL_QUEUE: usize = 16;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Encoding {
    Compact,
    CompactNav,
    Full,
}

impl Encoding {
    fn name(self) -> &'static str {
        match self {
            Encoding::Compact => "compact",
            Encoding::CompactNav => "compact+nav",
            Encoding::Full => "full",
        }
    }
}

/// The formation at `t_s`: line abreast, each vehicle drifting `a` metres
/// (and `a` / 0.3 x 5° of yaw) around its slot on a 60 s cycle.
fn truth_at(ids: &[VehicleId], a: f64, t_s: f64) -> Vec<VehicleTruth> {
    drifting_line_abreast(ids, SPACING_M, a, t_s)
}

/// What one vehicle's modem holds and has on the way.
enum Outbox {
    Compact(LinkQueue),
    Full(VecDeque<Observation>),
}

struct Sender {
    outbox: Outbox,
    /// With `compact + nav`: the vehicle's own nav, sent as spans.
    spanner: Option<NavSpanner>,
    nav_spans: u64,
    busy_until_ns: u64,
    packets: u64,
    bytes: u64,
    dropped_full: u64,
}

impl Sender {
    /// Vehicle `id`'s modem for `encoding` (with `compact + nav`, a span every `nav_period_ns`).
    fn new(encoding: Encoding, id: VehicleId, nav_period_ns: u64) -> Sender {
        Sender {
            outbox: match encoding {
                Encoding::Compact | Encoding::CompactNav => {
                    Outbox::Compact(LinkQueue::new((LINK_WINDOW_S * 1e9) as u64 - LATENCY_NS))
                }
                Encoding::Full => Outbox::Full(VecDeque::new()),
            },
            spanner: (encoding == Encoding::CompactNav).then(|| NavSpanner::new(id, nav_period_ns)),
            nav_spans: 0,
            busy_until_ns: 0,
            packets: 0,
            bytes: 0,
            dropped_full: 0,
        }
    }

    fn offer(&mut self, obs: Observation) {
        match &mut self.outbox {
            Outbox::Compact(q) => q.offer(obs),
            Outbox::Full(q) => {
                if q.len() < FULL_QUEUE {
                    q.push_back(obs);
                } else {
                    self.dropped_full += 1;
                }
            }
        }
    }

    /// The next packet at `now_ns`: what the receivers decode, and its size
    /// on the wire. A navigation span goes first when one is due.
    fn next(&mut self, now_ns: u64) -> Result<Option<(LinkContent, usize)>, EvalError> {
        let setup = |e: String| EvalError::Setup(e);
        if let Some(span) = self.spanner.as_mut().and_then(|s| s.due(now_ns)) {
            let bytes =
                shoal_proto::compact::encode_nav_span(&span).map_err(|e| setup(e.to_string()))?;
            let back =
                shoal_proto::compact::decode_nav_span(&bytes).map_err(|e| setup(e.to_string()))?;
            self.nav_spans += 1;
            return Ok(Some((LinkContent::Nav(back), bytes.len())));
        }
        Ok(match &mut self.outbox {
            Outbox::Compact(q) => match q.next(now_ns) {
                Some(o) => {
                    let bytes =
                        shoal_proto::compact::encode(&o).map_err(|e| setup(e.to_string()))?;
                    let back =
                        shoal_proto::compact::decode(&bytes).map_err(|e| setup(e.to_string()))?;
                    Some((LinkContent::Observation(Box::new(back)), bytes.len()))
                }
                None => None,
            },
            Outbox::Full(q) => match q.pop_front() {
                Some(o) => {
                    let n = shoal_proto::codec::encode(&o)
                        .map_err(|e| setup(e.to_string()))?
                        .len();
                    Some((LinkContent::Observation(Box::new(o)), n))
                }
                None => None,
            },
        })
    }
}

/// Columns of `links.csv`, one row per (formation, encoding, rate, seed).
const CSV_COLUMNS: [&str; 17] = [
    "formation",
    "encoding",
    "rate_bps",
    "seed",
    "median_diff_cm",
    "p95_diff_cm",
    "max_diff_cm",
    "pairs_missing",
    "median_oldest_news_s",
    "p95_local_vs_truth_cm",
    "p95_full_rate_vs_truth_cm",
    "packets_per_s",
    "bytes_per_packet",
    "superseded",
    "expired",
    "queue_full_drops",
    "nav_spans_per_s",
];

/// One trial's comparison of every vehicle's map with the full-rate one.
#[derive(Debug, Clone, Default)]
struct Trial {
    /// |Δt| of every pair in every vehicle's map against the full-rate map, m.
    diffs_m: Vec<f64>,
    /// The same against the truth, and the full-rate map's against the truth.
    local_truth_m: Vec<f64>,
    full_truth_m: Vec<f64>,
    /// Pair slots where a vehicle's map had a pair the full-rate map had, but not localized.
    missing: usize,
    slots: usize,
    /// For every vehicle's map and second: the oldest news of another vehicle, s.
    ages_s: Vec<f64>,
    packets_per_s: f64,
    bytes_per_packet: f64,
    superseded: u64,
    expired: u64,
    queue_full_drops: u64,
    nav_spans_per_s: f64,
}

fn pair_poses(map: &FleetMap) -> BTreeMap<VehicleId, Pose> {
    map.vehicles
        .iter()
        .filter(|v| v.state == VehicleState::Live)
        .map(|v| (v.vehicle, v.reference_from_vehicle))
        .collect()
}

/// |Δt| of each pair localized in `map` against `truth` (world poses).
fn truth_errors(map: &FleetMap, truth: &[VehicleTruth], out: &mut Vec<f64>) {
    let m = pair_poses(map);
    for (k, a) in truth.iter().enumerate() {
        for b in &truth[k + 1..] {
            if let (Some(ma), Some(mb)) = (m.get(&a.vehicle), m.get(&b.vehicle)) {
                let want = (a.world_from_body.inverse() * b.world_from_body)
                    .translation
                    .vector;
                out.push(((ma.inverse() * mb).translation.vector - want).norm());
            }
        }
    }
}

fn compare(local: &FleetMap, full: &FleetMap, ids: &[VehicleId], now_ns: u64, t: &mut Trial) {
    let (a, b) = (pair_poses(local), pair_poses(full));
    for (k, &i) in ids.iter().enumerate() {
        for &j in &ids[k + 1..] {
            let (Some(fi), Some(fj)) = (b.get(&i), b.get(&j)) else {
                continue;
            };
            t.slots += 1;
            let (Some(li), Some(lj)) = (a.get(&i), a.get(&j)) else {
                t.missing += 1;
                continue;
            };
            let d = (li.inverse() * lj).translation.vector - (fi.inverse() * fj).translation.vector;
            t.diffs_m.push(d.norm());
        }
    }
    let oldest = local
        .vehicles
        .iter()
        .map(|v| now_ns.saturating_sub(v.last_seen_ns) as f64 * 1e-9)
        .fold(0.0, f64::max);
    t.ages_s.push(oldest);
}

/// Hand the packets that have arrived by `now_ns` to their receivers' fusion.
fn deliver(in_flight: &mut Vec<(u64, usize, LinkContent)>, local: &mut [Fusion], now_ns: u64) {
    in_flight.retain(|(arrive, r, content)| {
        if *arrive > now_ns {
            return true;
        }
        match content {
            LinkContent::Observation(obs) => {
                let _ = local[*r].ingest_linked((**obs).clone(), obs.observer, now_ns);
            }
            LinkContent::Nav(span) => {
                let _ = local[*r].ingest_linked_nav(span, span.vehicle, now_ns);
            }
        }
        false
    });
}

fn run_trial(
    fleet: &Fleet,
    drift_m: f64,
    encoding: Encoding,
    rate_bps: f64,
    duration_s: u64,
    seed: u64,
    observations: &ObsSynthParams,
) -> Result<Trial, EvalError> {
    let ids: Vec<VehicleId> = fleet.vehicles.iter().map(|v| v.id).collect();
    let mut synth = ObsSynth::new(fleet, *observations, seed);
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x5eed_11ce);
    let exact = FusionParams {
        record_solve_time: false,
        ..FusionParams::default()
    };
    // What a vehicle sees itself is kept for the usual window, what crossed
    // the link for the link window (what `shoal fusion --link` does).
    let link_params = FusionParams {
        link_window_s: LINK_WINDOW_S,
        ..exact
    };
    let mut full_rate = Fusion::new(fleet, exact, "full-rate");
    let mut local: Vec<Fusion> = ids
        .iter()
        .map(|id| Fusion::new(fleet, link_params, &id.to_string()))
        .collect();
    let with_nav = encoding == Encoding::CompactNav;
    let mut nav_sensors = with_nav
        .then(|| NavSensors::new(NavSensorParams::default(), seed))
        .transpose()
        .map_err(|e| EvalError::Setup(e.to_string()))?;
    let nav_period_ns = nav_span_period_ns(rate_bps, MODEM_OVERHEAD_BYTES);
    let mut senders: Vec<Sender> = ids
        .iter()
        .map(|&id| Sender::new(encoding, id, nav_period_ns))
        .collect();
    let mut in_flight: Vec<(u64, usize, LinkContent)> = Vec::new();
    let mut trial = Trial::default();
    let end_ns = duration_s * 1_000_000_000;
    let mut now = 0u64;
    while now <= end_ns {
        if let Some(sensors) = nav_sensors.as_mut().filter(|_| now.is_multiple_of(NAV_NS)) {
            // Every vehicle's own nav: in full to the full-rate map and to its
            // own fusion, to its link sender for the others.
            for (k, t) in truth_at(&ids, drift_m, now as f64 * 1e-9)
                .iter()
                .enumerate()
            {
                let nav = sensors.measure(t, now);
                let refused = |e: shoal_fusion::NavRejected| {
                    EvalError::Setup(format!("nav of vehicle {}: {e}", t.vehicle))
                };
                full_rate.ingest_nav(nav, t.vehicle, now).map_err(refused)?;
                local[k].ingest_nav(nav, t.vehicle, now).map_err(refused)?;
                if let Some(sp) = senders[k].spanner.as_mut() {
                    sp.offer(nav);
                }
            }
        }
        if now.is_multiple_of(FRAME_NS) {
            let truth = truth_at(&ids, drift_m, now as f64 * 1e-9);
            for s in synth.observe(&truth, now) {
                let o = s.obs;
                let Some(k) = ids.iter().position(|v| *v == o.observer) else {
                    continue;
                };
                let _ = full_rate.ingest(o.clone(), o.observer, now);
                let _ = local[k].ingest(o.clone(), o.observer, now);
                senders[k].offer(o);
            }
        }
        for (k, s) in senders.iter_mut().enumerate() {
            while s.busy_until_ns <= now {
                let Some((content, n)) = s.next(now)? else {
                    break;
                };
                s.busy_until_ns =
                    s.busy_until_ns.max(now) + airtime_ns(n, MODEM_OVERHEAD_BYTES, rate_bps);
                s.packets += 1;
                s.bytes += (n + MODEM_OVERHEAD_BYTES) as u64;
                for r in (0..ids.len()).filter(|r| *r != k) {
                    if rng.gen::<f64>() >= LOSS {
                        in_flight.push((s.busy_until_ns + LATENCY_NS, r, content.clone()));
                    }
                }
            }
        }
        deliver(&mut in_flight, &mut local, now);
        if now.is_multiple_of(1_000_000_000) && now >= WARMUP_S * 1_000_000_000 {
            let full = full_rate.solve(now);
            let truth = truth_at(&ids, drift_m, now as f64 * 1e-9);
            truth_errors(&full, &truth, &mut trial.full_truth_m);
            for f in &mut local {
                let m = f.solve(now);
                compare(&m, &full, &ids, now, &mut trial);
                truth_errors(&m, &truth, &mut trial.local_truth_m);
            }
        }
        now += STEP_NS;
    }
    let packets: u64 = senders.iter().map(|s| s.packets).sum();
    let bytes: u64 = senders.iter().map(|s| s.bytes).sum();
    trial.packets_per_s = packets as f64 / ids.len() as f64 / duration_s as f64;
    trial.nav_spans_per_s = senders.iter().map(|s| s.nav_spans).sum::<u64>() as f64
        / ids.len() as f64
        / duration_s as f64;
    trial.bytes_per_packet = if packets > 0 {
        bytes as f64 / packets as f64
    } else {
        0.0
    };
    for s in &senders {
        if let Outbox::Compact(q) = &s.outbox {
            trial.superseded += q.stats().superseded;
            trial.expired += q.stats().expired;
        }
        trial.queue_full_drops += s.dropped_full;
    }
    Ok(trial)
}

/// Per-condition figures over seeds: each seed's p95 / max / median age, then their range.
#[derive(Debug, Default)]
struct Cell {
    p95_cm: Vec<f64>,
    max_cm: Vec<f64>,
    median_cm: Vec<f64>,
    missing: Vec<f64>,
    age_median_s: Vec<f64>,
    packets_per_s: Vec<f64>,
    bytes_per_packet: Vec<f64>,
    local_truth_p95_cm: Vec<f64>,
    full_truth_p95_cm: Vec<f64>,
    nav_spans_per_s: Vec<f64>,
}

fn range(v: &[f64]) -> Value {
    let lo = v.iter().copied().fold(f64::INFINITY, f64::min);
    let hi = v.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let mean = v.iter().sum::<f64>() / v.len().max(1) as f64;
    json!({"mean": mean, "min": lo, "max": hi})
}

/// The two bar plots: the 95th-percentile difference and the pairs unknown,
/// per rate (`values[series][rate]`).
fn plots(
    out: &Path,
    rates: &[f64],
    series: Vec<String>,
    p95_values: &[Vec<Option<f64>>],
    unknown_values: &[Vec<Option<f64>>],
) -> Value {
    let categories: Vec<String> = rates.iter().map(|r| format!("{r} bit/s")).collect();
    let p1 = super::features::plot_or_warn(super::plot::bars(
        &out.join("eval-links-difference"),
        &super::plot::Grouped {
            title: "Decentralized map against the full-rate map (95th percentile, pairs it has)"
                .into(),
            x_label: "link rate per vehicle".into(),
            y_label: "difference (cm)".into(),
            categories: categories.clone(),
            series: series.clone(),
        },
        p95_values,
    ));
    let p2 = super::features::plot_or_warn(super::plot::bars(
        &out.join("eval-links-unknown"),
        &super::plot::Grouped {
            title: "Vehicle pairs a decentralized map does not have".into(),
            x_label: "link rate per vehicle".into(),
            y_label: "pairs unknown (%)".into(),
            categories,
            series,
        },
        unknown_values,
    ));
    json!([p1, p2])
}

/// One `links.csv` row: the trial's figures.
fn csv_row(formation: &str, enc: Encoding, rate: f64, seed: u64, t: &Trial) -> Vec<String> {
    let cm = |v: &[f64], p: f64| quantile(v, p).unwrap_or(f64::NAN) * 100.0;
    let max = t.diffs_m.iter().copied().fold(f64::NAN, f64::max) * 100.0;
    vec![
        formation.into(),
        enc.name().into(),
        rate.to_string(),
        seed.to_string(),
        format!("{:.2}", cm(&t.diffs_m, 0.5)),
        format!("{:.2}", cm(&t.diffs_m, 0.95)),
        format!("{max:.2}"),
        format!("{:.3}", t.missing as f64 / t.slots.max(1) as f64),
        format!("{:.2}", quantile(&t.ages_s, 0.5).unwrap_or(f64::NAN)),
        format!("{:.2}", cm(&t.local_truth_m, 0.95)),
        format!("{:.2}", cm(&t.full_truth_m, 0.95)),
        format!("{:.2}", t.packets_per_s),
        format!("{:.1}", t.bytes_per_packet),
        t.superseded.to_string(),
        t.expired.to_string(),
        t.queue_full_drops.to_string(),
        format!("{:.3}", t.nav_spans_per_s),
    ]
}

pub fn run(opts: &EvalOptions) -> Result<Value, EvalError> {
    let fleet = Fleet::parse(
        crate::demo::PAPER_FLEET,
        Path::new("configs/fleets/paper.toml"),
    )
    .map_err(|e| EvalError::Setup(e.to_string()))?;
    let duration_s = opts.count(60, 300) as u64;
    let observations = super::fusion::observation_model(opts, "links")?;
    let seeds: Vec<u64> = (0..if opts.quick { 2 } else { 5 })
        .map(|k| opts.seed.wrapping_add(k))
        .collect();
    let rates: Vec<f64> = if opts.quick {
        vec![300.0, 1000.0]
    } else {
        RATES_BPS.to_vec()
    };
    let encodings = [Encoding::Compact, Encoding::CompactNav, Encoding::Full];
    let bar = opts.bar(
        FORMATIONS.len() * encodings.len() * rates.len() * seeds.len(),
        "links: trials",
    );
    let mut csv = Csv::new(&CSV_COLUMNS);
    let mut results = Map::new();
    // Per "formation, encoding": the mean over seeds of the p95 difference, per rate.
    let mut series = Vec::new();
    let mut p95_values: Vec<Vec<Option<f64>>> = Vec::new();
    let mut unknown_values: Vec<Vec<Option<f64>>> = Vec::new();
    for (formation, drift_m) in FORMATIONS {
        let mut by_encoding = Map::new();
        for enc in encodings {
            let mut per = Map::new();
            series.push(format!("{formation}, {}", enc.name()));
            p95_values.push(Vec::new());
            unknown_values.push(Vec::new());
            for &rate in &rates {
                let mut cell = Cell::default();
                for &seed in &seeds {
                    let t = run_trial(&fleet, drift_m, enc, rate, duration_s, seed, &observations)?;
                    let q = |p: f64| quantile(&t.diffs_m, p).map_or(f64::NAN, |v| v * 100.0);
                    let missing = t.missing as f64 / t.slots.max(1) as f64;
                    let age = quantile(&t.ages_s, 0.5).unwrap_or(f64::NAN);
                    let max = t.diffs_m.iter().copied().fold(f64::NAN, f64::max) * 100.0;
                    csv.row(csv_row(formation, enc, rate, seed, &t));
                    cell.median_cm.push(q(0.5));
                    cell.p95_cm.push(q(0.95));
                    cell.max_cm.push(max);
                    cell.missing.push(missing);
                    cell.age_median_s.push(age);
                    cell.packets_per_s.push(t.packets_per_s);
                    cell.bytes_per_packet.push(t.bytes_per_packet);
                    cell.local_truth_p95_cm
                        .push(quantile(&t.local_truth_m, 0.95).unwrap_or(f64::NAN) * 100.0);
                    cell.full_truth_p95_cm
                        .push(quantile(&t.full_truth_m, 0.95).unwrap_or(f64::NAN) * 100.0);
                    cell.nav_spans_per_s.push(t.nav_spans_per_s);
                    bar.inc(1);
                }
                let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
                if let Some(last) = p95_values.last_mut() {
                    last.push(Some(mean(&cell.p95_cm)));
                }
                if let Some(last) = unknown_values.last_mut() {
                    last.push(Some(100.0 * mean(&cell.missing)));
                }
                per.insert(
                    format!("{rate}"),
                    json!({
                        "median_diff_cm": range(&cell.median_cm),
                        "p95_diff_cm": range(&cell.p95_cm),
                        "max_diff_cm": range(&cell.max_cm),
                        "pairs_missing": range(&cell.missing),
                        "median_oldest_news_s": range(&cell.age_median_s),
                        "packets_per_s": range(&cell.packets_per_s),
                        "bytes_per_packet": range(&cell.bytes_per_packet),
                        "p95_local_vs_truth_cm": range(&cell.local_truth_p95_cm),
                        "p95_full_rate_vs_truth_cm": range(&cell.full_truth_p95_cm),
                        "nav_spans_per_s": range(&cell.nav_spans_per_s),
                    }),
                );
            }
            by_encoding.insert(enc.name().into(), Value::Object(per));
        }
        results.insert(formation.into(), Value::Object(by_encoding));
    }
    bar.finish_and_clear();
    csv.write(&opts.out.join("links.csv"))?;
    let plots = plots(&opts.out, &rates, series, &p95_values, &unknown_values);
    Ok(json!({
        "plots": plots,
        "setup": format!(
            "paper fleet, line abreast {SPACING_M} m, holding station or drifting ±0.3 m / ±5° on a 60 s cycle; obs_synth at 2 Hz per camera; per-vehicle link at each rate, {} s latency, {} % loss per receiver, {MODEM_OVERHEAD_BYTES} bytes framing per packet; decentralized fusion keeps its own observations 2 s and what crossed the link {LINK_WINDOW_S} s; maps compared every second after {WARMUP_S} s with the full-rate map (default fusion fed every observation at once); {} s per trial",
            LATENCY_NS as f64 * 1e-9,
            LOSS * 100.0,
            duration_s
        ),
        "seeds": seeds,
        "observation_model": opts.profile_name(),
        "results": results,
    }))
}
