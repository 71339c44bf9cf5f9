//! Ray casting of the pixels inside the regions of interest: the corner
//! lattice, the pixel classes (uniform patch, plate edge with exact module
//! coverage, supersampled), and the water terms of each sample.

use super::roi::Roi;
use super::trace::{self, Hit, Objects};
use super::Renderer;
use crate::render::optics::LampIntegral;
use shoal_proto::CameraModel;

/// Per-pixel accumulators of the ray-cast part (see `docs/water-model.md`).
#[derive(Debug, Default, Clone, Copy)]
pub(super) struct Sample {
    clean: f64,
    direct: f64,
    scatter: f64,
    veil: f64,
    lamp: f64,
}

/// Water terms that are constant for a frame.
#[derive(Debug, Clone)]
pub(super) struct Medium {
    pub(super) c: f64,
    pub(super) s: f64,
    pub(super) illum: f64,
    pub(super) lamp_power: f64,
    pub(super) lamp: LampIntegral,
}

impl Medium {
    #[inline]
    fn sample(&self, hit: Option<Hit>) -> Sample {
        match hit {
            None => Sample {
                clean: 0.0,
                direct: 0.0,
                scatter: 0.0,
                veil: 1.0,
                lamp: 1.0,
            },
            Some(h) => {
                let r = h.range;
                let tr = (-self.c * r).exp();
                let lamp_in = if self.lamp_power > 0.0 {
                    self.lamp_power * h.lamp_geom * tr / (r * r).max(1e-4)
                } else {
                    0.0
                };
                let j = self.illum * h.radiance + lamp_in;
                Sample {
                    clean: h.radiance,
                    direct: j * tr,
                    scatter: j * tr * ((self.s * self.c * r).exp() - 1.0),
                    veil: 1.0 - tr,
                    lamp: if self.lamp_power > 0.0 {
                        self.lamp.fraction(r)
                    } else {
                        1.0
                    },
                }
            }
        }
    }
}

/// Sheared-grid supersampling offsets: N² samples whose x (and y)
/// coordinates are all distinct multiples of 1/N², so even an axis-aligned
/// edge is resolved to 1/N² of a pixel.
pub(super) fn sample_offsets(n: usize) -> Vec<(f64, f64)> {
    let nn = (n * n) as f64;
    let mut v = Vec::with_capacity(n * n);
    for j in 0..n {
        for i in 0..n {
            v.push((
                ((i * n + j) as f64 + 0.5) / nn - 0.5,
                ((j * n + i) as f64 + 0.5) / nn - 0.5,
            ));
        }
    }
    v
}

impl Renderer {
    /// Ray-cast every pixel inside some ROI.
    pub(super) fn cast(
        &mut self,
        cam: &CameraModel,
        objects: &Objects,
        rois: &[Option<Roi>],
        medium: &Medium,
    ) {
        let w = cam.width as usize;
        let h = cam.height as usize;
        let mut spans: Vec<(usize, usize, bool)> = Vec::new();
        // Objects whose ROI covers the current row: (id, x0, x1).
        let mut row_objects: Vec<(u32, usize, usize)> = Vec::new();
        let mut span_ids: Vec<u32> = Vec::new();
        let mut pixel_ids: Vec<u32> = Vec::new();
        let mut fine_objects = vec![false; rois.len()];
        for (i, r) in rois.iter().enumerate() {
            if let Some(r) = r {
                fine_objects[i] = r.fine;
            }
        }
        let mut prev: Vec<(usize, usize, Vec<LatticePoint>)> = Vec::new();
        for y in 0..h {
            spans.clear();
            row_objects.clear();
            for (id, r) in rois.iter().enumerate() {
                if let Some(r) = r {
                    if y >= r.rect.y0 && y <= r.rect.y1 {
                        spans.push((r.rect.x0, r.rect.x1, r.fine));
                        row_objects.push((id as u32, r.rect.x0, r.rect.x1));
                    }
                }
            }
            if spans.is_empty() {
                prev.clear();
                continue;
            }
            spans.sort_unstable_by_key(|s| s.0);
            let mut merged: Vec<(usize, usize)> = Vec::new();
            for &(a, b, _) in &spans {
                match merged.last_mut() {
                    Some(last) if a <= last.1 + 1 => last.1 = last.1.max(b),
                    _ => merged.push((a, b)),
                }
            }
            let v = y as f64;
            let mut next_prev = Vec::with_capacity(merged.len());
            for &(x0, x1) in &merged {
                // Pixel-corner lattice rows above and below this row (shared by
                // neighbouring pixels; the upper one reused from the row above).
                // ROIs have a margin of ≥ 2 px around their objects, so rays
                // through this span can only hit objects whose ROI meets it.
                span_ids.clear();
                span_ids.extend(
                    row_objects
                        .iter()
                        .filter(|o| o.1 <= x1 && o.2 >= x0)
                        .map(|o| o.0),
                );
                let top = match prev.iter().position(|(a, b, _)| *a == x0 && *b == x1) {
                    Some(k) => prev.swap_remove(k).2,
                    None => lattice_row(cam, objects, &span_ids, x0, x1, v - 0.5),
                };
                let bottom = lattice_row(cam, objects, &span_ids, x0, x1, v + 0.5);
                for x in x0..=x1 {
                    let k = x - x0;
                    let u = x as f64;
                    let guess = (
                        0.25 * (top[k].0 .0
                            + top[k + 1].0 .0
                            + bottom[k].0 .0
                            + bottom[k + 1].0 .0),
                        0.25 * (top[k].0 .1
                            + top[k + 1].0 .1
                            + bottom[k].0 .1
                            + bottom[k + 1].0 .1),
                    );
                    let centre = trace::ray_from(cam, u, v, guess);
                    pixel_ids.clear();
                    pixel_ids.extend(
                        row_objects
                            .iter()
                            .filter(|o| o.1 <= x && o.2 >= x)
                            .map(|o| o.0),
                    );
                    let hit_c = objects.trace_in(&pixel_ids, centre.0, centre.1);
                    let corners = [top[k].1, top[k + 1].1, bottom[k + 1].1, bottom[k].1];
                    let kind = classify_pixel(objects, &hit_c, &corners, &fine_objects);
                    let s = self.pixel_sample(
                        cam,
                        objects,
                        &pixel_ids,
                        kind,
                        hit_c,
                        centre,
                        (u, v),
                        medium,
                    );
                    let i = y * w + x;
                    self.clean[i] = s.clean as f32;
                    self.direct[i] = s.direct as f32;
                    self.scatter[i] = s.scatter as f32;
                    self.veil[i] = s.veil as f32;
                    self.lamp[i] = s.lamp as f32;
                }
                next_prev.push((x0, x1, bottom));
            }
            prev = next_prev;
        }
    }

    /// The sample of one pixel of class `kind`: its centre sample, the exact
    /// module coverage of a plate edge, or the mean of the supersampling
    /// offsets around pixel centre `(u, v)` (ray `centre`, hit `hit_c`).
    fn pixel_sample(
        &self,
        cam: &CameraModel,
        objects: &Objects,
        ids: &[u32],
        kind: PixelKind,
        hit_c: Option<Hit>,
        centre: (f64, f64),
        (u, v): (f64, f64),
        medium: &Medium,
    ) -> Sample {
        let nsamples = self.offsets.len() as f64;
        if let PixelKind::Uniform = kind {
            medium.sample(hit_c)
        } else if let (PixelKind::PlateEdge(white), Some(h)) = (kind, hit_c) {
            // Exact area coverage of the modules under the pixel.
            let plate = &objects.plates[h.object as usize];
            let mix = |a: f64, b: f64| white * a + (1.0 - white) * b;
            let cos_i = h.lamp_geom
                / if h.radiance > 0.5 * plate.shade {
                    trace::ALBEDO_WHITE
                } else {
                    trace::ALBEDO_BLACK
                };
            let hit = Hit {
                radiance: plate.shade * mix(trace::ALBEDO_WHITE, trace::ALBEDO_BLACK),
                lamp_geom: cos_i * mix(trace::ALBEDO_WHITE, trace::ALBEDO_BLACK),
                ..h
            };
            medium.sample(Some(hit))
        } else {
            let mut acc = Sample::default();
            for &(du, dv) in &self.offsets {
                let r = trace::ray_from(cam, u + du, v + dv, centre);
                let s = medium.sample(objects.trace_in(ids, r.0, r.1));
                acc.clean += s.clean;
                acc.direct += s.direct;
                acc.scatter += s.scatter;
                acc.veil += s.veil;
                acc.lamp += s.lamp;
            }
            Sample {
                clean: acc.clean / nsamples,
                direct: acc.direct / nsamples,
                scatter: acc.scatter / nsamples,
                veil: acc.veil / nsamples,
                lamp: acc.lamp / nsamples,
            }
        }
    }
}

/// A pixel corner's ray and what it hits.
type LatticePoint = ((f64, f64), Option<Hit>);

/// The pixel-corner points `u = x0 − ½ … x1 + ½` at image row `v`.
fn lattice_row(
    cam: &CameraModel,
    objects: &Objects,
    ids: &[u32],
    x0: usize,
    x1: usize,
    v: f64,
) -> Vec<LatticePoint> {
    let first = cam.ray(x0 as f64 - 0.5, v);
    let (mut prev, mut last) = (first, first);
    (x0..=x1 + 1)
        .map(|x| {
            // Linear extrapolation from the two previous rays: Newton then
            // converges in one step.
            let guess = (2.0 * last.0 - prev.0, 2.0 * last.1 - prev.1);
            let r = trace::ray_from(cam, x as f64 - 0.5, v, guess);
            prev = if x == x0 { r } else { last };
            last = r;
            (r, objects.trace_in(ids, r.0, r.1))
        })
        .collect()
}

/// How a pixel is rendered.
#[derive(Debug, Clone, Copy, PartialEq)]
enum PixelKind {
    /// One uniform patch: its centre sample.
    Uniform,
    /// Inside one plate's face, across module edges: this white fraction.
    PlateEdge(f64),
    /// Anything else (silhouettes, occlusions, tiny features): supersampled.
    Mixed,
}

/// Classify a pixel from the hits at its centre and corners (see
/// [`pixel_is_uniform`]). Plate edges: all five on one plate's face; the
/// pixel's footprint is the corners' quadrilateral in plate coordinates and
/// its white fraction is computed exactly.
fn classify_pixel(
    objects: &Objects,
    centre: &Option<Hit>,
    corners: &[Option<Hit>; 4],
    fine: &[bool],
) -> PixelKind {
    if pixel_is_uniform(objects, centre, corners, fine) {
        return PixelKind::Uniform;
    }
    let (Some(c), [Some(a), Some(b), Some(d), Some(e)]) = (centre, corners) else {
        return PixelKind::Mixed;
    };
    let Some(plate) = objects.plates.get(c.object as usize) else {
        return PixelKind::Mixed;
    };
    let back = (plate.modules as u32 + 2).pow(2);
    let hits = [a, b, d, e, c];
    if fine.get(c.object as usize).copied().unwrap_or(true)
        || hits.iter().any(|h| h.object != c.object || h.patch == back)
    {
        return PixelKind::Mixed;
    }
    let (mut c0, mut c1, mut r0, mut r1) = (i64::MAX, i64::MIN, i64::MAX, i64::MIN);
    for h in hits {
        let (col, row) = plate.decode_patch(h.patch);
        c0 = c0.min(col);
        c1 = c1.max(col);
        r0 = r0.min(row);
        r1 = r1.max(row);
    }
    let quad = [a.plane, b.plane, d.plane, e.plane];
    match plate.white_coverage(&quad, c0, c1, r0, r1) {
        Some(f) => PixelKind::PlateEdge(f),
        None => PixelKind::Mixed,
    }
}

/// Whether a pixel is one uniform patch, from the hits at its centre and
/// corners: same object, and for a plate all modules between the corners'
/// modules of one colour (the pixel's footprint on a plane is convex, so a
/// module edge crossing it separates its corners).
fn pixel_is_uniform(
    objects: &Objects,
    centre: &Option<Hit>,
    corners: &[Option<Hit>; 4],
    fine: &[bool],
) -> bool {
    let obj = |h: &Option<Hit>| h.map(|h| h.object);
    let o = obj(centre);
    if corners.iter().any(|c| obj(c) != o) {
        return false;
    }
    let Some(o) = o else {
        return true;
    };
    if fine.get(o as usize).copied().unwrap_or(true) {
        return false;
    }
    let Some(plate) = objects.plates.get(o as usize) else {
        return true; // a hull: smooth shading
    };
    let patches: Vec<u32> = corners
        .iter()
        .chain([centre])
        .flatten()
        .map(|h| h.patch)
        .collect();
    let back = (plate.modules as u32 + 2).pow(2);
    if patches.iter().all(|&p| p == back) {
        return true;
    }
    if patches.contains(&back) {
        return false;
    }
    let (mut c0, mut c1, mut r0, mut r1) = (i64::MAX, i64::MIN, i64::MAX, i64::MIN);
    for &p in &patches {
        let (c, r) = plate.decode_patch(p);
        c0 = c0.min(c);
        c1 = c1.max(c);
        r0 = r0.min(r);
        r1 = r1.max(r);
    }
    plate.uniform(c0, c1, r0, r1)
}
