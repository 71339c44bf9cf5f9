//! Small plane geometry for the detector: 4-point homographies, lines, quads.

use nalgebra::{Matrix3, SMatrix, SVector, Vector3};

/// A point in pixels (`[x, y]`).
pub type Px = [f64; 2];

/// The homography `H` with `dst_i ~ H · src_i` for four correspondences, or
/// `None` when they are degenerate (three collinear points).
pub fn homography_4(src: &[Px; 4], dst: &[Px; 4]) -> Option<Matrix3<f64>> {
    let mut a = SMatrix::<f64, 8, 8>::zeros();
    let mut b = SVector::<f64, 8>::zeros();
    for i in 0..4 {
        let [x, y] = src[i];
        let [u, v] = dst[i];
        let r = 2 * i;
        a.row_mut(r)
            .copy_from_slice(&[x, y, 1.0, 0.0, 0.0, 0.0, -u * x, -u * y]);
        a.row_mut(r + 1)
            .copy_from_slice(&[0.0, 0.0, 0.0, x, y, 1.0, -v * x, -v * y]);
        b[r] = u;
        b[r + 1] = v;
    }
    let h = a.lu().solve(&b)?;
    if !h.iter().all(|v| v.is_finite()) {
        return None;
    }
    Some(Matrix3::new(
        h[0], h[1], h[2], h[3], h[4], h[5], h[6], h[7], 1.0,
    ))
}

/// Apply a homography to a point.
#[inline]
pub fn apply(h: &Matrix3<f64>, p: Px) -> Px {
    let q = h * Vector3::new(p[0], p[1], 1.0);
    [q.x / q.z, q.y / q.z]
}

/// Twice the signed area (shoelace); positive for a quad that is clockwise
/// as seen in an image with y pointing down.
pub fn signed_area2(q: &[Px; 4]) -> f64 {
    (0..4)
        .map(|i| {
            let a = q[i];
            let b = q[(i + 1) % 4];
            a[0] * b[1] - b[0] * a[1]
        })
        .sum()
}

pub fn dist(a: Px, b: Px) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2)).sqrt()
}

/// Mean side length of a quad.
/// Mean of the four corners.
pub fn centre(q: &[Px; 4]) -> Px {
    let s = q.iter().fold([0.0, 0.0], |a, c| [a[0] + c[0], a[1] + c[1]]);
    [s[0] / 4.0, s[1] / 4.0]
}

pub fn mean_side(q: &[Px; 4]) -> f64 {
    (0..4).map(|i| dist(q[i], q[(i + 1) % 4])).sum::<f64>() / 4.0
}

/// Shortest side length of a quad.
pub fn min_side(q: &[Px; 4]) -> f64 {
    (0..4)
        .map(|i| dist(q[i], q[(i + 1) % 4]))
        .fold(f64::INFINITY, f64::min)
}

/// A line `n · p = d` with unit normal `n`.
#[derive(Debug, Clone, Copy)]
pub struct Line {
    pub n: [f64; 2],
    pub d: f64,
}

impl Line {
    /// Total-least-squares line through weighted points; `None` if fewer than 2 or degenerate.
    pub fn fit(pts: &[(Px, f64)]) -> Option<Line> {
        let wsum: f64 = pts.iter().map(|p| p.1).sum();
        if pts.len() < 2 || wsum <= 0.0 {
            return None;
        }
        let mx = pts.iter().map(|(p, w)| p[0] * w).sum::<f64>() / wsum;
        let my = pts.iter().map(|(p, w)| p[1] * w).sum::<f64>() / wsum;
        let (mut sxx, mut sxy, mut syy) = (0.0, 0.0, 0.0);
        for (p, w) in pts {
            let (dx, dy) = (p[0] - mx, p[1] - my);
            sxx += w * dx * dx;
            sxy += w * dx * dy;
            syy += w * dy * dy;
        }
        // Direction = eigenvector of the larger eigenvalue; normal is perpendicular.
        let theta = 0.5 * (2.0 * sxy).atan2(sxx - syy);
        let n = [-theta.sin(), theta.cos()];
        if !(n[0].is_finite() && n[1].is_finite()) {
            return None;
        }
        Some(Line {
            n,
            d: n[0] * mx + n[1] * my,
        })
    }

    pub fn through(a: Px, b: Px) -> Option<Line> {
        let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
        let l = (dx * dx + dy * dy).sqrt();
        if l < 1e-12 {
            return None;
        }
        let n = [-dy / l, dx / l];
        Some(Line {
            n,
            d: n[0] * a[0] + n[1] * a[1],
        })
    }

    pub fn distance(&self, p: Px) -> f64 {
        self.n[0] * p[0] + self.n[1] * p[1] - self.d
    }

    pub fn intersect(&self, o: &Line) -> Option<Px> {
        let det = self.n[0] * o.n[1] - self.n[1] * o.n[0];
        if det.abs() < 1e-9 {
            return None;
        }
        Some([
            (self.d * o.n[1] - self.n[1] * o.d) / det,
            (self.n[0] * o.d - self.d * o.n[0]) / det,
        ])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn homography_maps_the_four_points() {
        let src = [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]];
        let dst = [[10.0, 12.0], [50.0, 8.0], [55.0, 60.0], [8.0, 49.0]];
        let h = homography_4(&src, &dst).unwrap();
        for i in 0..4 {
            assert!(dist(apply(&h, src[i]), dst[i]) < 1e-9);
        }
        let degenerate = [[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [0.0, 1.0]];
        assert!(
            homography_4(&degenerate, &dst).is_none() || homography_4(&src, &degenerate).is_none()
        );
    }

    #[test]
    fn line_fit_and_intersection() {
        let pts: Vec<(Px, f64)> = (0..10)
            .map(|i| ([i as f64, 2.0 * i as f64 + 1.0], 1.0))
            .collect();
        let l = Line::fit(&pts).unwrap();
        assert!(l.distance([3.0, 7.0]).abs() < 1e-9);
        let v = Line::through([5.0, -10.0], [5.0, 10.0]).unwrap();
        let p = l.intersect(&v).unwrap();
        assert!(dist(p, [5.0, 11.0]) < 1e-9);
    }

    #[test]
    fn clockwise_in_image_has_positive_area() {
        let q = [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]];
        assert!(signed_area2(&q) > 0.0);
    }
}
