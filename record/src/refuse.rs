//! Offline re-fusion (`shoal fuse`): run [`shoal_fusion::Fusion`] over a log's
//! observations, with no Zenoh and no wall clock, as fast as the CPU allows.
//!
//! The time line is the log's simulated clock: `now` is the newest capture
//! stamp seen so far (SimTruth and observation stamps), observations are
//! ingested in log order, and the map is solved at the stamps of the original
//! run's maps (or at a fixed rate of that clock). `solve_time_us` is not
//! recorded, so the same file gives the same output, bit for bit.

use crate::reader::{header, scan_wire, LogHeader, LogSource};
use crate::recorder::{Converter, RecordOptions, RecorderStats};
use crate::writer::{LogWriter, WriterOptions};
use crate::RecordError;
use proto::config::Fleet;
use proto::geometry::difference;
use proto::{FleetMap, KeyKind, MessageKind, Observation, SimTruth, VehicleId, VehicleState};
use shoal_fusion::{Fusion, FusionParams};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// When to solve.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum SolveAt {
    /// At the stamps of the central maps recorded in the log.
    OriginalMaps,
    /// Every `1/rate` seconds of the log's clock.
    RateHz(f64),
}

impl SolveAt {
    /// The solve period in nanoseconds of the log's clock (`None` at the
    /// original maps' stamps); a rate that is not finite, not above zero or
    /// above 1 GHz (a period under one nanosecond) is refused.
    pub fn period_ns(&self) -> Result<Option<u64>, RecordError> {
        match *self {
            SolveAt::OriginalMaps => Ok(None),
            SolveAt::RateHz(rate_hz) if rate_hz.is_finite() && rate_hz > 0.0 && rate_hz <= 1e9 => {
                Ok(Some((1e9 / rate_hz).round().max(1.0) as u64))
            }
            SolveAt::RateHz(rate_hz) => Err(RecordError::SolveRate { rate_hz }),
        }
    }
}

#[derive(Debug, Clone)]
pub struct FuseOptions {
    pub params: FusionParams,
    pub solve_at: SolveAt,
    /// Use this fleet instead of the one attached to the log.
    pub fleet: Option<Fleet>,
}

impl Default for FuseOptions {
    fn default() -> Self {
        Self {
            params: FusionParams::default(),
            solve_at: SolveAt::OriginalMaps,
            fleet: None,
        }
    }
}

/// Differences between the re-fused maps and the original ones at the same stamps.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct MapComparison {
    pub maps_compared: u64,
    /// Vehicle estimates compared (Live in both maps).
    pub estimates_compared: u64,
    pub max_position_diff_m: f64,
    pub max_angle_diff_deg: f64,
    pub mean_position_diff_m: f64,
}

#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct FuseSummary {
    pub output: PathBuf,
    pub observations: u64,
    pub rejected_at_ingest: u64,
    /// The vehicles' nav states read, and those fusion refused.
    pub nav_states: u64,
    pub nav_refused: u64,
    pub maps_written: u64,
    pub original_maps: u64,
    /// Envelopes of the log that did not decode (observations, truth, maps, unknown kinds): counted, not re-fused.
    pub undecodable: u64,
    /// What was wrong with the input log (None: intact).
    pub input_damage: Option<String>,
    pub comparison: MapComparison,
    /// The re-fused maps against the log's ground truth (`None`: the log has none).
    pub truth: Option<crate::truth_score::TruthScore>,
    /// The pose graph of the last re-fused map (`shoal fuse --g2o` writes it).
    #[serde(skip)]
    pub last_graph: Option<shoal_fusion::export::PoseGraph>,
}

/// The fleet a log was recorded with (its attachment), unless overridden.
pub fn fleet_of(src: impl LogSource, input: &Path) -> Result<Fleet, RecordError> {
    let h = header(src).map_err(|source| RecordError::NotMcap {
        path: input.to_path_buf(),
        source,
    })?;
    let text = h
        .fleet_toml
        .ok_or_else(|| RecordError::NoFleet(input.to_path_buf()))?;
    let source = h
        .metadata
        .get("fleet_file")
        .map_or_else(|| PathBuf::from("fleet.toml"), PathBuf::from);
    Fleet::parse(&text, &source).map_err(|source| RecordError::AttachedFleet {
        path: input.to_path_buf(),
        source,
    })
}

/// Re-fuse `input` into `output`. The output carries the input's
/// observations, nav states, truth, status and commands (raw and Foxglove), and the new
/// map track in place of the old one.
pub fn refuse(input: &Path, output: &Path, opts: &FuseOptions) -> Result<FuseSummary, RecordError> {
    let solve_period_ns = opts.solve_at.period_ns()?;
    let h = header(input).map_err(|source| RecordError::NotMcap {
        path: input.to_path_buf(),
        source,
    })?;
    let fleet = fleet_for(input, &h.metadata, opts.fleet.as_ref())?;
    let out = proto::files::OutputFile::new(output, &[input])?;
    let keys = fleet.keys();
    let mut params = opts.params;
    params.record_solve_time = false;
    let mut fusion = Fusion::new(&fleet, params, "central");
    let mut writer = output_writer(out.temp_path(), input, &h, opts.solve_at)?;
    let conv_opts = RecordOptions {
        frames: false,
        ..RecordOptions::default()
    };
    let fleet = Arc::new(fleet);
    let mut conv = Converter::new(fleet.clone(), conv_opts);
    let stats = RecorderStats::default();
    let mut summary = FuseSummary {
        output: output.to_path_buf(),
        ..FuseSummary::default()
    };
    let mut now: u64 = 0;
    let mut next_solve: Option<u64> = None;
    let mut cmp = CompareAcc::default();
    let mut truth = crate::truth_score::TruthAcc::default();
    let map_key = keys.map();
    let res = scan_wire(
        input,
        |channel, log_time, data| -> Result<(), RecordError> {
            let key = channel.topic.as_str();
            let kind = crate::recorder::envelope_kind(data);
            match (kind, keys.parse(key)) {
                (Some(MessageKind::SimTruth), _) => {
                    match proto::decode::<SimTruth>(data) {
                        Ok(t) => {
                            now = now.max(t.stamp_ns);
                            truth.add_truth(t);
                        }
                        Err(_) => summary.undecodable += 1,
                    }
                    conv.write(&mut writer, key, data, log_time, &stats)?;
                }
                (Some(MessageKind::Observation), Ok(KeyKind::Observations { vehicle }))
                | (Some(MessageKind::NavState), Ok(KeyKind::Nav { vehicle })) => {
                    ingest(&mut fusion, &mut now, &mut summary, vehicle, data);
                    conv.write(&mut writer, key, data, log_time, &stats)?;
                }
                (Some(MessageKind::FleetMap), _) => {
                    if key == map_key {
                        let decoded = proto::decode::<FleetMap>(data);
                        if decoded.is_err() {
                            summary.undecodable += 1;
                        }
                        if let Ok(original) = decoded {
                            summary.original_maps += 1;
                            if opts.solve_at == SolveAt::OriginalMaps {
                                let map = fusion.solve(original.stamp_ns);
                                cmp.add(&map, &original);
                                truth.add_map(&map);
                                write_map(
                                    &mut writer,
                                    &mut conv,
                                    &map_key,
                                    &map,
                                    log_time,
                                    &stats,
                                )?;
                                summary.maps_written += 1;
                            }
                        }
                    }
                    return Ok(());
                }
                (Some(MessageKind::CameraFrame), _) => return Ok(()),
                (None, _) => {
                    summary.undecodable += 1;
                    return Ok(());
                }
                _ => conv.write(&mut writer, key, data, log_time, &stats)?,
            }
            if let Some(period) = solve_period_ns {
                let due = *next_solve.get_or_insert(now + period);
                if now >= due {
                    let map = fusion.solve(now);
                    truth.add_map(&map);
                    write_map(&mut writer, &mut conv, &map_key, &map, log_time, &stats)?;
                    summary.maps_written += 1;
                    next_solve = Some(due + period * ((now - due) / period + 1));
                }
            }
            Ok(())
        },
    );
    let outcome = res.map_err(|e| match e.into_record_error(input) {
        Ok(e) | Err(e) => e,
    })?;
    if let Some(d) = &outcome.damage {
        tracing::warn!("{}: {d}; re-fused what was readable", input.display());
    }
    summary.input_damage = outcome.damage;
    writer.finish()?;
    out.commit()?;
    summary.comparison = cmp.finish();
    summary.truth = truth.finish();
    // With odometry factors the graph solved last is the one over time.
    summary.last_graph = match fusion.last_time_graph() {
        Some((g, _)) => Some(g.clone()),
        None => fusion.last_graph().cloned(),
    };
    Ok(summary)
}

/// Feed one observation or nav state envelope (arrived on `vehicle`'s key)
/// to `fusion`, advancing `now` to its capture stamp and counting it.
fn ingest(
    fusion: &mut Fusion,
    now: &mut u64,
    summary: &mut FuseSummary,
    vehicle: VehicleId,
    data: &[u8],
) {
    match crate::recorder::envelope_kind(data) {
        Some(MessageKind::Observation) => match proto::decode::<Observation>(data) {
            Ok(o) => {
                *now = (*now).max(o.stamp_ns);
                summary.observations += 1;
                if fusion.ingest(o, vehicle, *now).is_err() {
                    summary.rejected_at_ingest += 1;
                }
            }
            Err(_) => summary.undecodable += 1,
        },
        Some(MessageKind::NavState) => match proto::decode::<proto::NavState>(data) {
            Ok(n) => {
                *now = (*now).max(n.stamp_ns);
                summary.nav_states += 1;
                if fusion.ingest_nav(n, vehicle, *now).is_err() {
                    summary.nav_refused += 1;
                }
            }
            Err(_) => summary.undecodable += 1,
        },
        _ => summary.undecodable += 1,
    }
}

/// The re-fused log's writer: the input's metadata and fleet, and where it came from.
fn output_writer(
    path: &Path,
    input: &Path,
    h: &LogHeader,
    solve_at: SolveAt,
) -> Result<LogWriter, RecordError> {
    let mut meta = h.metadata.clone();
    meta.insert(
        "refused_from".into(),
        input
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default(),
    );
    meta.insert("fusion".into(), format!("offline re-fusion, {solve_at:?}"));
    LogWriter::create(
        path,
        &WriterOptions::default(),
        &meta,
        h.fleet_toml.as_deref(),
        0,
    )
}

/// The fleet to re-fuse with: the one given (which must be the fleet the log
/// was recorded with) or the log's own attachment.
fn fleet_for(
    input: &Path,
    metadata: &BTreeMap<String, String>,
    given: Option<&Fleet>,
) -> Result<Fleet, RecordError> {
    match given {
        Some(f) => match metadata.get("fleet").filter(|n| **n != f.name) {
            Some(recorded) => Err(RecordError::FleetMismatch {
                path: input.to_path_buf(),
                recorded: recorded.clone(),
                given: f.name.clone(),
            }),
            None => Ok(f.clone()),
        },
        None => fleet_of(input, input),
    }
}

fn write_map(
    writer: &mut LogWriter,
    conv: &mut Converter,
    key: &str,
    map: &FleetMap,
    log_time: u64,
    stats: &RecorderStats,
) -> Result<(), RecordError> {
    let bytes = proto::encode(map).map_err(|source| RecordError::Encode {
        what: "map",
        source,
    })?;
    conv.write(writer, key, &bytes, log_time, stats)
}

#[derive(Default)]
struct CompareAcc {
    c: MapComparison,
    sum: f64,
}

impl CompareAcc {
    fn add(&mut self, ours: &FleetMap, original: &FleetMap) {
        if let Some(d) = compare_maps(ours, original) {
            self.c.maps_compared += 1;
            for (pos, ang) in d.values() {
                self.c.estimates_compared += 1;
                self.sum += pos;
                self.c.max_position_diff_m = self.c.max_position_diff_m.max(*pos);
                self.c.max_angle_diff_deg = self.c.max_angle_diff_deg.max(*ang);
            }
        }
    }
    fn finish(mut self) -> MapComparison {
        if self.c.estimates_compared > 0 {
            self.c.mean_position_diff_m = self.sum / self.c.estimates_compared as f64;
        }
        self.c
    }
}

/// Position (m) and angle (deg) difference of every non-reference vehicle
/// Live in both maps; `None` if the maps have different references.
pub fn compare_maps(a: &FleetMap, b: &FleetMap) -> Option<BTreeMap<VehicleId, (f64, f64)>> {
    if a.reference != b.reference {
        return None;
    }
    let mut out = BTreeMap::new();
    for va in a
        .vehicles
        .iter()
        .filter(|v| v.state == VehicleState::Live && v.vehicle != a.reference)
    {
        if let Some(vb) = b
            .vehicles
            .iter()
            .find(|v| v.vehicle == va.vehicle && v.state == VehicleState::Live)
        {
            let d = difference(&va.reference_from_vehicle, &vb.reference_from_vehicle);
            out.insert(
                va.vehicle,
                (
                    d.fixed_rows::<3>(0).norm(),
                    d.fixed_rows::<3>(3).norm().to_degrees(),
                ),
            );
        }
    }
    Some(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_solve_rate_that_gives_no_whole_nanosecond_period_is_refused() {
        for bad in [0.0, -1.0, f64::NAN, f64::INFINITY, 1e10] {
            assert!(
                matches!(
                    SolveAt::RateHz(bad).period_ns(),
                    Err(RecordError::SolveRate { .. })
                ),
                "{bad} accepted"
            );
        }
        assert_eq!(
            SolveAt::RateHz(10.0).period_ns().unwrap(),
            Some(100_000_000)
        );
        assert_eq!(SolveAt::RateHz(1e9).period_ns().unwrap(), Some(1));
        assert_eq!(SolveAt::OriginalMaps.period_ns().unwrap(), None);
    }
}
