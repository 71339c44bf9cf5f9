//! Stage 2 of the detector, **read codes** (paper §5, the 10x10 grid):
//! every quad is tried as the *code square* (the black border around the
//! data bits). A homography maps its module grid into the image, each
//! module's mean grey level is compared with a threshold halfway between the
//! black border's and the white ring's (or quiet zone's) means, and the data
//! bits are matched to the table under all four rotations, correcting at most
//! the code set's correction budget. A code that does not match is dropped,
//! never guessed.
//!
//! Input: [`Quad`]s and the detection image. Output: [`CodeSquare`]s — the
//! ID, the bits corrected, and the code square's corners refined by the
//! corner stage ([`super::corners`]), one per marker — and the quads that
//! read no code.

use super::corners::FittedSquare;
use super::geom::{apply, dist, homography_4, mean_side, Px};
use super::quads::Quad;
use super::refine::{refine_by_edge_lines_coarse, refine_by_edge_lines_wide, Polarity};
use super::DetectParams;
use crate::mat::GrayView;
use shoal_proto::marker::{rotate_code, CodeSet, MarkerId};

/// The default correction budget never exceeds AprilTag 3's own default
/// (`DEFAULT_BITS_CORRECTED`): each further bit multiplies the chance that a
/// foreign pattern reads as a code (tag36h11's radius of 5 bits accepts ~1.5 %
/// of random 36-bit patterns, 2 bits ~2·10⁻⁵), and on real photos the 3–5-bit
/// reads were other tags' faces (docs/real-data.md).
pub const DEFAULT_CORRECTION_CAP_BITS: u32 = 2;

/// A decoded code square: which marker, how it read, where it is.
#[derive(Debug, Clone)]
pub struct CodeSquare {
    pub id: MarkerId,
    /// Bits corrected when decoding.
    pub hamming: u32,
    /// The refined code square, corners in upright order (TL, TR, BR, BL).
    pub square: FittedSquare,
    /// Mean module size (px) of the refined square.
    pub module_px: f64,
}

/// What reading a code square again on its refined edges said
/// ([`CodeReader::confirm`]).
enum Confirmed {
    /// The first read.
    Same,
    /// Nothing read again on the refined square.
    Unread,
    /// Another ID or rotation: (bits corrected, ID, quarter turns from the
    /// first read's upright order).
    Other(u32, MarkerId, usize),
    /// Rereads that disagree with the same number of corrected bits.
    Conflict,
}

/// A code read from one quad, before refinement.
#[derive(Debug, Clone, Copy)]
struct Code {
    id: MarkerId,
    hamming: u32,
    /// The quad's corners in upright order (TL, TR, BR, BL).
    upright: [Px; 4],
}

/// The code table of one [`CodeSet`] under all four rotations, and the
/// correction budget.
#[derive(Debug, Clone)]
pub struct CodeReader {
    codes: CodeSet,
    /// `(rotated bits, id, k)` for every code and quarter turn `k`.
    rotated: Vec<(u64, MarkerId, usize)>,
    correction_bits: u32,
    min_contrast: f64,
    max_border_error_rate: f64,
}

impl CodeReader {
    pub fn new(codes: CodeSet, params: &DetectParams) -> CodeReader {
        let n = codes.data_side();
        let rotated: Vec<(u64, MarkerId, usize)> = (0..codes.len() as MarkerId)
            .filter_map(|id| codes.code(id).ok().map(|c| (id, c)))
            .flat_map(|(id, c)| (0..4).map(move |k| (rotate_code(c, n, k), id, k)))
            .collect();
        let correction_bits = params.max_correction_bits.unwrap_or_else(|| {
            codes
                .table()
                .max_correction_bits
                .max(unique_decoding_radius(&rotated))
                .min(DEFAULT_CORRECTION_CAP_BITS)
        });
        CodeReader {
            codes,
            rotated,
            correction_bits,
            min_contrast: params.min_contrast,
            max_border_error_rate: params.max_border_error_rate,
        }
    }

    /// The code set has a code table (the generated tables may be absent).
    pub fn has_codes(&self) -> bool {
        !self.rotated.is_empty()
    }

    /// Bits corrected at most.
    pub fn correction_bits(&self) -> u32 {
        self.correction_bits
    }

    /// Read every quad of `quads` as a code square, refine the ones that
    /// read with `refine(corners, module px)` and merge them into `found`;
    /// returns the quads that read no code. The same marker is usually found
    /// several times (threshold windows, both sides of a thin dark band), and
    /// refinement pulls all of them onto the same edges: one entry per
    /// marker, the fewest corrected bits kept.
    pub fn decode(
        &self,
        (view, raw): (&GrayView<'_>, Option<&GrayView<'_>>),
        quads: &[Quad],
        mut refine: impl FnMut(&[Px; 4], f64) -> FittedSquare,
        found: &mut Vec<CodeSquare>,
    ) -> Vec<Quad> {
        let m = (self.codes.data_side() + 2) as f64;
        let mut undecoded = Vec::new();
        for q in quads {
            let Some(code) = self.read(view, q) else {
                undecoded.push(*q);
                continue;
            };
            let (mut id, mut hamming) = (code.id, code.hamming);
            let rough_module = mean_side(&code.upright) / m;
            // Already found from another contour of the same square: skip the refinement.
            if found.iter().any(|f| {
                f.id == id
                    && f.hamming <= hamming
                    && dist(f.square.corners[0], code.upright[0]) < 0.5 * rough_module
            }) {
                continue;
            }
            let mut square = refine(&code.upright, rough_module);
            match self.confirm((view, raw), &square.corners, id) {
                Confirmed::Same => {}
                // The first read stands; but where the refined square reads
                // nothing, the refinement may have followed a corner pulled
                // out (docs/detector.md, "A corner pulled out"): a square on
                // the edges searched wider that reads this very code exactly,
                // and whose refinement reads it again, replaces it.
                Confirmed::Unread => {
                    if let Some(better) =
                        self.relocated((view, raw), &code, rough_module, &mut refine)
                    {
                        square = better;
                    }
                }
                Confirmed::Other(h, again, k) => {
                    let upright = std::array::from_fn(|i| square.corners[(i + k) % 4]);
                    (id, hamming) = (again, h);
                    square = refine(&upright, rough_module);
                }
                Confirmed::Conflict => {
                    undecoded.push(*q);
                    continue;
                }
            }
            let module_px = mean_side(&square.corners) / m;
            let corner = square.corners[0];
            let decoded = CodeSquare {
                id,
                hamming,
                square,
                module_px,
            };
            match found
                .iter_mut()
                .find(|f| f.id == id && dist(f.square.corners[0], corner) < 0.5 * module_px)
            {
                Some(f) if hamming < f.hamming => *f = decoded,
                Some(_) => {}
                None => found.push(decoded),
            }
        }
        undecoded
    }

    /// The square of `code` found on its edges searched ±1.5 modules wide
    /// ([`refine_by_edge_lines_wide`]) and refined, when it reads `code`'s ID
    /// with no bit corrected in its upright order, and its refinement reads
    /// it again; `None` otherwise.
    fn relocated(
        &self,
        (view, raw): (&GrayView<'_>, Option<&GrayView<'_>>),
        code: &Code,
        module_px: f64,
        refine: &mut impl FnMut(&[Px; 4], f64) -> FittedSquare,
    ) -> Option<FittedSquare> {
        let wide = refine_by_edge_lines_wide(view, &code.upright, module_px, Polarity::DarkInside)?;
        if self.read_square(view, &wide) != Some((0, code.id, 0)) {
            return None;
        }
        let square = refine(&wide, module_px);
        matches!(
            self.confirm((view, raw), &square.corners, code.id),
            Confirmed::Same
        )
        .then_some(square)
    }

    /// The code read again on the refined square (`corners`, in the first
    /// read's upright order): on the detection image and on the raw frame.
    /// A polygon whose corners are off by a module (a small marker's
    /// contour on a downsampled level) can sample a grid one corrected bit
    /// from another ID or rotation, and a restoration that rings or
    /// saturates a module of 3 px (HOIRM at 0.5 /m and 3.5 m) can turn a
    /// bit; the refined square samples the true grid, and the raw frame has
    /// neither artefact. No reread: [`Confirmed::Unread`] (the first read
    /// stands; [`Self::relocated`] may move its square); rereads that
    /// agree with it: [`Confirmed::Same`]; rereads that agree with each
    /// other, or the one with the fewer corrected bits: [`Confirmed::Other`];
    /// rereads that disagree at the same count: [`Confirmed::Conflict`].
    fn confirm(
        &self,
        (view, raw): (&GrayView<'_>, Option<&GrayView<'_>>),
        corners: &[Px; 4],
        id: MarkerId,
    ) -> Confirmed {
        let reads: Vec<(u32, MarkerId, usize)> = [Some(view), raw]
            .into_iter()
            .flatten()
            .filter_map(|v| self.read_square(v, corners))
            .collect();
        let best = reads.iter().map(|r| r.0).min();
        let winners: Vec<_> = reads.iter().filter(|r| Some(r.0) == best).collect();
        match winners.as_slice() {
            [] => Confirmed::Unread,
            [w, rest @ ..] if rest.iter().all(|r| (r.1, r.2) == (w.1, w.2)) => {
                if (w.1, w.2) == (id, 0) {
                    Confirmed::Same
                } else {
                    Confirmed::Other(w.0, w.1, w.2)
                }
            }
            _ => Confirmed::Conflict,
        }
    }

    /// The code inside `quad` taken as the code square, or `None` when it
    /// reads no code of the table within the correction budget.
    ///
    /// The square's true edge lies `inset_px` outside the traced polygon; on
    /// small markers that is a third of a module, enough to misread bits. A
    /// square that reads no code there is read once more on its edges
    /// located in the image (the coarse edge lines of [`super::refine`]):
    /// at 1.5–2 px per module, or on a contour merged with a neighbouring
    /// shadow, the polygon's corners are off by more than half a module
    /// (AprilTag 3 refines every quad's edges before decoding for the same
    /// reason). A quad pieced from a larger outline ([`Quad::exact_only`])
    /// counts only when its first read is exact.
    fn read(&self, view: &GrayView<'_>, quad: &Quad) -> Option<Code> {
        let side = mean_side(&quad.pts);
        let grow = (side + 2.0 * quad.inset_px) / side;
        let centre = [
            quad.pts.iter().map(|p| p[0]).sum::<f64>() / 4.0,
            quad.pts.iter().map(|p| p[1]).sum::<f64>() / 4.0,
        ];
        let outer = quad.pts.map(|p| {
            [
                centre[0] + grow * (p[0] - centre[0]),
                centre[1] + grow * (p[1] - centre[1]),
            ]
        });
        let module_px = mean_side(&outer) / (self.codes.data_side() + 2) as f64;
        let read_on = |square: [Px; 4]| self.read_square(view, &square).map(|r| (r, square));
        let ((hamming, id, k), square) = read_on(outer)
            .or_else(|| {
                // The polygon's corners are kept: the refinement starts from them.
                let edges =
                    refine_by_edge_lines_coarse(view, &outer, module_px, Polarity::DarkInside)?;
                self.read_square(view, &edges).map(|r| (r, outer))
            })
            .or_else(|| {
                // A corner a module or more off: the square found replaces
                // the polygon, which would lead the refinement astray.
                // Searched this widely, a square has more ways to match a
                // code by chance: only an exact code counts.
                let wide =
                    refine_by_edge_lines_wide(view, &outer, module_px, Polarity::DarkInside)?;
                read_on(wide).filter(|((hamming, _, _), _)| *hamming == 0)
            })
            .filter(|((hamming, _, _), _)| !quad.exact_only || *hamming == 0)?;
        // Seen rotated clockwise k times: the upright corner i sits at quad corner (i + k) mod 4.
        let upright = std::array::from_fn(|i| square[(i + k) % 4]);
        Some(Code {
            id,
            hamming,
            upright,
        })
    }

    /// The code of the square whose outer corners are `outer` (clockwise on
    /// screen): `(bits corrected, id, quarter turns)`. The modules are read
    /// as sampled, and when that matches no code, once more sharpened
    /// ([`SHARPENING`]).
    fn read_square(&self, view: &GrayView<'_>, outer: &[Px; 4]) -> Option<(u32, MarkerId, usize)> {
        let m = self.codes.data_side() + 2;
        let (values, thr) = self.module_values(view, outer)?;
        self.best_match(data_bits(&values, m, |_, _| 0.0, thr))
            .or_else(|| {
                self.best_match(data_bits(
                    &values,
                    m,
                    |r, c| laplacian(&values, m, r, c),
                    thr,
                ))
            })
    }

    /// The mean grey level of every module of the code square (border and
    /// data, row by row) whose outer corners are `outer`, and the
    /// black/white threshold from the border and the ring outside it;
    /// `None` when those do not look like a code square.
    fn module_values(&self, view: &GrayView<'_>, outer: &[Px; 4]) -> Option<(Vec<f64>, f64)> {
        let n = self.codes.data_side();
        let m = n + 2; // code square: black border + data
        let ms = m as f64;
        let cells = [[0.0, 0.0], [ms, 0.0], [ms, ms], [0.0, ms]];
        let hmat = homography_4(&cells, outer)?;
        let module_px = mean_side(outer) / ms;
        // Sub-samples per module side: more for big modules, at most 4x4.
        let s = (module_px / 3.0).clamp(1.0, 4.0) as usize;
        let cell_mean = |r: i32, c: i32| -> f64 {
            let mut acc = 0.0;
            for i in 0..s {
                for j in 0..s {
                    // The central 60% of the module, away from blurred module edges.
                    let fy = 0.2 + 0.6 * (i as f64 + 0.5) / s as f64;
                    let fx = 0.2 + 0.6 * (j as f64 + 0.5) / s as f64;
                    let p = apply(&hmat, [f64::from(c) + fx, f64::from(r) + fy]);
                    acc += view.sample(p[0], p[1]);
                }
            }
            acc / (s * s) as f64
        };
        let mi = m as i32;
        // Border ring (black) and the ring one module outside (white: the
        // enhanced marker's white ring, or the quiet zone of the others).
        let border: Vec<f64> = ring_cells(mi, 0)
            .into_iter()
            .map(|(r, c)| cell_mean(r, c))
            .collect();
        let outside: Vec<f64> = ring_cells(mi, 1)
            .into_iter()
            .filter_map(|(r, c)| {
                let p = apply(&hmat, [f64::from(c) + 0.5, f64::from(r) + 0.5]);
                view.contains(p[0], p[1], 1.0).then(|| cell_mean(r, c))
            })
            .collect();
        let thr = self.threshold(&border, &outside)?;
        // The code square's modules (border and data), row by row.
        let values: Vec<f64> = (0..mi)
            .flat_map(|r| (0..mi).map(move |c| (r, c)))
            .map(|(r, c)| cell_mean(r, c))
            .collect();
        Some((values, thr))
    }

    /// The grey level between black and white, from the border modules'
    /// and the surrounding ring's means; `None` when the contrast is too low
    /// or too many of them read the wrong colour.
    fn threshold(&self, border: &[f64], outside: &[f64]) -> Option<f64> {
        if outside.len() < border.len() / 2 {
            return None;
        }
        let black = median(border);
        let white = median(outside);
        if white - black < self.min_contrast {
            return None;
        }
        let thr = 0.5 * (black + white);
        let bad_border = border.iter().filter(|&&v| v > thr).count();
        let bad_outside = outside.iter().filter(|&&v| v < thr).count();
        let rate = self.max_border_error_rate;
        if bad_border as f64 > rate * border.len() as f64
            || bad_outside as f64 > rate * outside.len() as f64
        {
            return None;
        }
        Some(thr)
    }

    /// The nearest code to `bits` under all rotations: `(bits corrected,
    /// id, quarter turns)`; `None` beyond the budget or when two IDs tie.
    fn best_match(&self, bits: u64) -> Option<(u32, MarkerId, usize)> {
        let mut best: Option<(u32, MarkerId, usize)> = None;
        let mut tie = false;
        for &(code, id, k) in &self.rotated {
            let d = (code ^ bits).count_ones();
            match best {
                Some((bd, bid, _)) if d == bd && bid != id => tie = true,
                Some((bd, _, _)) if d >= bd => {}
                _ => {
                    best = Some((d, id, k));
                    tie = false;
                }
            }
        }
        let (d, id, k) = best?;
        if d > self.correction_bits || (tie && d > 0) {
            return None;
        }
        Some((d, id, k))
    }
}

/// AprilTag 3's decode sharpening (`decode_sharpening`, 0.25): each
/// module's value plus this times the module grid's Laplacian. At 1.5–2 px
/// per module the optics and the pixel area mix every module with its
/// neighbours; the Laplacian on the module grid undoes that first-order
/// blur.
const SHARPENING: f64 = 0.25;

/// `SHARPENING` × the 4-neighbour Laplacian of `values` (an `m`×`m` module
/// grid) at module (`r`, `c`); neighbours outside the grid are left out.
fn laplacian(values: &[f64], m: usize, r: usize, c: usize) -> f64 {
    let v = values[r * m + c];
    let mut lap = 0.0;
    for (dr, dc) in [(-1i32, 0i32), (1, 0), (0, -1), (0, 1)] {
        let (rr, cc) = (r as i32 + dr, c as i32 + dc);
        if rr >= 0 && cc >= 0 && (rr as usize) < m && (cc as usize) < m {
            lap += v - values[rr as usize * m + cc as usize];
        }
    }
    SHARPENING * lap
}

/// The data bits (inside the one-module border) of an `m`×`m` module grid,
/// row by row: a module is white (1) when its value plus `adjust(r, c)` is
/// above `thr`.
fn data_bits(values: &[f64], m: usize, adjust: impl Fn(usize, usize) -> f64, thr: f64) -> u64 {
    let mut bits = 0u64;
    for r in 1..m - 1 {
        for c in 1..m - 1 {
            let v = values[r * m + c] + adjust(r, c);
            bits = (bits << 1) | u64::from(v > thr);
        }
    }
    bits
}

/// The module cells (row, column) of the ring `k` modules outside the
/// border of an `m`-module code square (`k = 0`: the border itself).
fn ring_cells(m: i32, k: i32) -> Vec<(i32, i32)> {
    let (lo, hi) = (-k, m - 1 + k);
    let mut v = Vec::new();
    for c in lo..=hi {
        v.push((lo, c));
        v.push((hi, c));
    }
    for r in lo + 1..hi {
        v.push((r, lo));
        v.push((r, hi));
    }
    v
}

/// Bits that can be corrected without ambiguity in the codes actually in use
/// (`(d_min − 1) / 2` over all IDs and rotations). OpenCV's figure for
/// `DICT_4X4_1000` is 0, but the 50 codes of the enhanced marker's set are
/// farther apart, as OpenCV's own `DICT_4X4_50` (1 bit) says.
fn unique_decoding_radius(rotated: &[(u64, MarkerId, usize)]) -> u32 {
    let mut dmin = u32::MAX;
    for (i, a) in rotated.iter().enumerate() {
        for b in &rotated[i + 1..] {
            if a.1 != b.1 {
                dmin = dmin.min((a.0 ^ b.0).count_ones());
            }
        }
    }
    // A code equal to its own rotation is ambiguous in orientation: count that too.
    for a in rotated {
        for b in rotated {
            if a.1 == b.1 && a.2 != b.2 && a.0 == b.0 {
                return 0;
            }
        }
    }
    if dmin == u32::MAX {
        0
    } else {
        dmin.saturating_sub(1) / 2
    }
}

fn median(v: &[f64]) -> f64 {
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    if s.is_empty() {
        return f64::NAN;
    }
    s[s.len() / 2]
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A tag36h11 tag rendered at `module_px` pixels per module, turned by
    /// `angle_rad`, pixel-area integrated and blurred by a Gaussian of
    /// `sigma_px`: the image and the code square's outer corners
    /// (clockwise on screen).
    fn small_tag(
        id: MarkerId,
        module_px: f64,
        angle_rad: f64,
        sigma_px: f64,
    ) -> (opencv::core::Mat, [Px; 4]) {
        use opencv::core::{Mat, Size, BORDER_REPLICATE, CV_8UC1};
        use opencv::prelude::*;
        let codes = CodeSet::AprilTag36h11;
        let n = codes.data_side();
        let m = (n + 2) as f64;
        let code = codes.code(id).unwrap();
        // 48 px, or the tag and three modules round it when larger.
        let size = 48.max(((m + 6.0) * module_px).ceil() as i32);
        let centre = [f64::from(size) / 2.0 - 0.3, f64::from(size) / 2.0 + 0.2];
        let (sin, cos) = angle_rad.sin_cos();
        // Module coordinates (u right, v down from the code square's corner) → pixels.
        let to_px = |u: f64, v: f64| {
            let (x, y) = ((u - 0.5 * m) * module_px, (v - 0.5 * m) * module_px);
            [centre[0] + cos * x - sin * y, centre[1] + sin * x + cos * y]
        };
        let white_at = |x: f64, y: f64| -> bool {
            let (dx, dy) = (x - centre[0], y - centre[1]);
            let u = (cos * dx + sin * dy) / module_px + 0.5 * m;
            let v = (-sin * dx + cos * dy) / module_px + 0.5 * m;
            if !(0.0..m).contains(&u) || !(0.0..m).contains(&v) {
                return true;
            }
            let (c, r) = (u as usize, v as usize);
            if r == 0 || c == 0 || r == n + 1 || c == n + 1 {
                return false;
            }
            let bit = (r - 1) * n + (c - 1);
            (code >> (n * n - 1 - bit)) & 1 == 1
        };
        const SUB: usize = 6;
        let mut img = Mat::new_rows_cols_with_default(size, size, CV_8UC1, 0.into()).unwrap();
        for y in 0..size as usize {
            for x in 0..size as usize {
                let mut white = 0;
                for i in 0..SUB {
                    for j in 0..SUB {
                        let (sx, sy) = (
                            x as f64 - 0.5 + (j as f64 + 0.5) / SUB as f64,
                            y as f64 - 0.5 + (i as f64 + 0.5) / SUB as f64,
                        );
                        white += usize::from(white_at(sx, sy));
                    }
                }
                let g = 50.0 + 140.0 * white as f64 / (SUB * SUB) as f64;
                *img.at_2d_mut::<u8>(y as i32, x as i32).unwrap() = g.round() as u8;
            }
        }
        let mut blurred = Mat::default();
        opencv::imgproc::gaussian_blur(
            &img,
            &mut blurred,
            Size::new(0, 0),
            sigma_px,
            sigma_px,
            BORDER_REPLICATE,
        )
        .unwrap();
        (
            blurred,
            [to_px(0.0, 0.0), to_px(m, 0.0), to_px(m, m), to_px(0.0, m)],
        )
    }

    #[test]
    fn reads_a_blurred_tag_of_1_7_px_modules_by_sharpening_its_module_grid() {
        // 1.7 px per module under a 0.9 px Gaussian: the smallest tags of
        // AprilTag 3's regression photos (`docs/detector.md`, "Small tags on
        // real photos"). There the plain read is 6–8 bits off (the
        // exploration that chose these figures printed 8, 6, 7 for IDs 0, 7,
        // 23), beyond the 2-bit budget, and the sharpened one 1–2 bits.
        const MODULE_PX: f64 = 1.7;
        const BLUR_SIGMA_PX: f64 = 0.9;
        let reader = CodeReader::new(CodeSet::AprilTag36h11, &DetectParams::default());
        for id in [0, 7, 23] {
            let (img, outer) = small_tag(id, MODULE_PX, 0.2, BLUR_SIGMA_PX);
            let view = GrayView::new(&img).unwrap();
            let (values, thr) = reader.module_values(&view, &outer).unwrap();
            assert_eq!(
                reader.best_match(data_bits(&values, 8, |_, _| 0.0, thr)),
                None,
                "ID {id}: the plain read should be beyond the budget here"
            );
            let (hamming, read, _) = reader.read_square(&view, &outer).unwrap();
            assert_eq!(read, id);
            assert!(hamming <= reader.correction_bits());
        }
    }

    #[test]
    fn a_polygon_with_a_corner_pulled_a_module_out_is_read_on_the_square_its_edges_give() {
        // As the contour of a tag whose black square a shadow joins at one
        // corner: that corner 1.4 modules out, its neighbour 0.7 down (the
        // tag turned 40° of the public rotation steps, docs/detector.md,
        // "A corner pulled out"). 12 px per module: the coarse edge search
        // reaches ±6 px only.
        let (img, outer) = small_tag(7, 12.0, 0.0, 1.0);
        let view = GrayView::new(&img).unwrap();
        let reader = CodeReader::new(CodeSet::AprilTag36h11, &DetectParams::default());
        let mut pulled = outer;
        pulled[3] = [outer[3][0] - 12.0, outer[3][1] + 12.0];
        pulled[2] = [outer[2][0] - 1.0, outer[2][1] + 8.0];
        assert!(
            reader.read_square(&view, &pulled).is_none(),
            "the premise: the polygon reads nothing"
        );
        let code = reader
            .read(
                &view,
                &Quad {
                    pts: pulled,
                    inset_px: 0.0,
                    exact_only: false,
                },
            )
            .expect("read on the edges found");
        assert_eq!((code.id, code.hamming), (7, 0));
        for (got, want) in code.upright.iter().zip(&outer) {
            assert!(dist(*got, *want) < 0.5, "{got:?} against {want:?}");
        }
        // A corner more than two modules off is beyond the wide search: it
        // would have to move that corner farther than it may.
        let mut far = outer;
        far[3] = [outer[3][0] - 30.0, outer[3][1] + 30.0];
        assert!(refine_by_edge_lines_wide(&view, &far, 12.0, Polarity::DarkInside).is_none());
    }

    #[test]
    fn a_refinement_that_followed_a_pulled_corner_is_replaced_by_the_square_the_wide_edges_give() {
        // The tag turned -40° of the public rotation steps read on its
        // polygon, then its refinement ran out along the card's edge to a
        // corner 15 px off, where the square reads nothing (docs/detector.md,
        // "A corner pulled out"). Here the first refinement is made to do
        // that (one corner two modules out); later ones are the coarse
        // edge lines from where they start.
        use super::super::corners::SquareCorners;
        let (img, outer) = small_tag(7, 12.0, 0.0, 1.0);
        let view = GrayView::new(&img).unwrap();
        let reader = CodeReader::new(CodeSet::AprilTag36h11, &DetectParams::default());
        let mut astray = outer;
        astray[2] = [outer[2][0] + 24.0, outer[2][1] + 14.0];
        assert!(
            reader.read_square(&view, &astray).is_none(),
            "the premise: that square reads nothing"
        );
        let calls = std::cell::Cell::new(0);
        let refine = |q: &[Px; 4], module_px: f64| {
            calls.set(calls.get() + 1);
            let corners = if calls.get() == 1 {
                astray
            } else {
                refine_by_edge_lines_coarse(&view, q, module_px, Polarity::DarkInside).unwrap_or(*q)
            };
            FittedSquare::without_fit(corners, SquareCorners::CoarseLines)
        };
        let mut found = Vec::new();
        let quad = Quad {
            pts: outer,
            inset_px: 0.0,
            exact_only: false,
        };
        assert!(reader
            .decode((&view, None), &[quad], refine, &mut found)
            .is_empty());
        assert_eq!(found.len(), 1);
        assert_eq!((found[0].id, found[0].hamming), (7, 0));
        for (got, want) in found[0].square.corners.iter().zip(&outer) {
            assert!(dist(*got, *want) < 0.5, "{got:?} against {want:?}");
        }
        assert!(calls.get() >= 2, "the wide square was refined");
    }

    #[test]
    fn a_sharp_tag_reads_exactly_without_sharpening() {
        // 2.1 px per module under a 0.5 px blur reads with no bit wrong
        // plain: sharpening is only the second read.
        let reader = CodeReader::new(CodeSet::AprilTag36h11, &DetectParams::default());
        for id in [0, 7, 23] {
            let (img, outer) = small_tag(id, 2.1, 0.2, 0.5);
            let view = GrayView::new(&img).unwrap();
            let (values, thr) = reader.module_values(&view, &outer).unwrap();
            let plain = reader.best_match(data_bits(&values, 8, |_, _| 0.0, thr));
            assert_eq!(plain.map(|p| (p.0, p.1)), Some((0, id)));
        }
    }

    #[test]
    fn enhanced_set_corrects_one_bit_like_opencv_4x4_50() {
        let reader = CodeReader::new(CodeSet::Shoal, &DetectParams::default());
        assert_eq!(reader.correction_bits(), 1);
        let reader = CodeReader::new(CodeSet::AprilTag36h11, &DetectParams::default());
        assert!(reader.correction_bits() >= 2);
    }

    #[test]
    fn the_border_ring_and_the_ring_outside_it_go_round_the_square() {
        // A 6-module code square: 20 border cells, 28 one module outside.
        let border = ring_cells(6, 0);
        let outside = ring_cells(6, 1);
        assert_eq!(border.len(), 20);
        assert_eq!(outside.len(), 28);
        assert!(border
            .iter()
            .all(|&(r, c)| r == 0 || r == 5 || c == 0 || c == 5));
        assert!(outside
            .iter()
            .all(|&(r, c)| r == -1 || r == 6 || c == -1 || c == 6));
    }
}
