//! Which fused map the page shows, and the ground truth it is compared with.

use proto::{FleetMap, SimTruth};

/// Ground truth and a map are of the same instant when their stamps differ by
/// at most this (both come from the simulator's clock, so they are equal).
pub const TRUTH_MATCH_NS: u64 = 1_000_000;

/// The instant a map's estimates describe: its newest accepted observation's
/// capture stamp (the map's own stamp when it has none) — the same instant
/// `shoal demo` scores against (`src/demo.rs`, `pair_errors`).
pub fn valid_at_ns(map: &FleetMap) -> u64 {
    map.edges
        .iter()
        .filter(|e| e.rejected.is_none())
        .map(|e| e.stamp_ns)
        .max()
        .unwrap_or(map.stamp_ns)
}

/// The map to show and the ground truth to compare it with. Without truth
/// (a real trial) that is the newest map. In simulation the truth of a tick
/// arrives after its frames are rendered, so the newest map is often a
/// tick ahead of the newest truth: the newest map that *has* its truth is
/// shown instead (a lag of one rendering time), so that the error is not
/// inflated by the swarm's motion over a tick. A map is paired with the
/// truth of [`valid_at_ns`]. `maps` and `truths` are
/// oldest first.
pub fn pair_map_with_truth<'a, M>(
    maps: &'a [(FleetMap, M)],
    truths: &'a [SimTruth],
) -> (Option<&'a (FleetMap, M)>, Option<&'a SimTruth>) {
    let newest = maps.last();
    if truths.is_empty() {
        return (newest, None);
    }
    for m in maps.iter().rev() {
        let at = valid_at_ns(&m.0);
        if let Some(t) = nearest_truth(truths, at) {
            if t.stamp_ns.abs_diff(at) <= TRUTH_MATCH_NS {
                return (Some(m), Some(t));
            }
        }
    }
    // No map has its truth yet: the newest map, with the nearest truth.
    (
        newest,
        newest.and_then(|m| nearest_truth(truths, m.0.stamp_ns)),
    )
}

/// Of `truths` (any order), the one whose stamp is nearest `stamp_ns`.
pub fn nearest_truth<'a>(
    truths: impl IntoIterator<Item = &'a SimTruth>,
    stamp_ns: u64,
) -> Option<&'a SimTruth> {
    truths
        .into_iter()
        .min_by_key(|t| t.stamp_ns.abs_diff(stamp_ns))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::view::fixtures::{edge, truth_of};
    use proto::RejectReason;

    #[test]
    fn map_shown_is_the_newest_with_its_own_truth() {
        let maps: Vec<(FleetMap, ())> = [1, 2, 2, 3]
            .iter()
            .enumerate()
            .map(|(i, &s)| {
                let mut m = FleetMap {
                    fleet: "paper".into(),
                    producer: "central".into(),
                    seq: i as u64,
                    stamp_ns: s * 1_000_000_000,
                    reference: 10,
                    vehicles: vec![],
                    edges: vec![],
                    solve_time_us: 0,
                };
                m.seq = i as u64;
                (m, ())
            })
            .collect();
        let truths: Vec<SimTruth> = [1, 2].map(|s| truth_of(&[], s * 1_000_000_000)).into();
        // Map 3 (stamp 3 s) has no truth yet: the newest map of 2 s (seq 2) is shown.
        let (m, t) = pair_map_with_truth(&maps, &truths);
        assert_eq!((m.unwrap().0.seq, t.unwrap().stamp_ns), (2, 2_000_000_000));
        // Without truth at all, the newest map.
        let (m, t) = pair_map_with_truth(&maps, &[]);
        assert_eq!((m.unwrap().0.seq, t), (3, None));
        // A map stamped 3 s whose newest accepted observation is of 2 s is valid at 2 s.
        let mut late = maps[3].clone();
        late.0.edges = vec![
            edge(10, 15, None, 1.0),
            edge(10, 17, Some(RejectReason::Stale), 1.0),
        ];
        late.0.edges[0].stamp_ns = 2_000_000_000;
        late.0.edges[1].stamp_ns = 3_000_000_000;
        assert_eq!(valid_at_ns(&late.0), 2_000_000_000);
        let with_late = [maps[0].clone(), late];
        let (m, t) = pair_map_with_truth(&with_late, &truths);
        assert_eq!((m.unwrap().0.seq, t.unwrap().stamp_ns), (3, 2_000_000_000));
        // Truth only from long ago: newest map, nearest truth.
        let old = [truth_of(&[], 0)];
        let (m, t) = pair_map_with_truth(&maps[3..], &old);
        assert_eq!((m.unwrap().0.seq, t.unwrap().stamp_ns), (3, 0));
    }

    #[test]
    fn nearest_truth_matches_the_map_stamp() {
        let ts: Vec<SimTruth> = [1, 2, 3, 4]
            .map(|s| truth_of(&[], s * 1_000_000_000))
            .into();
        assert_eq!(
            nearest_truth(&ts, 2_400_000_000).unwrap().stamp_ns,
            2_000_000_000
        );
        assert_eq!(
            nearest_truth(&ts, 9_000_000_000).unwrap().stamp_ns,
            4_000_000_000
        );
        assert!(nearest_truth(&[], 0).is_none());
    }
}
