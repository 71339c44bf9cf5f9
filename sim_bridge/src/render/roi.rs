//! Regions of interest: the pixel bounds of each marker plate and hull
//! (only those pixels are ray-cast) and the groups of them that share one
//! forward-scatter PSF.

use super::optics::{Psf, Rect};
use super::trace::{Hull, Plate};
use crate::water::WaterParams;
use nalgebra::{Point3, Vector3};
use shoal_proto::{CameraModel, FlatPort};

/// Everything known about one object before ray casting.
#[derive(Debug, Clone)]
pub(super) struct Roi {
    pub(super) rect: Rect,
    /// Range for the object's PSF (m).
    pub(super) range_m: f64,
    /// Always supersample (features smaller than a few pixels).
    pub(super) fine: bool,
}

/// Smallest depth a ROI sample may have; nearer surfaces are clipped there.
pub(super) const ROI_NEAR_M: f64 = 1e-3;

/// Pixel bounds of a set of camera-frame points, with the segments given
/// as index pairs clipped at the near plane (a clipped point projects far
/// out, extending the ROI to the image border on its side).
fn roi_of(
    cam: &CameraModel,
    port: Option<&FlatPort>,
    pts: &[Point3<f64>],
    segments: &[(usize, usize)],
    margin_frac: f64,
) -> Option<Rect> {
    let (w, h) = (cam.width as f64, cam.height as f64);
    let (mut u0, mut v0, mut u1, mut v1) = (
        f64::INFINITY,
        f64::INFINITY,
        f64::NEG_INFINITY,
        f64::NEG_INFINITY,
    );
    // Behind a port nothing nearer than its outer surface is seen.
    let near = ROI_NEAR_M + port.map_or(0.0, FlatPort::outer_z);
    let mut add = |p: &Point3<f64>| {
        // The in-air ray's slope (through the port when there is one).
        let (xn, yn) = match port {
            None => (p.x / p.z, p.y / p.z),
            // No ray reaches it (past a bare port's critical angle): far off-screen.
            Some(port) => port.air_ray(p).unwrap_or((p.x * 1e9, p.y * 1e9)),
        };
        // Outside the lens model's sane range, clamp the direction to far off-screen.
        let lim = 4.0;
        let (u, v) = if xn.abs() > lim || yn.abs() > lim {
            (
                if xn > 0.0 {
                    1e9
                } else if xn < 0.0 {
                    -1e9
                } else {
                    cam.cx
                },
                if yn > 0.0 {
                    1e9
                } else if yn < 0.0 {
                    -1e9
                } else {
                    cam.cy
                },
            )
        } else {
            let q = match port {
                None => cam.project(p),
                Some(_) => cam.project(&Point3::new(xn, yn, 1.0)),
            }
            .unwrap_or(Point3::new(cam.cx, cam.cy, 1.0).xy());
            (q.x, q.y)
        };
        u0 = u0.min(u);
        v0 = v0.min(v);
        u1 = u1.max(u);
        v1 = v1.max(v);
    };
    for p in pts.iter().filter(|p| p.z > near) {
        add(p);
    }
    for &(a, b) in segments {
        let (pa, pb) = (pts[a], pts[b]);
        if (pa.z > near) != (pb.z > near) {
            let t = (near * 1.0001 - pa.z) / (pb.z - pa.z);
            add(&(pa + (pb - pa) * t));
        }
    }
    if !u0.is_finite() {
        return None;
    }
    let margin = 2.0 + margin_frac * (u1 - u0).max(v1 - v0).min(w.max(h));
    let (u0, v0, u1, v1) = (u0 - margin, v0 - margin, u1 + margin, v1 + margin);
    if u1 < -0.5 || v1 < -0.5 || u0 > w - 0.5 || v0 > h - 0.5 {
        return None;
    }
    Some(Rect {
        x0: u0.max(0.0).floor() as usize,
        y0: v0.max(0.0).floor() as usize,
        x1: (u1.min(w - 1.0).ceil() as usize).min(cam.width as usize - 1),
        y1: (v1.min(h - 1.0).ceil() as usize).min(cam.height as usize - 1),
    })
}

/// A grid of points over the plate and its mesh segments.
pub(super) fn plate_roi(cam: &CameraModel, port: Option<&FlatPort>, p: &Plate) -> Option<Roi> {
    let k = 16usize;
    let mut pts = Vec::with_capacity((k + 1) * (k + 1));
    let mut segs = Vec::new();
    for j in 0..=k {
        for i in 0..=k {
            let a = -p.half_m + 2.0 * p.half_m * i as f64 / k as f64;
            let b = -p.half_m + 2.0 * p.half_m * j as f64 / k as f64;
            pts.push(Point3::from(p.origin + p.ex * a + p.ey * b));
            let idx = j * (k + 1) + i;
            if i < k {
                segs.push((idx, idx + 1));
            }
            if j < k {
                segs.push((idx, idx + k + 1));
            }
        }
    }
    let rect = roi_of(cam, port, &pts, &segs, 0.01)?;
    let depth = p.origin.z.max(ROI_NEAR_M);
    let module_px = cam.fx.min(cam.fy) * p.module_m / depth;
    Some(Roi {
        rect,
        range_m: p.origin.norm(),
        fine: module_px < 3.0,
    })
}

/// Rings of points along the hull (48 around, 17 along) and its mesh segments.
pub(super) fn hull_roi(cam: &CameraModel, port: Option<&FlatPort>, hl: &Hull) -> Option<Roi> {
    let (na, nl) = (48usize, 16usize);
    let e1 = hl
        .axis
        .cross(&Vector3::x())
        .try_normalize(1e-9)
        .unwrap_or_else(|| hl.axis.cross(&Vector3::y()).normalize());
    let e2 = hl.axis.cross(&e1);
    let mut pts = Vec::with_capacity((na + 1) * (nl + 1));
    let mut segs = Vec::new();
    for j in 0..=nl {
        let s = -hl.half_len + 2.0 * hl.half_len * j as f64 / nl as f64;
        // Centre of each ring too, so the end caps are covered.
        let c = hl.center + hl.axis * s;
        pts.push(Point3::from(c));
        let base = pts.len();
        for i in 0..na {
            let a = std::f64::consts::TAU * i as f64 / na as f64;
            pts.push(Point3::from(c + (e1 * a.cos() + e2 * a.sin()) * hl.radius));
        }
        for i in 0..na {
            segs.push((base + i, base + (i + 1) % na));
            segs.push((base - 1, base + i));
            if j < nl {
                segs.push((base + i, base + i + na + 1));
            }
        }
    }
    let rect = roi_of(cam, port, &pts, &segs, 0.02)?;
    // Range for the PSF: nearest point of the axis segment, at least a radius.
    let s = (-hl.center).dot(&hl.axis).clamp(-hl.half_len, hl.half_len);
    let range_m = (hl.center + hl.axis * s).norm().max(hl.radius);
    let depth = (hl.center + hl.axis * s).z.max(ROI_NEAR_M);
    let diameter_px = cam.fx.min(cam.fy) * 2.0 * hl.radius / depth;
    Some(Roi {
        rect,
        range_m,
        fine: diameter_px < 4.0,
    })
}

/// Groups of overlapping ROIs (after dilating each by its PSF radius), each
/// with one PSF range: the area-weighted mean of its members' ranges.
pub(super) fn psf_groups(
    cam: &CameraModel,
    water: &WaterParams,
    rois: &[Option<Roi>],
) -> Vec<(Rect, f64)> {
    let (w, h) = (cam.width as usize, cam.height as usize);
    let f = 0.5 * (cam.fx + cam.fy);
    let mut groups: Vec<(Rect, f64, f64)> = Vec::new(); // rect, Σ area·range, Σ area
    for r in rois.iter().flatten() {
        let margin = Psf::for_range(water, f, r.range_m).radius_px().ceil() as usize;
        let rect = r.rect.dilated(margin, w, h);
        let area = (r.rect.width() * r.rect.height()) as f64;
        groups.push((rect, area * r.range_m, area));
    }
    loop {
        let mut merged = false;
        'outer: for i in 0..groups.len() {
            for j in i + 1..groups.len() {
                if groups[i].0.overlaps(&groups[j].0) {
                    let g = groups.swap_remove(j);
                    groups[i] = (
                        groups[i].0.union(&g.0),
                        groups[i].1 + g.1,
                        groups[i].2 + g.2,
                    );
                    merged = true;
                    break 'outer;
                }
            }
        }
        if !merged {
            break;
        }
    }
    groups
        .into_iter()
        .map(|(r, ar, a)| (r, ar / a.max(1e-12)))
        .collect()
}
