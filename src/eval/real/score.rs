//! Scoring one split of a recording: what each method read of what the
//! truth knows, its false reads, and the pose consistency the truth allows
//! (pair distances and jitter, rotation between steps, corner errors).

use super::manifest::{Manifest, Truth};
use crate::eval::table::{median, quantile};
use nalgebra::Matrix3;
use shoal_proto::geometry::Pose;
use std::collections::{BTreeMap, BTreeSet};

/// A reference corner farther than this fraction of the marker's side from
/// the detected one means the detection is somewhere else: a false read.
const MISPLACED_FRACTION: f64 = 0.25;

/// One marker a method read in one frame.
#[derive(Debug, Clone)]
pub(super) struct Read {
    pub(super) id: u32,
    /// The outer square's corners (corner IDs 0..4), in corner-ID order.
    pub(super) outer_px: Vec<[f64; 2]>,
    pub(super) camera_from_marker: Option<Pose>,
    /// PnP's other planar hypothesis (the flip), when it has one.
    pub(super) alternative: Option<Pose>,
    /// The covariance of the marker's position in the camera frame (m²) as
    /// the node states it for `camera_from_marker` (`shoal_node::pose::stated_covariance`).
    pub(super) position_cov: Option<Matrix3<f64>>,
}

/// What one method read over one split.
#[derive(Debug, Default)]
pub(super) struct MethodRun {
    /// Per frame: (frame index, frame name, reads).
    pub(super) frames: Vec<(usize, String, Vec<Read>)>,
    pub(super) detect_ms: Vec<f64>,
}

/// The IDs the truth knows.
fn known_ids(truth: &Truth) -> BTreeSet<u32> {
    match truth {
        Truth::Layout { centres_m } => centres_m.keys().copied().collect(),
        Truth::Corners { images } => images.values().flatten().map(|t| t.id).collect(),
        Truth::RotationSteps { id, .. } => [*id].into(),
    }
}

/// Mean distance of each reference corner to the nearest detected one, px.
fn corner_error(reference: &[[f64; 2]; 4], found: &[[f64; 2]]) -> Option<f64> {
    if found.is_empty() {
        return None;
    }
    let mut sum = 0.0;
    for r in reference {
        let d = found
            .iter()
            .map(|f| ((f[0] - r[0]).powi(2) + (f[1] - r[1]).powi(2)).sqrt())
            .fold(f64::INFINITY, f64::min);
        sum += d;
    }
    Some(sum / 4.0)
}

fn side_px(corners: &[[f64; 2]; 4]) -> f64 {
    (0..4)
        .map(|k| {
            let (a, b) = (corners[k], corners[(k + 1) % 4]);
            ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2)).sqrt()
        })
        .sum::<f64>()
        / 4.0
}

/// The figures of one method on one split.
#[derive(Debug, Default, Clone, serde::Serialize)]
pub(super) struct Scores {
    pub(super) frames: usize,
    pub(super) present: usize,
    pub(super) read: usize,
    pub(super) recall: Option<f64>,
    pub(super) false_reads: usize,
    /// Reads of a known ID that no other detector family confirmed.
    pub(super) unconfirmed: usize,
    pub(super) corner_err_px_median: Option<f64>,
    pub(super) pairs: usize,
    pub(super) distance_ratio_median: Option<f64>,
    pub(super) distance_ratio_iqr: Option<f64>,
    /// The same over the pairs of present markers only (a read of a known ID
    /// no other family confirms, counted under `unconfirmed`, left out): the
    /// consistency of what a method reads right, apart from its false reads.
    pub(super) distance_ratio_iqr_present: Option<f64>,
    pub(super) jitter_mm_median: Option<f64>,
    /// Jitter over the (frame, pair)s every method read.
    pub(super) jitter_mm_median_common: Option<f64>,
    /// Jitter over the pairs of present markers only (as
    /// [`Scores::distance_ratio_iqr_present`]).
    pub(super) jitter_mm_median_present: Option<f64>,
    /// The stated covariance against the jitter: the mean over consecutive
    /// frames of `(Δd)² / (σ²_d(t) + σ²_d(t−1))` for each pair's distance `d`,
    /// 1 when honest (a χ²₁ mean; below 1 also when the errors of
    /// consecutive frames are correlated, as the same view's are).
    pub(super) jitter_nees_mean: Option<f64>,
    /// Its median (χ²₁'s is 0.455): less moved by a few gross steps.
    pub(super) jitter_nees_median: Option<f64>,
    /// The steps it is taken over.
    pub(super) jitter_nees_steps: usize,
    pub(super) rotation_err_deg_median: Option<f64>,
    /// The same with each image's planar flip chosen to agree best.
    pub(super) rotation_err_deg_median_flip_resolved: Option<f64>,
    pub(super) detect_ms_mean: Option<f64>,
}

/// Reads of known markers by `(frame, key)`, false reads, corner errors (px).
type Tally = (BTreeSet<(usize, u32)>, usize, Vec<f64>);

/// What one method read of what the truth knows: `(frame, key)` where the
/// key is the marker ID, or with [`Truth::Corners`] the reference marker's
/// index in its image's list; the false reads (with a layout or rotation
/// truth: an ID it does not know, or one read a second time in a frame);
/// the corner errors (px).
fn tally(m: &Manifest, run: &MethodRun) -> Tally {
    let known = known_ids(&m.truth);
    let mut good = BTreeSet::new();
    let mut false_reads = 0;
    let mut corner_errs = Vec::new();
    for (idx, name, reads) in &run.frames {
        if let Truth::Corners { images } = &m.truth {
            let refs = images.get(name).map_or(&[][..], Vec::as_slice);
            for r in reads {
                // The nearest reference of that ID not taken yet, if close enough.
                let best = refs
                    .iter()
                    .enumerate()
                    .filter(|(k, t)| t.id == r.id && !good.contains(&(*idx, *k as u32)))
                    .filter_map(|(k, t)| corner_error(&t.corners, &r.outer_px).map(|e| (k, t, e)))
                    .min_by(|a, b| a.2.total_cmp(&b.2));
                match best {
                    Some((k, t, e)) if e < MISPLACED_FRACTION * side_px(&t.corners) => {
                        if !t.hand_checked {
                            corner_errs.push(e);
                        }
                        good.insert((*idx, k as u32));
                    }
                    _ => false_reads += 1,
                }
            }
        } else {
            // Every known ID is one marker in one place: a second read of
            // it in the same frame is a read of something else.
            for r in reads.iter().filter(|r| !m.unlisted_ids.contains(&r.id)) {
                if !known.contains(&r.id) || !good.insert((*idx, r.id)) {
                    false_reads += 1;
                }
            }
        }
    }
    (good, false_reads, corner_errs)
}

/// A pair's distance in one frame: measured and known (m), and the variance
/// of the measured one the stated covariances give (m²; `None` without them).
#[derive(Debug, Clone, Copy)]
struct PairDistance {
    measured: f64,
    known: f64,
    variance: Option<f64>,
}

/// Pair distances per (frame, pair) for a layout truth.
fn pair_distances(
    centres: &BTreeMap<u32, [f64; 3]>,
    run: &MethodRun,
) -> BTreeMap<(usize, u32, u32), PairDistance> {
    let mut out = BTreeMap::new();
    for (idx, _, reads) in &run.frames {
        // An ID read twice in one frame (a false read beside the tag) says
        // nothing of where that tag is: neither read is paired.
        let twice = |id: u32| reads.iter().filter(|r| r.id == id).count() > 1;
        let posed: Vec<(u32, Pose, Option<Matrix3<f64>>)> = reads
            .iter()
            .filter(|r| centres.contains_key(&r.id) && !twice(r.id))
            .filter_map(|r| r.camera_from_marker.map(|p| (r.id, p, r.position_cov)))
            .collect();
        for (i, (a, pa, ca)) in posed.iter().enumerate() {
            for (b, pb, cb) in &posed[i + 1..] {
                let (a, b) = (*a.min(b), *a.max(b));
                let between = pa.translation.vector - pb.translation.vector;
                let measured = between.norm();
                // Along the line between the two: the two tags' errors are
                // independent (separate corners), their sum's variance the sum.
                let variance = ca.zip(*cb).and_then(|(ca, cb)| {
                    let u = between / measured;
                    let v = (u.transpose() * (ca + cb) * u)[0];
                    (measured > 0.0 && v.is_finite() && v > 0.0).then_some(v)
                });
                let (ka, kb) = (centres[&a], centres[&b]);
                let known =
                    ((ka[0] - kb[0]).powi(2) + (ka[1] - kb[1]).powi(2) + (ka[2] - kb[2]).powi(2))
                        .sqrt();
                out.insert(
                    (*idx, a, b),
                    PairDistance {
                        measured,
                        known,
                        variance,
                    },
                );
            }
        }
    }
    out
}

/// Each pair's consecutive frames: the two distances, over the (frame,
/// pair)s in `keep` (all when `None`).
fn steps<'a>(
    d: &'a BTreeMap<(usize, u32, u32), PairDistance>,
    keep: Option<&'a BTreeSet<(usize, u32, u32)>>,
) -> impl Iterator<Item = (&'a PairDistance, &'a PairDistance)> + 'a {
    let kept = move |k: &(usize, u32, u32)| keep.is_none_or(|keep| keep.contains(k));
    d.iter().filter_map(move |(&(idx, a, b), now)| {
        let before = (idx.checked_sub(1)?, a, b);
        (kept(&(idx, a, b)) && kept(&before)).then_some(())?;
        d.get(&before).map(|prev| (prev, now))
    })
}

/// Median |change| of each pair's distance between consecutive frames, mm,
/// over the (frame, pair)s in `keep` (all when `None`).
fn jitter_mm(
    d: &BTreeMap<(usize, u32, u32), PairDistance>,
    keep: Option<&BTreeSet<(usize, u32, u32)>>,
) -> Option<f64> {
    let changes: Vec<f64> = steps(d, keep)
        .map(|(prev, now)| (now.measured - prev.measured).abs() * 1e3)
        .collect();
    median(&changes)
}

/// `(Δd)² / (σ²_d(t) + σ²_d(t−1))` of every consecutive step both of whose
/// distances have a stated variance ([`Scores::jitter_nees_mean`]).
fn jitter_nees(d: &BTreeMap<(usize, u32, u32), PairDistance>) -> Vec<f64> {
    steps(d, None)
        .filter_map(|(prev, now)| {
            let var = prev.variance? + now.variance?;
            Some((now.measured - prev.measured).powi(2) / var)
        })
        .collect()
}

/// |measured − nominal| rotation between consecutive steps, degrees: with
/// PnP's best hypothesis of each image, or (`resolve_flips`) with whichever
/// of each image's two planar hypotheses agrees best — the detector-bound
/// error, since a flip is resolved downstream by other observations.
fn rotation_errors(
    id: u32,
    angle_deg: &BTreeMap<String, f64>,
    run: &MethodRun,
    resolve_flips: bool,
) -> Vec<f64> {
    let mut steps: Vec<(f64, Vec<Pose>)> = run
        .frames
        .iter()
        .filter_map(|(_, name, reads)| {
            let angle = *angle_deg.get(name)?;
            let read = reads.iter().find(|r| r.id == id)?;
            let mut poses = vec![read.camera_from_marker?];
            if resolve_flips {
                poses.extend(read.alternative);
            }
            Some((angle, poses))
        })
        .collect();
    steps.sort_by(|a, b| a.0.total_cmp(&b.0));
    steps
        .windows(2)
        .map(|w| {
            let nominal = (w[1].0 - w[0].0).abs();
            w[0].1
                .iter()
                .flat_map(|a| w[1].1.iter().map(move |b| (a, b)))
                .map(|(a, b)| {
                    ((a.rotation.inverse() * b.rotation).angle().to_degrees() - nominal).abs()
                })
                .fold(f64::INFINITY, f64::min)
        })
        .collect()
}

/// The interquartile range of `v`.
fn iqr(v: &[f64]) -> Option<f64> {
    quantile(v, 0.75).zip(quantile(v, 0.25)).map(|(a, b)| a - b)
}

/// The (frame, pair)s of `d` whose two markers are both `present` in their frame.
fn present_pairs(
    d: &BTreeMap<(usize, u32, u32), PairDistance>,
    present: &BTreeSet<(usize, u32)>,
) -> BTreeSet<(usize, u32, u32)> {
    d.keys()
        .filter(|(i, a, b)| present.contains(&(*i, *a)) && present.contains(&(*i, *b)))
        .copied()
        .collect()
}

/// Measured over known distance of the [`present_pairs`].
fn present_ratios(
    d: &BTreeMap<(usize, u32, u32), PairDistance>,
    present: &BTreeSet<(usize, u32)>,
) -> Vec<f64> {
    present_pairs(d, present)
        .iter()
        .map(|k| d[k].measured / d[k].known)
        .collect()
}

/// The detector family of a method (`shoal+hoirm` → `shoal`, `apriltag3-d1` → `apriltag3`).
fn family(method: &str) -> &str {
    method.split(['+', '-']).next().unwrap_or(method)
}

/// The (frame, ID)s read by at least two detector families (by one when
/// only two families run): a weak code family's false positives that happen
/// to carry a listed ID are not taken for present markers.
fn confirmed(tallies: &BTreeMap<&String, Tally>) -> BTreeSet<(usize, u32)> {
    let mut by: BTreeMap<(usize, u32), BTreeSet<&str>> = BTreeMap::new();
    for (method, (good, _, _)) in tallies {
        for key in good {
            by.entry(*key).or_default().insert(family(method));
        }
    }
    let families: BTreeSet<&str> = tallies.keys().map(|m| family(m)).collect();
    let need = if families.len() >= 3 { 2 } else { 1 };
    by.into_iter()
        .filter(|(_, f)| f.len() >= need)
        .map(|(k, _)| k)
        .collect()
}

pub(super) fn scores(m: &Manifest, runs: &BTreeMap<String, MethodRun>) -> BTreeMap<String, Scores> {
    let tallies: BTreeMap<&String, _> = runs.iter().map(|(k, r)| (k, tally(m, r))).collect();
    let frames: BTreeMap<&str, usize> = runs
        .values()
        .flat_map(|r| r.frames.iter().map(|(i, n, _)| (n.as_str(), *i)))
        .collect();
    let present: BTreeSet<(usize, u32)> = match &m.truth {
        Truth::Corners { images } => images
            .iter()
            .filter_map(|(name, tags)| frames.get(name.as_str()).map(|i| (*i, tags.len())))
            .flat_map(|(i, n)| (0..n as u32).map(move |k| (i, k)))
            .collect(),
        // The marker is in every image the steps list, read by anyone or not.
        Truth::RotationSteps { id, angle_deg } => angle_deg
            .keys()
            .filter_map(|name| frames.get(name.as_str()).map(|i| (*i, *id)))
            .collect(),
        Truth::Layout { .. } => confirmed(&tallies),
    };
    let distances: BTreeMap<&String, _> = match &m.truth {
        Truth::Layout { centres_m } => runs
            .iter()
            .map(|(k, r)| (k, pair_distances(centres_m, r)))
            .collect(),
        _ => BTreeMap::new(),
    };
    let common: Option<BTreeSet<(usize, u32, u32)>> = distances
        .values()
        .map(|d| d.keys().copied().collect::<BTreeSet<_>>())
        .reduce(|a, b| a.intersection(&b).copied().collect());
    runs.iter()
        .map(|(name, run)| {
            let (good, false_reads, corner_errs) = &tallies[name];
            let mut s = Scores {
                frames: run.frames.len(),
                present: present.len(),
                read: good.intersection(&present).count(),
                unconfirmed: good.difference(&present).count(),
                false_reads: *false_reads,
                corner_err_px_median: median(corner_errs),
                detect_ms_mean: (!run.detect_ms.is_empty())
                    .then(|| run.detect_ms.iter().sum::<f64>() / run.detect_ms.len() as f64),
                ..Scores::default()
            };
            s.recall = (s.present > 0).then(|| s.read as f64 / s.present as f64);
            if let Some(d) = distances.get(name) {
                let ratios: Vec<f64> = d.values().map(|p| p.measured / p.known).collect();
                s.pairs = ratios.len();
                s.distance_ratio_median = median(&ratios);
                s.distance_ratio_iqr = iqr(&ratios);
                s.distance_ratio_iqr_present = iqr(&present_ratios(d, &present));
                if m.video.is_some() {
                    s.jitter_mm_median = jitter_mm(d, None);
                    s.jitter_mm_median_common = jitter_mm(d, common.as_ref());
                    s.jitter_mm_median_present = jitter_mm(d, Some(&present_pairs(d, &present)));
                    let nees = jitter_nees(d);
                    s.jitter_nees_steps = nees.len();
                    s.jitter_nees_mean =
                        (!nees.is_empty()).then(|| nees.iter().sum::<f64>() / nees.len() as f64);
                    s.jitter_nees_median = median(&nees);
                }
            }
            if let Truth::RotationSteps { id, angle_deg } = &m.truth {
                s.rotation_err_deg_median = median(&rotation_errors(*id, angle_deg, run, false));
                s.rotation_err_deg_median_flip_resolved =
                    median(&rotation_errors(*id, angle_deg, run, true));
            }
            (name.clone(), s)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Isometry3, Translation3, UnitQuaternion};

    fn read(id: u32, x: f64, sigma_m: Option<f64>) -> Read {
        Read {
            id,
            outer_px: Vec::new(),
            camera_from_marker: Some(Isometry3::from_parts(
                Translation3::new(x, 0.0, 1.0),
                UnitQuaternion::identity(),
            )),
            alternative: None,
            // Stretched across the line between the tags, which must not count.
            position_cov: sigma_m.map(|s| Matrix3::from_diagonal(&[s * s, 9.0, 9.0].into())),
        }
    }

    #[test]
    fn the_present_spread_and_jitter_leave_out_pairs_with_an_unconfirmed_read() {
        let pair = |measured: f64| PairDistance {
            measured,
            known: 1.0,
            variance: None,
        };
        // Frame 0: tags 1 and 2 present; frame 1: tag 2 a read no one confirms.
        let d: BTreeMap<(usize, u32, u32), PairDistance> = [
            ((0, 1, 2), pair(1.01)),
            ((1, 1, 2), pair(1.9)),
            ((1, 1, 3), pair(0.99)),
        ]
        .into();
        let present: BTreeSet<(usize, u32)> = [(0, 1), (0, 2), (1, 1), (1, 3)].into();
        let mut kept = present_ratios(&d, &present);
        kept.sort_by(f64::total_cmp);
        assert_eq!(kept, vec![0.99, 1.01]);
        let pairs: Vec<_> = present_pairs(&d, &present).into_iter().collect();
        assert_eq!(pairs, vec![(0, 1, 2), (1, 1, 3)]);
        // The jitter over those: the pair 1–2 has no present step to change from.
        assert_eq!(jitter_mm(&d, Some(&present_pairs(&d, &present))), None);
        assert!(jitter_mm(&d, None).is_some());
        assert!(iqr(&[1.0, 1.0, 1.0, 2.0]).is_some_and(|r| r > 0.0));
    }

    #[test]
    fn an_id_read_twice_in_a_frame_is_not_paired_and_counts_as_a_false_read() {
        let centres: BTreeMap<u32, [f64; 3]> = [
            (1, [0.0, 0.0, 0.0]),
            (2, [0.5, 0.0, 0.0]),
            (3, [1.0, 0.0, 0.0]),
        ]
        .into();
        let run = MethodRun {
            frames: vec![(
                0,
                "0".into(),
                vec![
                    read(1, 0.0, None),
                    read(2, 0.5, None),
                    read(2, 0.9, None),
                    read(3, 1.0, None),
                ],
            )],
            detect_ms: Vec::new(),
        };
        let d = pair_distances(&centres, &run);
        assert_eq!(d.keys().copied().collect::<Vec<_>>(), vec![(0, 1, 3)]);
        // Scored: tag 2 read once, and once as a false read (so is an ID
        // the layout does not know, 9); in the next frame tag 2 again.
        let m: Manifest = serde_json::from_value(serde_json::json!({
            "name": "layout", "underwater": false, "codes": "apriltag16h5", "side_m": 0.1,
            "images": ["0", "1"], "splits": {"dev": [0, 2]},
            "truth": {"layout": {"centres_m": {"1": [0.0, 0.0, 0.0], "2": [0.5, 0.0, 0.0], "3": [1.0, 0.0, 0.0]}}}
        }))
        .unwrap();
        let mut run = run;
        run.frames[0].2.push(read(9, 2.0, None));
        run.frames.push((1, "1".into(), vec![read(2, 0.5, None)]));
        let (good, false_reads, _) = tally(&m, &run);
        assert_eq!(good, [(0, 1), (0, 2), (0, 3), (1, 2)].into());
        assert_eq!(false_reads, 2);
    }

    #[test]
    fn the_jitter_nees_weighs_each_step_by_the_stated_variance_along_the_pair() {
        let centres: BTreeMap<u32, [f64; 3]> = [(1, [0.0, 0.0, 0.0]), (2, [0.5, 0.0, 0.0])].into();
        let frame = |idx: usize, d: f64, sigma: [Option<f64>; 2]| {
            (
                idx,
                format!("{idx}"),
                vec![read(2, d, sigma[1]), read(1, 0.0, sigma[0])],
            )
        };
        let s = Some(0.001);
        let run = MethodRun {
            frames: vec![
                frame(0, 0.500, [s, s]),
                // 2 mm against σ_d² = 2·(1 mm)² each frame: NEES 4e-6 / 4e-6 = 1.
                frame(1, 0.502, [s, s]),
                // 4 mm: 16e-6 / 4e-6 = 4.
                frame(2, 0.498, [s, s]),
                // No stated covariance on one tag: the steps on either side of it are left out.
                frame(3, 0.498, [s, None]),
                frame(4, 0.530, [s, s]),
            ],
            detect_ms: Vec::new(),
        };
        let d = pair_distances(&centres, &run);
        assert_eq!(d.len(), 5);
        assert!((d[&(1, 1, 2)].variance.unwrap() - 2e-6).abs() < 1e-15);
        assert!(d[&(3, 1, 2)].variance.is_none());
        let nees = jitter_nees(&d);
        assert_eq!(nees.len(), 2, "{nees:?}");
        assert!(
            (nees[0] - 1.0).abs() < 1e-6 && (nees[1] - 4.0).abs() < 1e-6,
            "{nees:?}"
        );
        // The jitter itself still takes every step: 2, 4, 0 and 32 mm.
        assert!((jitter_mm(&d, None).unwrap() - 3.0).abs() < 1e-6);
    }
}
