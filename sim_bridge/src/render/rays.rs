//! The exact viewing rays of a camera's pixel centres and pixel corners,
//! computed once per camera (row by row, as regions of interest first need
//! them) and reused by every later frame of that camera.
//!
//! Each ray is [`trace::ray_from`]'s Newton solution of the lens model
//! (exact to ~1e-13 in normalized units), so a table lookup is the same ray
//! the renderer would otherwise solve for at every pixel of every frame.

use super::trace;
use shoal_proto::CameraModel;

/// One row of rays, `(x, y)` of the in-air direction `(x, y, 1)`.
type Row = Box<[(f64, f64)]>;

/// Lazily filled ray rows of one camera model.
#[derive(Debug, Default)]
pub(super) struct RayTable {
    cam: Option<CameraModel>,
    /// Corner row `y` is at `v = y − ½` (`0..=h`), its rays at `u = x − ½` (`0..=w`).
    corners: Vec<Option<Row>>,
    /// Centre row `y` is at `v = y`, its rays at `u = x` (`0..w`).
    centres: Vec<Option<Row>>,
}

impl RayTable {
    /// Make the table describe `cam` (dropping the rows of another camera)
    /// and fill the rows pixel rows `rows` need, on up to `threads` threads.
    pub(super) fn prepare(&mut self, cam: &CameraModel, rows: &[bool], threads: usize) {
        let h = cam.height as usize;
        if self.cam.as_ref() != Some(cam) {
            self.cam = Some(*cam);
            self.corners = vec![None; h + 1];
            self.centres = vec![None; h];
        }
        // (is a corner row, row index) of every missing row.
        let mut missing: Vec<(bool, usize)> = Vec::new();
        for (y, _) in rows.iter().enumerate().take(h).filter(|(_, &r)| r) {
            for cy in [y, y + 1] {
                if self.corners[cy].is_none() && !missing.contains(&(true, cy)) {
                    missing.push((true, cy));
                }
            }
            if self.centres[y].is_none() {
                missing.push((false, y));
            }
        }
        if missing.is_empty() {
            return;
        }
        let computed: Vec<((bool, usize), Row)> =
            super::par::map_chunks(&missing, threads, |&(corner, y)| {
                ((corner, y), ray_row(cam, corner, y))
            });
        for ((corner, y), row) in computed {
            if corner {
                self.corners[y] = Some(row);
            } else {
                self.centres[y] = Some(row);
            }
        }
    }

    /// The corner rays of pixel row `y` above (`bottom` false) or below it,
    /// `w + 1` of them; [`RayTable::prepare`] must have filled that row.
    #[inline]
    pub(super) fn corner_row(&self, y: usize, bottom: bool) -> &[(f64, f64)] {
        let r = if bottom { y + 1 } else { y };
        self.corners[r]
            .as_deref()
            .expect("ray table row prepared before casting")
    }

    /// The centre rays of pixel row `y` (`w` of them), prepared.
    #[inline]
    pub(super) fn centre_row(&self, y: usize) -> &[(f64, f64)] {
        self.centres[y]
            .as_deref()
            .expect("ray table row prepared before casting")
    }
}

/// One full row of rays: corners (`v = y − ½`, `u = −½ … w − ½`) or centres
/// (`v = y`, `u = 0 … w − 1`). Each Newton solve starts from the linear
/// extrapolation of the two previous rays, so it converges in one step.
fn ray_row(cam: &CameraModel, corner: bool, y: usize) -> Row {
    let w = cam.width as usize;
    let (shift, n) = if corner { (-0.5, w + 1) } else { (0.0, w) };
    let v = y as f64 + shift;
    let first = cam.ray(shift, v);
    let (mut prev, mut last) = (first, first);
    (0..n)
        .map(|x| {
            let guess = (2.0 * last.0 - prev.0, 2.0 * last.1 - prev.1);
            let r = trace::ray_from(cam, x as f64 + shift, v, guess);
            prev = if x == 0 { r } else { last };
            last = r;
            r
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Point3;

    #[test]
    fn table_rays_project_back_onto_their_pixels() {
        let cam = CameraModel::vehicle_1440();
        let mut rows = vec![false; cam.height as usize];
        for y in [0, 539, 1079] {
            rows[y] = true;
        }
        let mut t = RayTable::default();
        t.prepare(&cam, &rows, 2);
        for y in [0usize, 539, 1079] {
            for (x, &(rx, ry)) in t.centre_row(y).iter().enumerate() {
                let p = cam.project(&Point3::new(rx, ry, 1.0)).unwrap();
                assert!((p.x - x as f64).abs() < 1e-9 && (p.y - y as f64).abs() < 1e-9);
            }
            for bottom in [false, true] {
                let v = y as f64 + if bottom { 0.5 } else { -0.5 };
                for (x, &(rx, ry)) in t.corner_row(y, bottom).iter().enumerate() {
                    let p = cam.project(&Point3::new(rx, ry, 1.0)).unwrap();
                    assert!((p.x - (x as f64 - 0.5)).abs() < 1e-9 && (p.y - v).abs() < 1e-9);
                }
            }
        }
        // Another camera replaces the rows.
        let other = CameraModel { fx: 1000.0, ..cam };
        t.prepare(&other, &rows, 1);
        let (rx, ry) = t.centre_row(539)[0];
        let p = other.project(&Point3::new(rx, ry, 1.0)).unwrap();
        assert!((p.x - 0.0).abs() < 1e-9 && (p.y - 539.0).abs() < 1e-9);
    }
}
