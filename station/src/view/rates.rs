//! Camera health from a node's status reports: rates over a window of
//! reports, and per-frame latency.

use proto::NodeStatus;
use serde::Serialize;

/// One camera's health, from two successive status reports of its node.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct CameraView {
    pub camera: u8,
    pub name: String,
    /// Frames per second over the interval between the two reports (the
    /// node's own figure for its last period when there is no earlier report).
    pub frame_rate_hz: f64,
    /// Detections per second over the interval between the two reports
    /// (`None` for the first report of a node).
    pub detection_rate_hz: Option<f64>,
    /// Detections per processed frame over that interval.
    pub detections_per_frame: Option<f64>,
    /// Restoration + detection + pose, mean per frame of the newest report
    /// period that had frames, milliseconds (`None`: no frame yet).
    pub latency_ms: Option<f64>,
    pub frames_dropped: u64,
    pub frames_invalid: u64,
}

/// Per-camera figures from the newest status `current` and, when there is
/// one, the node's previous report `previous` (rates are differences of the
/// counters over the reports' uptime difference; a restarted node, whose
/// counters went backwards, gets no rate until its next report).
pub fn camera_views(previous: Option<&NodeStatus>, current: &NodeStatus) -> Vec<CameraView> {
    current
        .cameras
        .iter()
        .map(|c| {
            let before = previous
                .filter(|p| p.uptime_s < current.uptime_s)
                .and_then(|p| p.cameras.iter().find(|pc| pc.camera == c.camera))
                .filter(|pc| pc.detections <= c.detections && pc.frames_in <= c.frames_in);
            let dt_s = previous.map_or(0.0, |p| current.uptime_s - p.uptime_s);
            let (fps, rate, per_frame) = match before {
                Some(pc) if dt_s > 0.0 => {
                    let det = (c.detections - pc.detections) as f64;
                    let frames = (c.frames_in - pc.frames_in) as f64;
                    (
                        frames / dt_s,
                        Some(det / dt_s),
                        (frames > 0.0).then_some(det / frames),
                    )
                }
                _ => (f64::from(c.frame_rate_hz), None, None),
            };
            CameraView {
                camera: c.camera,
                name: c.name.clone(),
                frame_rate_hz: fps,
                detection_rate_hz: rate,
                detections_per_frame: per_frame,
                latency_ms: None,
                frames_dropped: c.frames_dropped,
                frames_invalid: c.frames_invalid,
            }
        })
        .collect()
}

/// Status reports of a node over which camera rates are averaged: a node
/// reports every second, and at the demo's 0.5 frames per wall-clock
/// second a one-second figure flickers between 0 and 1.
pub const RATE_WINDOW_REPORTS: usize = 6;

/// A node's newest status reports (oldest first), and the newest's age.
#[derive(Debug, Clone, Default)]
pub struct NodeReports {
    pub window: std::collections::VecDeque<NodeStatus>,
    /// Seconds since the newest report arrived (wall clock of the station).
    pub age_s: f64,
}

impl NodeReports {
    pub fn push(&mut self, status: NodeStatus) {
        // A restarted node starts a new window (its counters start again).
        if self
            .window
            .back()
            .is_some_and(|last| status.uptime_s < last.uptime_s)
        {
            self.window.clear();
        }
        self.window.push_back(status);
        while self.window.len() > RATE_WINDOW_REPORTS {
            self.window.pop_front();
        }
        self.age_s = 0.0;
    }

    pub fn current(&self) -> Option<&NodeStatus> {
        self.window.back()
    }

    /// Per-camera figures over the window (see [`camera_views`]), with each
    /// camera's latency from the newest report whose period had frames (a
    /// period without frames reports 0 ms).
    pub fn camera_views(&self) -> Vec<CameraView> {
        let Some(current) = self.current() else {
            return Vec::new();
        };
        let mut views = camera_views(self.oldest(), current);
        for v in &mut views {
            v.latency_ms = self.window.iter().rev().find_map(|s| {
                s.cameras
                    .iter()
                    .find(|c| c.camera == v.camera)
                    .map(|c| f64::from(c.restore_ms + c.detect_ms + c.pose_ms))
                    .filter(|&ms| ms > 0.0)
            });
        }
        views
    }

    /// The oldest report of the window, when there are at least two.
    pub fn oldest(&self) -> Option<&NodeStatus> {
        (self.window.len() >= 2).then(|| &self.window[0])
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::view::fixtures::status;

    #[test]
    fn camera_rates_come_from_successive_reports() {
        let first = camera_views(None, &status(10.0, 20, 10));
        assert_eq!(first[0].detection_rate_hz, None);
        let v = camera_views(Some(&status(10.0, 20, 10)), &status(12.0, 24, 14));
        assert!((v[0].frame_rate_hz - 2.0).abs() < 1e-12, "{v:?}");
        assert!(
            (v[0].detection_rate_hz.unwrap() - 2.0).abs() < 1e-12,
            "{v:?}"
        );
        assert!(
            (v[0].detections_per_frame.unwrap() - 1.0).abs() < 1e-12,
            "{v:?}"
        );
        // A restarted node (counters and uptime went back) gets no rate.
        let v = camera_views(Some(&status(30.0, 60, 50)), &status(1.0, 2, 1));
        assert_eq!(v[0].detection_rate_hz, None);
    }

    #[test]
    fn rates_average_over_a_window_of_reports_and_restart_with_the_node() {
        let mut r = NodeReports::default();
        for k in 0..10u64 {
            // One frame every other second: per-report figures flicker, the window does not.
            r.push(status(k as f64, k / 2, k / 2));
        }
        assert_eq!(r.window.len(), RATE_WINDOW_REPORTS);
        let v = camera_views(r.oldest(), r.current().unwrap());
        assert!((v[0].frame_rate_hz - 0.4).abs() < 1e-12, "{v:?}");
        // Latency from the newest report with frames, not a frameless period's 0.
        let mut idle = status(10.0, 5, 5);
        idle.cameras[0].restore_ms = 0.0;
        idle.cameras[0].detect_ms = 0.0;
        idle.cameras[0].pose_ms = 0.0;
        r.push(idle);
        assert_eq!(r.camera_views()[0].latency_ms, Some(31.5));
        r.push(status(0.5, 0, 0));
        assert_eq!(r.window.len(), 1, "a restarted node starts a new window");
        assert!(r.oldest().is_none());
    }
}
