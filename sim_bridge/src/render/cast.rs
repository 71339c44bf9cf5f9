//! Ray casting of the pixels inside the regions of interest: the corner
//! lattice, the pixel classes (uniform patch, plate edge with exact module
//! coverage, supersampled), and the water terms of each sample.

use super::rays::RayTable;
use super::roi::Roi;
use super::trace::{self, Hit, Objects};
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

/// The ray-cast outputs of a band of image rows (row-major, `w` wide,
/// starting at row `y0`).
pub(super) struct Band<'a> {
    pub(super) y0: usize,
    pub(super) clean: &'a mut [f32],
    pub(super) direct: &'a mut [f32],
    pub(super) scatter: &'a mut [f32],
    pub(super) veil: &'a mut [f32],
    pub(super) lamp: &'a mut [f32],
}

/// Everything casting a frame's rows needs, shared by the threads.
pub(super) struct Caster<'a> {
    pub(super) cam: &'a CameraModel,
    pub(super) objects: &'a Objects,
    pub(super) rois: &'a [Option<Roi>],
    pub(super) medium: &'a Medium,
    pub(super) rays: &'a RayTable,
    /// Supersampling offsets (pixel units around the centre).
    pub(super) offsets: &'a [(f64, f64)],
    /// Per object: always supersample (its ROI's `fine`).
    pub(super) fine: Vec<bool>,
}

impl Caster<'_> {
    /// Ray-cast every pixel of `band` inside some ROI (the others are left as they are).
    pub(super) fn cast_band(&self, band: Band<'_>) {
        let w = self.cam.width as usize;
        let rows = band.clean.len() / w.max(1);
        let mut spans: Vec<(usize, usize)> = Vec::new();
        // Objects whose ROI covers the current row: (id, x0, x1).
        let mut row_objects: Vec<(u32, usize, usize)> = Vec::new();
        let mut span_ids: Vec<u32> = Vec::new();
        let mut pixel_ids: Vec<u32> = Vec::new();
        // Corner hits of the row above's bottom edge, per span, reused as this row's top.
        let mut prev: Vec<(usize, usize, Vec<Option<Hit>>)> = Vec::new();
        for y in band.y0..band.y0 + rows {
            spans.clear();
            row_objects.clear();
            for (id, r) in self.rois.iter().enumerate() {
                if let Some(r) = r {
                    if y >= r.rect.y0 && y <= r.rect.y1 {
                        spans.push((r.rect.x0, r.rect.x1));
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
            for &(a, b) in &spans {
                match merged.last_mut() {
                    Some(last) if a <= last.1 + 1 => last.1 = last.1.max(b),
                    _ => merged.push((a, b)),
                }
            }
            let v = y as f64;
            let (top_rays, bottom_rays) = (
                self.rays.corner_row(y, false),
                self.rays.corner_row(y, true),
            );
            let centres = self.rays.centre_row(y);
            let mut next_prev = Vec::with_capacity(merged.len());
            for &(x0, x1) in &merged {
                // Pixel-corner hits above and below this row (shared by
                // neighbouring pixels; the upper ones reused from the row above).
                // ROIs have a margin of ≥ 2 px around their objects, so rays
                // through this span can only hit objects whose ROI meets it.
                span_ids.clear();
                span_ids.extend(
                    row_objects
                        .iter()
                        .filter(|o| o.1 <= x1 && o.2 >= x0)
                        .map(|o| o.0),
                );
                let corner_hits = |rays: &[(f64, f64)]| -> Vec<Option<Hit>> {
                    rays[x0..=x1 + 1]
                        .iter()
                        .map(|r| self.objects.trace_in(&span_ids, r.0, r.1))
                        .collect()
                };
                let top = match prev.iter().position(|(a, b, _)| *a == x0 && *b == x1) {
                    Some(k) => prev.swap_remove(k).2,
                    None => corner_hits(top_rays),
                };
                let bottom = corner_hits(bottom_rays);
                for x in x0..=x1 {
                    let k = x - x0;
                    let centre = centres[x];
                    pixel_ids.clear();
                    pixel_ids.extend(
                        row_objects
                            .iter()
                            .filter(|o| o.1 <= x && o.2 >= x)
                            .map(|o| o.0),
                    );
                    let hit_c = self.objects.trace_in(&pixel_ids, centre.0, centre.1);
                    let corners = [top[k], top[k + 1], bottom[k + 1], bottom[k]];
                    let kind = classify_pixel(self.objects, &hit_c, &corners, &self.fine);
                    let footprint = [
                        top_rays[x],
                        top_rays[x + 1],
                        bottom_rays[x],
                        bottom_rays[x + 1],
                    ];
                    let s = self.pixel_sample(&pixel_ids, kind, hit_c, &footprint, (x as f64, v));
                    let i = (y - band.y0) * w + x;
                    band.clean[i] = s.clean as f32;
                    band.direct[i] = s.direct as f32;
                    band.scatter[i] = s.scatter as f32;
                    band.veil[i] = s.veil as f32;
                    band.lamp[i] = s.lamp as f32;
                }
                next_prev.push((x0, x1, bottom));
            }
            prev = next_prev;
        }
    }

    /// The sample of one pixel of class `kind`: its centre sample, the exact
    /// module coverage of a plate edge, or the mean of the supersampling
    /// offsets around pixel centre `(u, v)` (hit `hit_c`; the corner rays
    /// `footprint`: top-left, top-right, bottom-left, bottom-right).
    fn pixel_sample(
        &self,
        ids: &[u32],
        kind: PixelKind,
        hit_c: Option<Hit>,
        footprint: &[(f64, f64); 4],
        (u, v): (f64, f64),
    ) -> Sample {
        let medium = self.medium;
        let nsamples = self.offsets.len() as f64;
        if let PixelKind::Uniform = kind {
            medium.sample(hit_c)
        } else if let (PixelKind::PlateEdge(white), Some(h)) = (kind, hit_c) {
            // Exact area coverage of the modules under the pixel.
            let plate = &self.objects.plates[h.object as usize];
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
            let [tl, tr, bl, br] = *footprint;
            let mut acc = Sample::default();
            for &(du, dv) in self.offsets {
                // One Newton step from the bilinear blend of the exact corner rays.
                let (s, t) = (du + 0.5, dv + 0.5);
                let guess = (
                    (1.0 - t) * ((1.0 - s) * tl.0 + s * tr.0) + t * ((1.0 - s) * bl.0 + s * br.0),
                    (1.0 - t) * ((1.0 - s) * tl.1 + s * tr.1) + t * ((1.0 - s) * bl.1 + s * br.1),
                );
                let r = trace::ray_near(self.cam, u + du, v + dv, guess);
                let s = medium.sample(self.objects.trace_in(ids, r.0, r.1));
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
    // All five hit (same object as the centre, which hit).
    let patches: [u32; 5] = [0, 1, 2, 3, 4].map(|i| {
        corners
            .get(i)
            .unwrap_or(centre)
            .map_or(u32::MAX, |h| h.patch)
    });
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
