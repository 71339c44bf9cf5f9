//! Stage 1 of the detector, **find quads** (paper §5, "shape, size, and
//! edge proximity"): adaptive mean threshold(s) of the detection image (dark
//! = foreground), all contours, polygon approximation; kept when they are
//! convex quadrilaterals of sufficient size, clear of the image border.
//!
//! Input: the detection image and [`DetectParams`]. Output: [`Quad`]s in
//! full-resolution pixels. Frames wider than
//! [`DetectParams::full_res_max_width`] are searched at half size; small
//! quads that read no code there are searched again at full resolution in a
//! window around them ([`full_res_quads`], the per-marker pyramid level).
//!
//! A frame's outermost row or column is sometimes not image at all: video
//! encoders and sensors leave a line of another level at the edge (the
//! public tank video's last column is ~240 DN beside ~50). The threshold's
//! local mean takes that line in, a dark band runs along the edge and merges
//! with the black border of any marker near it, and the marker's contour is
//! no longer a quad. [`edge_line_artefacts`] finds such lines (far from
//! their neighbour where the neighbour is close to the next) and the search
//! thresholds a copy with each replaced by its neighbour.

use super::contours::Contours;
use super::geom::{mean_side, min_side, signed_area2, Px};
use super::polygon::{approx_closed, bounding_box, is_convex};
use super::{DetectError, DetectParams};
use crate::mat::GrayView;
use opencv::core::{Mat, Point, Rect, Size, ToInputArray, Vector};
use opencv::imgproc;
use opencv::prelude::*;

/// A convex quad, clockwise on screen, in full-resolution pixels.
#[derive(Debug, Clone, Copy)]
pub struct Quad {
    pub pts: [Px; 4],
    /// How far inside the dark region's edge the polygon runs: contours
    /// trace the centres of the region's boundary pixels, half a pixel of
    /// the level they were found on (full-resolution pixels).
    pub inset_px: f64,
    /// Only an exact code counts: the quad was pieced together from a
    /// larger region's outline ([`quads_of_long_edges`]), which has more
    /// ways to frame a code by chance.
    pub exact_only: bool,
}

impl Quad {
    /// True when `other` has the same corners as this quad (in any cyclic
    /// order) within a tenth of its mean side: the same square found twice.
    fn same_as(&self, other: &[Px; 4]) -> bool {
        same_quad(&self.pts, other, 0.1 * mean_side(other))
    }
}

/// Candidate quads from the contours of one pyramid level of `gray` (half
/// size when wider than [`DetectParams::full_res_max_width`]).
pub fn find_quads(
    params: &DetectParams,
    gray: &(impl MatTraitConst + ToInputArray),
) -> Result<Vec<Quad>, DetectError> {
    Ok(find_quads_and_blobs(params, gray)?.0)
}

/// [`find_quads`], and on a downsampled level also the *blobs*: contours
/// of a small marker's size that are not a convex quadrilateral there but
/// whose convex hull is nearly one (a one-module ring of ≤ 1.5 level px
/// breaks into a frame with gaps or bridges: a 100 mm marker from ~4.5 m
/// on the 1440x1080 camera). They are not quads: only windows for
/// [`full_res_quads`] to search again.
pub fn find_quads_and_blobs(
    params: &DetectParams,
    gray: &(impl MatTraitConst + ToInputArray),
) -> Result<(Vec<Quad>, Vec<Quad>), DetectError> {
    find_quads_and_blobs_within(params, gray, None)
}

/// [`find_quads_and_blobs`], with `windows` (full-resolution rectangles)
/// only the dark regions that lie wholly inside one of them: the image is
/// thresholded whole, as always, but its contours are traced only there,
/// so every region inside a window gives the very contour it gives in the
/// whole image's search, and a region the window's edge cuts none.
pub fn find_quads_and_blobs_within(
    params: &DetectParams,
    gray: &(impl MatTraitConst + ToInputArray),
    windows: Option<&[Rect]>,
) -> Result<(Vec<Quad>, Vec<Quad>), DetectError> {
    let mut found = Found::default();
    match without_edge_artefacts(gray)? {
        Some(cleaned) => search_level(params, &cleaned, windows, &mut found)?,
        None => search_level(params, gray, windows, &mut found)?,
    }
    Ok((found.quads, found.blobs))
}

/// What one level's contours gave: quads, and (downsampled levels only) blobs.
#[derive(Default)]
struct Found {
    quads: Vec<Quad>,
    blobs: Vec<Quad>,
}

/// The quads of `img` searched at half size when it is wider than
/// [`DetectParams::full_res_max_width`], else in place (no copy).
fn search_level(
    params: &DetectParams,
    img: &(impl MatTraitConst + ToInputArray),
    windows: Option<&[Rect]>,
    found: &mut Found,
) -> Result<(), DetectError> {
    match half_level(params, img)? {
        Some(half) => quads_of_level(
            params,
            &half,
            Place::whole(&half, 2.0),
            None,
            windows,
            found,
        ),
        None => quads_of_level(params, img, Place::whole(img, 1.0), None, windows, found),
    }
}

/// Half of `gray` when it is wider than [`DetectParams::full_res_max_width`]
/// (the quads are then searched at half size), else `None`.
fn half_level(
    params: &DetectParams,
    gray: &(impl MatTraitConst + ToInputArray),
) -> Result<Option<Mat>, DetectError> {
    if gray.cols() <= params.full_res_max_width {
        return Ok(None);
    }
    let mut half = Mat::default();
    imgproc::resize(
        gray,
        &mut half,
        Size::new(gray.cols() / 2, gray.rows() / 2),
        0.0,
        0.0,
        imgproc::INTER_AREA,
    )?;
    Ok(Some(half))
}

/// An edge line at least this far (mean |difference|, grey levels) from
/// its neighbour…
const EDGE_LINE_MIN_STEP_DN: f64 = 12.0;
/// …and this many times farther than the neighbour is from the next line
/// (plus [`EDGE_LINE_SLACK_DN`]) is not image.
const EDGE_LINE_RATIO: f64 = 4.0;
const EDGE_LINE_SLACK_DN: f64 = 2.0;

/// Which of the frame's edge lines (top row, bottom row, left column,
/// right column) are artefacts: far from their neighbour line where the
/// neighbour is close to the next one. Image content that reaches the edge
/// continues into the neighbour lines and does not qualify; nor does a
/// frame smaller than 8 pixels either way.
pub fn edge_line_artefacts(gray: &impl MatTraitConst) -> Result<[bool; 4], DetectError> {
    let (w, h) = (gray.cols(), gray.rows());
    if w < 8 || h < 8 || gray.typ() != opencv::core::CV_8UC1 {
        return Ok([false; 4]);
    }
    // Rows as slices (a strided Mat is read row by row as well).
    let rows: Vec<&[u8]> = (0..h)
        .map(|y| gray.at_row::<u8>(y))
        .collect::<Result<_, _>>()?;
    // Mean |a − b| between lines `a` and `b` (rows when `by_rows`, else columns).
    let diff = |by_rows: bool, a: i32, b: i32| -> Result<f64, DetectError> {
        let sum: u64 = if by_rows {
            let (ra, rb) = (rows[a as usize], rows[b as usize]);
            ra.iter()
                .zip(rb)
                .map(|(&p, &q)| u64::from(p.abs_diff(q)))
                .sum()
        } else {
            let (a, b) = (a as usize, b as usize);
            rows.iter().map(|r| u64::from(r[a].abs_diff(r[b]))).sum()
        };
        Ok(sum as f64 / f64::from(if by_rows { w } else { h }))
    };
    let mut out = [false; 4];
    for (k, (by_rows, edge, n1, n2)) in [
        (true, 0, 1, 2),
        (true, h - 1, h - 2, h - 3),
        (false, 0, 1, 2),
        (false, w - 1, w - 2, w - 3),
    ]
    .into_iter()
    .enumerate()
    {
        let (d01, d12) = (diff(by_rows, edge, n1)?, diff(by_rows, n1, n2)?);
        out[k] = d01 >= EDGE_LINE_MIN_STEP_DN && d01 > EDGE_LINE_RATIO * d12 + EDGE_LINE_SLACK_DN;
    }
    Ok(out)
}

/// A copy of `gray` with each artefact edge line ([`edge_line_artefacts`])
/// replaced by its neighbour; `None` when there is none.
fn without_edge_artefacts(gray: &impl MatTraitConst) -> Result<Option<Mat>, DetectError> {
    let bad = edge_line_artefacts(gray)?;
    if !bad.contains(&true) {
        return Ok(None);
    }
    // A clone is continuous: rows of `w` bytes, one after the other.
    let mut c = gray.try_clone()?;
    let (w, h) = (c.cols() as usize, c.rows() as usize);
    let d = c.data_bytes_mut()?;
    for (k, (rows, edge, n1)) in [
        (true, 0, 1),
        (true, h - 1, h - 2),
        (false, 0, 1),
        (false, w - 1, w - 2),
    ]
    .into_iter()
    .enumerate()
    {
        if !bad[k] {
            continue;
        }
        if rows {
            d.copy_within(n1 * w..(n1 + 1) * w, edge * w);
        } else {
            for row in d.chunks_exact_mut(w) {
                row[edge] = row[n1];
            }
        }
    }
    Ok(Some(c))
}

/// Where a searched image lies in the frame: `scale` full-resolution
/// pixels per pixel, its top-left at `offset` (full-resolution pixels),
/// and the frame's own outline at that scale (`2 (w + h)`, in the image's
/// pixels; an outline longer is the background's, [`contour_quad`]).
#[derive(Debug, Clone, Copy)]
struct Place {
    scale: f64,
    offset: Px,
    frame_outline: f64,
}

impl Place {
    /// `level` is the whole frame at `scale`.
    fn whole(level: &impl MatTraitConst, scale: f64) -> Self {
        Place {
            scale,
            offset: [0.0, 0.0],
            frame_outline: 2.0 * f64::from(level.cols() + level.rows()),
        }
    }
}

/// The quads of one image (`level`, placed in the frame at `at`),
/// appended to `found` unless already there.
fn quads_of_level(
    params: &DetectParams,
    level: &(impl MatTraitConst + ToInputArray),
    at: Place,
    noise_dn: Option<f64>,
    windows: Option<&[Rect]>,
    found: &mut Found,
) -> Result<(), DetectError> {
    let mut bin = Mat::default();
    let mut approx: Vec<Point> = Vec::new();
    let mut traced = Contours::new();
    let view = GrayView::new(level)?;
    // The noise only matters to the flat test of the relative offset.
    let noise_dn = match (params.contrast_offset, noise_dn) {
        (Some(rel), _) if rel.flat_below_sigmas <= 0.0 => 0.0,
        (None, _) => 0.0,
        (Some(_), Some(n)) => n,
        (Some(_), None) => noise_sigma_dn(&view),
    };
    let mut table = SumTable::new(view);
    // The windows at this level (pixels of the level, within it, merged).
    let (scale, offset) = (at.scale, at.offset);
    let level_windows =
        windows.map(|ws| level_rects(ws, scale, offset, [level.cols(), level.rows()]));
    for &win in &params.threshold_windows {
        let win = (win.max(3)) | 1;
        binarize(params, level, win, noise_dn, &mut bin)?;
        drop_isolated(&mut bin)?;
        // The whole level, or each window of it (its contours in level pixels).
        let searched: Vec<Option<Rect>> = match &level_windows {
            None => vec![None],
            Some(rects) => rects.iter().copied().map(Some).collect(),
        };
        for window in searched {
            traced.trace(&GrayView::new(&bin)?, window);
            for c in traced.iter() {
                let shape = contour_quad(params, (level, &mut table), &at, c, &mut approx, window)?;
                let (shapes, list, exact_only) = match &shape {
                    Shape::Quad(q) => (std::slice::from_ref(q), &mut found.quads, false),
                    Shape::Joined(qs) => (qs.as_slice(), &mut found.quads, true),
                    Shape::Blob(q) => (std::slice::from_ref(q), &mut found.blobs, false),
                    Shape::Neither => continue,
                };
                for q in shapes {
                    // Level pixel centres to full-resolution pixel centres.
                    let q = q.map(|c| {
                        [
                            (c[0] + 0.5) * scale - 0.5 + offset[0],
                            (c[1] + 0.5) * scale - 0.5 + offset[1],
                        ]
                    });
                    // The same square found by another threshold window (or
                    // as a quad of its own and joined): keep one, read as a
                    // quad of its own where it was one.
                    if let Some(o) = list.iter_mut().find(|o| o.same_as(&q)) {
                        o.exact_only &= exact_only;
                        continue;
                    }
                    list.push(Quad {
                        pts: q,
                        inset_px: 0.5 * scale,
                        exact_only,
                    });
                }
            }
        }
    }
    Ok(())
}

/// Full-resolution rectangles `rects` on a level of `scale` full-resolution
/// pixels per pixel whose top-left is at `offset`: outward to whole level
/// pixels, within the level's `size`, and merged while any two overlap
/// (a region in the overlap is then traced once, whole).
fn level_rects(rects: &[Rect], scale: f64, offset: Px, size: [i32; 2]) -> Vec<Rect> {
    let mut boxes: Vec<[i32; 4]> = rects
        .iter()
        .map(|r| {
            let to =
                |v: i32, o: f64, round: fn(f64) -> f64| round((f64::from(v) - o) / scale) as i32;
            [
                to(r.x, offset[0], f64::floor).clamp(0, size[0]),
                to(r.y, offset[1], f64::floor).clamp(0, size[1]),
                to(r.x + r.width, offset[0], f64::ceil).clamp(0, size[0]),
                to(r.y + r.height, offset[1], f64::ceil).clamp(0, size[1]),
            ]
        })
        .filter(|b| b[2] > b[0] && b[3] > b[1])
        .collect();
    let overlap =
        |a: &[i32; 4], b: &[i32; 4]| a[0] < b[2] && b[0] < a[2] && a[1] < b[3] && b[1] < a[3];
    let mut merged = true;
    while merged {
        merged = false;
        let mut i = 0;
        while i < boxes.len() {
            let mut j = i + 1;
            while j < boxes.len() {
                if overlap(&boxes[i], &boxes[j]) {
                    let b = boxes.swap_remove(j);
                    let a = &mut boxes[i];
                    *a = [
                        a[0].min(b[0]),
                        a[1].min(b[1]),
                        a[2].max(b[2]),
                        a[3].max(b[3]),
                    ];
                    merged = true;
                } else {
                    j += 1;
                }
            }
            i += 1;
        }
    }
    boxes
        .into_iter()
        .map(|b| Rect::new(b[0], b[1], b[2] - b[0], b[3] - b[1]))
        .collect()
}

/// Clears every dark pixel of `bin` (255 on 0) that has no dark pixel
/// among its eight neighbours. Its contour would be a single point, never a
/// quad or a blob, and no other contour changes: contours follow 8-connected
/// dark regions, and an isolated pixel is its own region, next to none
/// (so clearing one in place cannot make another isolated either). Sensor
/// noise thresholded at twice its σ (the floor of a flat region) leaves
/// thousands of them on a 720x540 level, which `findContours` would
/// otherwise trace one by one.
fn drop_isolated(bin: &mut Mat) -> Result<(), DetectError> {
    let (w, h) = (bin.cols() as usize, bin.rows() as usize);
    if w < 3 || h < 3 || !bin.is_continuous() {
        return Ok(());
    }
    let data = bin.data_bytes_mut()?;
    // Pixels are 0 or 255, so or-ing neighbours and and-ing the result
    // into a pixel clears it exactly when none is dark. `or3`: a row's
    // pixels or'ed with their left and right neighbours (for the rows above
    // and below); `beside`: the left and right neighbours alone. Written as
    // shifted slices, which the compiler vectorises.
    let or3 = |row: &[u8], out: &mut [u8]| {
        out[0] = row[0] | row[1];
        out[w - 1] = row[w - 2] | row[w - 1];
        for (o, ((&a, &b), &c)) in out[1..w - 1]
            .iter_mut()
            .zip(row[..w - 2].iter().zip(&row[1..w - 1]).zip(&row[2..]))
        {
            *o = a | b | c;
        }
    };
    let (mut above, mut next) = (vec![0u8; w], vec![0u8; w]);
    let mut beside = vec![0u8; w];
    for y in 0..h {
        if y + 1 < h {
            or3(&data[(y + 1) * w..(y + 2) * w], &mut next);
        } else {
            next.fill(0);
        }
        let row = &mut data[y * w..(y + 1) * w];
        beside[0] = row[1];
        beside[w - 1] = row[w - 2];
        for (o, (&a, &c)) in beside[1..w - 1]
            .iter_mut()
            .zip(row[..w - 2].iter().zip(&row[2..]))
        {
            *o = a | c;
        }
        for (v, ((&a, &b), &n)) in row.iter_mut().zip(above.iter().zip(&beside).zip(&next)) {
            *v &= a | b | n;
        }
        // Clearing changed nothing the next row's test reads: a cleared
        // pixel was next to no dark pixel of it.
        or3(row, &mut above);
    }
    Ok(())
}

/// Rows of an image [`noise_sigma_dn`] reads at most (evenly spread).
const NOISE_ROWS: usize = 48;

/// The noise of a grey image (grey levels): the standard deviation a
/// pixel has about its neighbours in flat regions, from the median of the
/// absolute differences between horizontal neighbours (`1.4826·MAD/√2`,
/// the median read between the integer levels). Edges are a small share of
/// any frame's neighbour pairs, so the median is the flat regions'; at most
/// [`NOISE_ROWS`] rows are read. 0 for an image narrower than 2 pixels.
pub fn noise_sigma_dn(view: &GrayView<'_>) -> f64 {
    let (w, h) = (view.width, view.height);
    if w < 2 || h == 0 {
        return 0.0;
    }
    let step = h.div_ceil(NOISE_ROWS).max(1);
    let mut hist = [0u64; 256];
    for y in (0..h).step_by(step) {
        let row = view.row(y);
        for p in row[..w].windows(2) {
            hist[usize::from(p[0].abs_diff(p[1]))] += 1;
        }
    }
    let n: u64 = hist.iter().sum();
    let half = n as f64 / 2.0;
    let mut below = 0.0;
    let mut median = 0.0;
    for (k, &c) in hist.iter().enumerate() {
        let c = c as f64;
        if below + c >= half && c > 0.0 {
            // |d| = 0 stands for (−0.5, 0.5), half a level wide once folded;
            // |d| = k for k ± 0.5.
            let frac = (half - below) / c;
            median = if k == 0 {
                0.5 * frac
            } else {
                k as f64 - 0.5 + frac
            };
            break;
        }
        below += c;
    }
    1.4826 * median / std::f64::consts::SQRT_2
}

/// Side of the square tiles over which [`binarize`] takes the local range.
const RANGE_TILE_PX: usize = 4;

/// The dark pixels of `level` (255, else 0): at least the offset below the
/// mean of their `win` x `win` window. The offset is
/// [`DetectParams::threshold_offset`], or, with
/// [`DetectParams::contrast_offset`], the one that follows the local
/// contrast ([`ContrastOffset`](super::ContrastOffset)). The fixed offset
/// is OpenCV's `adaptiveThreshold` (mean, inverted), bit for bit, and so is
/// the relative one wherever it comes to the fixed value. `noise_dn` is
/// the level's noise σ (what is flat, and the floor there).
fn binarize(
    params: &DetectParams,
    level: &(impl MatTraitConst + ToInputArray),
    win: i32,
    noise_dn: f64,
    bin: &mut Mat,
) -> Result<(), DetectError> {
    let rel = params
        .contrast_offset
        .filter(|_| level.typ() == opencv::core::CV_8UC1 && level.cols() >= 8 && level.rows() >= 8);
    let Some(rel) = rel else {
        imgproc::adaptive_threshold(
            level,
            bin,
            255.0,
            imgproc::ADAPTIVE_THRESH_MEAN_C,
            imgproc::THRESH_BINARY_INV,
            win,
            params.threshold_offset,
        )?;
        return Ok(());
    };
    // adaptiveThreshold's mean: a normalised box filter, same depth,
    // replicated border.
    let mut mean = Mat::default();
    imgproc::box_filter(
        level,
        &mut mean,
        -1,
        Size::new(win, win),
        Point::new(-1, -1),
        true,
        opencv::core::BORDER_REPLICATE | opencv::core::BORDER_ISOLATED,
    )?;
    // A continuous level is read in place; a strided one (a view) copied once.
    let copy = if level.is_continuous() {
        None
    } else {
        Some(level.try_clone()?)
    };
    let src_data = match &copy {
        Some(c) => c.data_bytes()?,
        None => level.data_bytes()?,
    };
    let (w, h) = (level.cols() as usize, level.rows() as usize);
    let tw = w.div_ceil(RANGE_TILE_PX);
    let offsets = tile_offsets(params, rel, noise_dn, src_data, w, h, win as usize);
    // Dark where src − mean ≤ −offset, as `adaptiveThreshold` decides it.
    let mut out = Mat::new_rows_cols_with_default(
        h as i32,
        w as i32,
        opencv::core::CV_8UC1,
        opencv::core::Scalar::all(0.0),
    )?;
    let (sd, md) = (src_data, mean.data_bytes()?);
    let od = out.data_bytes_mut()?;
    // Each tile row's offsets spread over its pixels once, then a
    // branch-free pass the compiler vectorises.
    let mut row_off = vec![0i16; w];
    for (y, ((sr, mr), or)) in sd
        .chunks_exact(w)
        .zip(md.chunks_exact(w))
        .zip(od.chunks_exact_mut(w))
        .enumerate()
    {
        if y % RANGE_TILE_PX == 0 {
            let tiles = &offsets[(y / RANGE_TILE_PX) * tw..][..tw];
            for (x, o) in row_off.iter_mut().enumerate() {
                *o = -i16::from(tiles[x / RANGE_TILE_PX]);
            }
        }
        for (((ov, &sv), &mv), &neg) in or.iter_mut().zip(sr).zip(mr).zip(&row_off) {
            *ov = u8::from(i16::from(sv) - i16::from(mv) <= neg) * 255;
        }
    }
    *bin = out;
    Ok(())
}

/// `f` (min or max) of the `tw` x `th` tile values `v` over the tiles
/// within `r` of each, separably: along rows, then along columns.
fn spread_tiles(
    v: &[u8],
    tw: usize,
    th: usize,
    r: usize,
    f: impl Fn(u8, u8) -> u8 + Copy,
) -> Vec<u8> {
    // Along rows: each tile against its neighbours up to `r` away, as
    // shifted copies of the row (passes the compiler vectorises).
    let mut a = v.to_vec();
    for (ar, vr) in a.chunks_exact_mut(tw).zip(v.chunks_exact(tw)) {
        for shift in 1..=r.min(tw.saturating_sub(1)) {
            for (av, &x) in ar[..tw - shift].iter_mut().zip(&vr[shift..]) {
                *av = f(*av, x);
            }
            for (av, &x) in ar[shift..].iter_mut().zip(&vr[..tw - shift]) {
                *av = f(*av, x);
            }
        }
    }
    let mut b = vec![0u8; v.len()];
    for (ty, br) in b.chunks_exact_mut(tw).enumerate() {
        let (y0, y1) = (ty.saturating_sub(r), (ty + r).min(th - 1));
        br.copy_from_slice(&a[y0 * tw..(y0 + 1) * tw]);
        for yy in y0 + 1..=y1 {
            for (bv, &av) in br.iter_mut().zip(&a[yy * tw..(yy + 1) * tw]) {
                *bv = f(*bv, av);
            }
        }
    }
    b
}

/// The integer offset (as `adaptiveThreshold` floors it) of every
/// [`RANGE_TILE_PX`] tile of the `w` x `h` image `data`: from the grey-level
/// range over the tiles within about half the window `win` of it, and at
/// least the noise floor where the range over [`FLAT_EXTRA_TILES`] more is
/// flat against the image's noise `noise_dn` (0: no such test).
fn tile_offsets(
    params: &DetectParams,
    rel: super::ContrastOffset,
    noise_dn: f64,
    data: &[u8],
    w: usize,
    h: usize,
    win: usize,
) -> Vec<u8> {
    let t = RANGE_TILE_PX;
    let (tw, th) = (w.div_ceil(t), h.div_ceil(t));
    let (mut lo, mut hi) = (vec![u8::MAX; tw * th], vec![0u8; tw * th]);
    // Per tile row: the column-wise extremes over its rows first (a pass the
    // compiler vectorises), then each tile's over its columns.
    let (mut col_lo, mut col_hi) = (vec![u8::MAX; w], vec![0u8; w]);
    for (ty, rows) in data.chunks(t * w).take(th).enumerate() {
        col_lo.fill(u8::MAX);
        col_hi.fill(0);
        for row in rows.chunks_exact(w) {
            for ((l, u), &v) in col_lo.iter_mut().zip(col_hi.iter_mut()).zip(row) {
                *l = (*l).min(v);
                *u = (*u).max(v);
            }
        }
        let k0 = ty * tw;
        // Whole tiles (a fixed-size fold the compiler unrolls), the last,
        // narrower one apart.
        let whole = w / t;
        for (tx, (cl, ch)) in col_lo
            .chunks_exact(RANGE_TILE_PX)
            .zip(col_hi.chunks_exact(RANGE_TILE_PX))
            .enumerate()
        {
            let (cl, ch): (&[u8; RANGE_TILE_PX], &[u8; RANGE_TILE_PX]) = (
                cl.try_into().expect("a whole tile"),
                ch.try_into().expect("a whole tile"),
            );
            lo[k0 + tx] = cl.iter().fold(u8::MAX, |a, &b| a.min(b));
            hi[k0 + tx] = ch.iter().fold(0, |a, &b| a.max(b));
        }
        if whole < tw {
            lo[k0 + whole] = col_lo[whole * t..].iter().copied().min().unwrap_or(u8::MAX);
            hi[k0 + whole] = col_hi[whole * t..].iter().copied().max().unwrap_or(0);
        }
    }
    // Tiles within `r` of a tile, separably: rows, then columns. Whether
    // a tile is flat is read over a wider neighbourhood (`r` plus
    // FLAT_EXTRA_TILES): a faint, blurred marker's range over the window
    // alone is within the noise's spread; over the wider one some part of
    // its edges lifts it out.
    let r = ((win / 2 + t / 2) / t).max(1);
    let (lo, hi) = (
        spread_tiles(&lo, tw, th, r, u8::min),
        spread_tiles(&hi, tw, th, r, u8::max),
    );
    // The wider neighbourhood's extremes are the extremes of the narrow
    // ones within FLAT_EXTRA_TILES.
    let wide = noise_dn > 0.0 && rel.flat_below_sigmas > 0.0;
    let (lo_w, hi_w) = if wide {
        (
            spread_tiles(&lo, tw, th, FLAT_EXTRA_TILES, u8::min),
            spread_tiles(&hi, tw, th, FLAT_EXTRA_TILES, u8::max),
        )
    } else {
        (Vec::new(), Vec::new())
    };
    // The offset of every possible range, looked up per tile.
    let fixed = params.threshold_offset;
    let by_range: [u8; 256] = std::array::from_fn(|range| {
        let range = range as f64;
        let off = if range < rel.flat_below_dn {
            fixed
        } else {
            (rel.fraction * range).clamp(rel.min_dn.min(fixed), fixed)
        };
        off.floor() as u8
    });
    let offsets = lo
        .iter()
        .zip(&hi)
        .map(|(&l, &u)| by_range[usize::from(u - l)]);
    if !wide {
        return offsets.collect();
    }
    // Flat against the noise: the floor, where it is above the offset.
    let below = rel.flat_below_sigmas * noise_dn;
    let floor = (rel.flat_floor_sigmas * noise_dn).min(255.0).floor() as u8;
    offsets
        .zip(lo_w.iter().zip(&hi_w))
        .map(|(o, (&l, &u))| {
            if f64::from(u - l) < below {
                o.max(floor)
            } else {
                o
            }
        })
        .collect()
}

/// How many tiles beyond the threshold window's the neighbourhood reaches
/// over which [`tile_offsets`] decides that a region is flat against the
/// noise.
const FLAT_EXTRA_TILES: usize = 2;

/// The length of the closed polygon `pts`, as `cv::arcLength(pts, true)`
/// computes it for integer points (each step's length in `f32`, summed in
/// `f64`), so to the bit: without a call into OpenCV per contour, most of
/// which (noise's speckle) this length alone rejects.
pub(crate) fn closed_length(pts: &[Point]) -> f64 {
    let [.., last] = pts else {
        return 0.0;
    };
    if pts.len() == 1 {
        return 0.0;
    }
    let mut prev = (last.x as f32, last.y as f32);
    let mut perimeter = 0.0f64;
    for p in pts {
        let q = (p.x as f32, p.y as f32);
        let (dx, dy) = (q.0 - prev.0, q.1 - prev.1);
        perimeter += f64::from((dx * dx + dy * dy).sqrt());
        prev = q;
    }
    perimeter
}

/// What a contour is: a quad, a blob ([`find_quads_and_blobs`]) or neither.
enum Shape {
    Quad([Px; 4]),
    Blob([Px; 4]),
    /// Quads whose sides are long straight runs of a larger region's
    /// outline ([`quads_of_long_edges`]): read only on an exact code.
    Joined(Vec<[Px; 4]>),
    Neither,
}

/// A blob's least darkening against its surround, as a share of
/// [`DetectParams::min_contrast`] ([`SumTable::contrast`]). A far marker's blob
/// (half dark, in its white quiet zone) is ~6.5 grey levels below its
/// surround on the 1440x1080 camera at 0.5 /m and 5 m; the sensor noise's
/// speckle blobs, of the same size and shape, are within 1.1 (four
/// rendered fleet frames; `docs/detector.md`, *The paper's swarm range*).
const BLOB_CONTRAST: f64 = 0.5;

/// A summed-area table of a level, built on first use (the blob test).
struct SumTable<'a> {
    view: GrayView<'a>,
    /// `(width + 1) x (height + 1)`, row-major; entry (x, y) sums the pixels
    /// above and left of it, modulo 2³²: a rectangle's sum, the wrapping
    /// difference of four entries, is exact for any rectangle of fewer than
    /// 2³²/255 (16.8 million) pixels; the blob test asks for a blob's
    /// neighbourhood, a few hundred.
    sums: Vec<u32>,
}

impl<'a> SumTable<'a> {
    fn new(view: GrayView<'a>) -> Self {
        SumTable {
            view,
            sums: Vec::new(),
        }
    }

    /// Sum and count of the pixels in `[x0, x1) x [y0, y1)`, clipped to the level.
    fn sum(&mut self, x0: i32, y0: i32, x1: i32, y1: i32) -> (f64, f64) {
        let (w, h) = (self.view.width, self.view.height);
        if self.sums.is_empty() {
            // Each line: the row's running sums, then the line above added.
            let stride = w + 1;
            self.sums.reserve_exact(stride * (h + 1));
            self.sums.resize(stride, 0);
            for y in 0..h {
                let mut run = 0u32;
                self.sums.push(0);
                self.sums.extend(self.view.row(y)[..w].iter().map(|&v| {
                    run = run.wrapping_add(u32::from(v));
                    run
                }));
                let (above, line) = self.sums[y * stride..].split_at_mut(stride);
                for (s, &a) in line.iter_mut().zip(above.iter()) {
                    *s = s.wrapping_add(a);
                }
            }
        }
        let clip = |v: i32, n: usize| (v.max(0) as usize).min(n);
        let (x0, x1, y0, y1) = (clip(x0, w), clip(x1, w), clip(y0, h), clip(y1, h));
        if x1 <= x0 || y1 <= y0 {
            return (0.0, 0.0);
        }
        let at = |x: usize, y: usize| self.sums[y * (w + 1) + x];
        let s = at(x1, y1)
            .wrapping_add(at(x0, y0))
            .wrapping_sub(at(x0, y1))
            .wrapping_sub(at(x1, y0));
        (f64::from(s), ((x1 - x0) * (y1 - y0)) as f64)
    }

    /// How much darker the pixels inside `rect` (x, y, width, height) are
    /// than those of the band half its larger side wide around it (grey
    /// levels; the parts inside the level).
    fn contrast(&mut self, rect: [i32; 4]) -> f64 {
        let [x, y, w, h] = rect;
        let pad = (w.max(h) / 2).max(2);
        let (inner, n_inner) = self.sum(x, y, x + w, y + h);
        let (all, n_all) = self.sum(x - pad, y - pad, x + w + pad, y + h + pad);
        if n_inner == 0.0 || n_all <= n_inner {
            return 0.0;
        }
        (all - inner) / (n_all - n_inner) - inner / n_inner
    }
}

/// The contour `c` of `level` as a convex quad, clockwise, in level
/// pixels ([`Shape::Quad`]), or, on a downsampled level, as a blob's
/// convex hull ([`Shape::Blob`]); where it is neither (or its region is
/// cut by the level's or window's edge, or on a downsampled level is the
/// background's: an outline longer than the frame's, [`Place`]), the quads
/// pieced from its straight runs ([`Shape::Joined`], [`quads_of_long_edges`]);
/// [`Shape::Neither`] when there are none, the region is too small or (at
/// full resolution) the background's, or a corner comes closer than
/// [`DetectParams::border_margin_px`] to the border. `approx` is scratch
/// space for the polygon; `at` places `level` in the frame.
fn contour_quad(
    params: &DetectParams,
    (level, table): (&impl MatTraitConst, &mut SumTable<'_>),
    at: &Place,
    c: &[Point],
    approx: &mut Vec<Point>,
    window: Option<Rect>,
) -> Result<Shape, DetectError> {
    let (w, h) = (f64::from(level.cols()), f64::from(level.rows()));
    let scale = at.scale;
    let min_side_lvl = params.min_code_side_px / scale;
    if c.len() < 4 {
        return Ok(Shape::Neither);
    }
    let perim = closed_length(c);
    if perim < 4.0 * min_side_lvl {
        return Ok(Shape::Neither);
    }
    // One longer than the frame's own outline is background: no quad, and
    // at full resolution no marker joined to it is looked for either (on
    // the tank video that search cost 0.12 ms a frame and read nothing).
    // On a downsampled level it is: there the pixel or two between a
    // marker and what stands behind it closes, and the marker becomes part
    // of the background's dark region (the rotation steps' +70° tag, whose
    // border meets a shelf's post at half size and not at full size).
    let background = perim > at.frame_outline;
    if background && scale <= 1.0 {
        return Ok(Shape::Neither);
    }
    // The rectangle the contour was traced in: the level, or the window
    // ([`find_quads_and_blobs_within`]).
    let bounds = window.unwrap_or(Rect::new(0, 0, level.cols(), level.rows()));
    // A region that reaches the outermost row or column of the level or
    // window is cut by it (its outline follows the cut, not a square, and
    // may go on outside): no quad, but a marker joined to it may be.
    let (x1, y1) = (bounds.x + bounds.width - 1, bounds.y + bounds.height - 1);
    let cut = c
        .iter()
        .any(|p| p.x <= bounds.x || p.y <= bounds.y || p.x >= x1 || p.y >= y1);
    let joined = || -> Shape {
        let margin = params.border_margin_px / scale;
        let quads: Vec<[Px; 4]> = quads_of_long_edges(c, min_side_lvl, bounds)
            .into_iter()
            .filter(|q| within_margin(q, margin, [w, h]))
            .map(|mut q| {
                if signed_area2(&q) < 0.0 {
                    q.swap(1, 3);
                }
                q
            })
            .collect();
        if quads.is_empty() {
            Shape::Neither
        } else {
            Shape::Joined(quads)
        }
    };
    if cut || background {
        return Ok(joined());
    }
    approx_closed(c, params.approx_epsilon * perim, approx);
    let blob = approx.len() != 4 || !is_convex(approx);
    if blob && (scale <= 1.0 || perim > 4.0 * params.full_res_region_max_side_px / scale) {
        return Ok(joined());
    }
    if blob {
        // Only on a downsampled level, and only of a size the full-resolution
        // search is for: its convex hull nearly a quadrilateral.
        if scale <= 1.0 || perim > 4.0 * params.full_res_region_max_side_px / scale {
            return Ok(Shape::Neither);
        }
        // Darker than what surrounds it, as a marker with its quiet zone
        // is and sensor noise's speckle is not.
        let r = bounding_box(c);
        if table.contrast([r.x, r.y, r.width, r.height]) < BLOB_CONTRAST * params.min_contrast {
            return Ok(Shape::Neither);
        }
        // OpenCV's own copy of the outline, for its hull.
        let c = Vector::<Point>::from_slice(c);
        let mut hull: Vector<Point> = Vector::new();
        imgproc::convex_hull(&c, &mut hull, true, true)?;
        let hull_perim = closed_length(hull.as_slice());
        approx_closed(hull.as_slice(), params.approx_epsilon * hull_perim, approx);
        if approx.len() != 4 {
            return Ok(Shape::Neither);
        }
    }
    let mut q = [[0.0; 2]; 4];
    for (i, pt) in approx.iter().enumerate() {
        q[i] = [f64::from(pt.x), f64::from(pt.y)];
    }
    if !within_margin(&q, params.border_margin_px / scale, [w, h]) {
        return Ok(Shape::Neither);
    }
    // The polygon traces the centres of the region's boundary pixels, half a
    // pixel inside the square's edge at each end: the square's side is one
    // level pixel longer than the traced one (a steeply tilted small tag's
    // short side sits right at the limit).
    if min_side(&q) + 1.0 < min_side_lvl {
        return Ok(Shape::Neither);
    }
    if signed_area2(&q) < 0.0 {
        q.swap(1, 3);
    }
    Ok(if blob { Shape::Blob(q) } else { Shape::Quad(q) })
}

/// The corner margin: every corner of `q` at least `margin` inside a level
/// of `size` (width, height).
fn within_margin(q: &[Px; 4], margin: f64, [w, h]: [f64; 2]) -> bool {
    q.iter().all(|c| {
        c[0] >= margin && c[1] >= margin && c[0] <= w - 1.0 - margin && c[1] <= h - 1.0 - margin
    })
}

/// How far (level pixels) an outline's points may stray from the line of
/// the straight run they belong to ([`straight_runs`]): a square's side,
/// blurred and sampled, stays within a pixel or so of its line, and a long
/// one bows by a pixel and a half (the rotation steps' +70° tag, 98 px).
const JOINED_EPS_PX: f64 = 1.5;
/// Each side's straight run covers at least this share of it…
const JOINED_MIN_COVER: f64 = 0.5;
/// …and reaches no further than this share beyond either corner.
const JOINED_MAX_OVERHANG: f64 = 0.15;
/// The sine of the sharpest corner a joined quad may have (20°).
const JOINED_MIN_CORNER_SIN: f64 = 0.342;
/// At most this many quads tried per outline (bounds the cost on a
/// region of texture; a marker's four runs link to few others).
const JOINED_MAX_TRIED: usize = 4096;

/// Convex quads whose four sides are straight runs of the outline `c`
/// (in the outline's order), for a region that is no quad itself: a
/// marker whose black border touches a dark neighbour (a card's shaded
/// edge, its stand, a shadow, texture reaching the frame's edge) is one
/// region with it, whose outline still runs along most of the marker's
/// four sides. The outline is cut into straight runs ([`straight_runs`]);
/// runs along the edge of `bounds` (where the region was cut) and shorter
/// than `min_side` are left out. Four runs, in the outline's order, each
/// crossing the next at a corner ahead of its own end and behind the
/// next's start, are the sides; their lines' crossings the corners
/// ([`quad_of_runs`]). Of quads sharing a run, the one whose runs cover
/// the most of its sides is kept.
fn quads_of_long_edges(c: &[Point], min_side: f64, bounds: Rect) -> Vec<[Px; 4]> {
    let (x0, y0) = (f64::from(bounds.x), f64::from(bounds.y));
    let (x1, y1) = (
        x0 + f64::from(bounds.width - 1),
        y0 + f64::from(bounds.height - 1),
    );
    let on_cut = |a: Px, b: Px| {
        (a[0] <= x0 && b[0] <= x0)
            || (a[1] <= y0 && b[1] <= y0)
            || (a[0] >= x1 && b[0] >= x1)
            || (a[1] >= y1 && b[1] >= y1)
    };
    let runs: Vec<Run> = straight_runs(c, min_side)
        .into_iter()
        .filter(|&(a, b)| !on_cut(a, b))
        .map(|(a, b)| Run::new(a, b))
        .collect();
    let m = runs.len();
    if m < 4 {
        return Vec::new();
    }
    let next = linked_runs(&runs, JOINED_REACH, |i, j| follows(&runs, i, j));
    let mut found: Vec<(f64, [usize; 4], [Px; 4])> = Vec::new();
    four_cycles(&next, |ks| {
        let sides = ks.map(|k| (runs[k].a, runs[k].b));
        if let Some((q, cover)) = quad_of_runs(&sides, min_side) {
            found.push((cover, ks, q));
        }
    });
    found.sort_by(|x, y| y.0.total_cmp(&x.0));
    let mut used = vec![false; m];
    let mut quads = Vec::new();
    for (_, ks, q) in found {
        if ks.iter().any(|&k| used[k]) {
            continue;
        }
        ks.iter().for_each(|&k| used[k] = true);
        quads.push(q);
    }
    quads
}

/// At most this many paths of three links followed per outline: a
/// bound on the search's time where the runs link densely (texture, a
/// regular grid). Through the realistic camera after HOIRM the most an
/// outline took was ~24 000 (`eval node-rate --profile realistic`), on the
/// real recordings ~3 700.
const JOINED_MAX_PATHS: usize = 1 << 20;

/// Every cycle `a → b → c → d → a` of `next` (each run's possible
/// successors, ascending) with `a < b < c < d`, in order, given to
/// `visit`: each quad once, from its first run in the outline's order. At
/// most [`JOINED_MAX_TRIED`] cycles and [`JOINED_MAX_PATHS`] paths; returns
/// the paths followed.
fn four_cycles(next: &[Vec<usize>], mut visit: impl FnMut([usize; 4])) -> usize {
    let (mut tried, mut paths) = (0, 0);
    'search: for (a, after_a) in next.iter().enumerate() {
        for &b in after_a.iter().filter(|&&b| b > a) {
            for &c in next[b].iter().filter(|&&c| c > b) {
                for &d in next[c].iter().filter(|&&d| d > c) {
                    paths += 1;
                    if paths > JOINED_MAX_PATHS {
                        break 'search;
                    }
                    if !next[d].contains(&a) {
                        continue;
                    }
                    tried += 1;
                    if tried > JOINED_MAX_TRIED {
                        break 'search;
                    }
                    visit([a, b, c, d]);
                }
            }
        }
    }
    paths
}

/// A straight run of an outline: from `a` to `b`, `len` long, along the
/// unit vector `dir`.
#[derive(Debug, Clone, Copy)]
struct Run {
    a: Px,
    b: Px,
    len: f64,
    dir: Px,
}

impl Run {
    fn new(a: Px, b: Px) -> Self {
        let len = super::geom::dist(a, b);
        let dir = [(b[0] - a[0]) / len, (b[1] - a[1]) / len];
        Self { a, b, len, dir }
    }
}

/// How far, in lengths of a run, the corner it meets the next side at may
/// lie from its start (the cover's reach and the overhang beyond it).
const JOINED_REACH: f64 = (1.0 + JOINED_MAX_OVERHANG) / JOINED_MIN_COVER;

/// Whether run `j` of `runs` may follow run `i` as a
/// quad's next side: their lines cross at a corner ahead of i's end and
/// behind j's start, each run covering its share of the side up to it
/// ([`JOINED_MIN_COVER`], [`JOINED_MAX_OVERHANG`]), at a corner no sharper
/// than [`JOINED_MIN_CORNER_SIN`]. [`quad_of_runs`] checks the whole quad.
fn follows(runs: &[Run], i: usize, j: usize) -> bool {
    let reach = 1.0 / JOINED_MIN_COVER;
    let slack = JOINED_MAX_OVERHANG * reach;
    let (
        Run {
            a, len: li, dir: u, ..
        },
        Run {
            a: c,
            len: lj,
            dir: v,
            ..
        },
    ) = (runs[i], runs[j]);
    let sin = u[0] * v[1] - u[1] * v[0];
    if sin.abs() < JOINED_MIN_CORNER_SIN {
        return false;
    }
    // The corner a + t·l_i·u = c + s·l_j·v.
    let w = [c[0] - a[0], c[1] - a[1]];
    let t = (w[0] * v[1] - w[1] * v[0]) / sin / li;
    let s = (w[0] * u[1] - w[1] * u[0]) / sin / lj;
    (1.0 - slack..=reach + slack).contains(&t) && (-reach - slack..=slack).contains(&s)
}

/// Up to this many runs [`linked_runs`] asks every pair within reach of each
/// other directly; beyond, it looks them up in a grid of the starts.
const FEW_RUNS: usize = 16;

/// For each of `runs`, the runs that may follow it
/// (`links(i, j)`), ascending. `links` is asked only of pairs whose starts
/// lie within `reach·(l_i + l_j)` of each other, which every linked pair
/// does (the corner lies within `reach·l_i` of run i's start, run j's
/// start within `reach·l_j` of the corner): a grid of the starts, and each
/// pair looked up from its longer run. An outline of texture or noise has
/// thousands of short runs, and asking every pair cost up to ~0.3 s on one
/// outline (a frame through the realistic camera after HOIRM).
fn linked_runs(runs: &[Run], reach: f64, links: impl Fn(usize, usize) -> bool) -> Vec<Vec<usize>> {
    let m = runs.len();
    let mut next = vec![Vec::new(); m];
    let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
    for Run { a, .. } in runs {
        for k in 0..2 {
            lo[k] = lo[k].min(a[k]);
            hi[k] = hi[k].max(a[k]);
        }
    }
    if m == 0 || !(lo[0].is_finite() && lo[1].is_finite() && hi[0].is_finite() && hi[1].is_finite())
    {
        return next;
    }
    // A little over the bound, so that rounding never drops a pair.
    let within = |d2: f64, r: f64| d2 <= (r * (1.0 + 1e-9) + 1e-6).powi(2);
    // The pair (i, j), each way, when their starts are within reach.
    let mut ask = |i: usize, j: usize| {
        let (ri, rj) = (&runs[i], &runs[j]);
        let d2 = (rj.a[0] - ri.a[0]).powi(2) + (rj.a[1] - ri.a[1]).powi(2);
        if !within(d2, reach * (ri.len + rj.len)) {
            return;
        }
        if links(i, j) {
            next[i].push(j);
        }
        if links(j, i) {
            next[j].push(i);
        }
    };
    if m <= FEW_RUNS {
        // Few runs (most outlines): every pair, without building the grid.
        for i in 0..m {
            for j in i + 1..m {
                ask(i, j);
            }
        }
    } else {
        linked_by_grid(runs, reach, (lo, hi), &mut ask);
    }
    for n in &mut next {
        n.sort_unstable();
    }
    next
}

/// [`linked_runs`]' pairs looked up in a grid of the runs' starts (within
/// `lo..hi`): each pair near enough to link given to `ask` once, from its
/// longer run (ties by index).
fn linked_by_grid(
    runs: &[Run],
    reach: f64,
    (lo, hi): (Px, Px),
    ask: &mut impl FnMut(usize, usize),
) {
    const CELL_PX: f64 = 16.0;
    let m = runs.len();
    let cells = |k: usize| ((hi[k] - lo[k]) / CELL_PX) as usize + 1;
    let (nx, ny) = (cells(0), cells(1));
    let cell_of = |p: Px| {
        let c = |k: usize| ((p[k].clamp(lo[k], hi[k]) - lo[k]) / CELL_PX) as usize;
        (c(0).min(nx - 1), c(1).min(ny - 1))
    };
    let mut grid: Vec<Vec<usize>> = vec![Vec::new(); nx * ny];
    for (k, r) in runs.iter().enumerate() {
        let (cx, cy) = cell_of(r.a);
        grid[cy * nx + cx].push(k);
    }
    // Runs ordered by length (ties by index): the longer of a pair looks the other up.
    let mut by_length: Vec<usize> = (0..m).collect();
    by_length.sort_unstable_by(|&i, &j| runs[i].len.total_cmp(&runs[j].len).then(i.cmp(&j)));
    let mut rank = vec![0; m];
    for (r, &k) in by_length.iter().enumerate() {
        rank[k] = r;
    }
    for (i, &Run { a, len: li, .. }) in runs.iter().enumerate() {
        let r = 2.0 * reach * li;
        let (cx0, cy0) = cell_of([a[0] - r, a[1] - r]);
        let (cx1, cy1) = cell_of([a[0] + r, a[1] + r]);
        for cy in cy0..=cy1 {
            for &j in grid[cy * nx + cx0..=cy * nx + cx1].iter().flatten() {
                // Each pair once, from its longer run (ties by index).
                if rank[j] < rank[i] {
                    ask(i, j);
                }
            }
        }
    }
}

/// The straight runs of the closed outline `pts` at least `min_len` long,
/// in its order: from each run's first point, the run goes on while every
/// point so far lies within [`JOINED_EPS_PX`] of the line from it to the
/// newest point (the directions that keep all of them that close form a
/// cone, narrowed at each point; a point outside it ends the run, and the
/// next starts where this one ended). Scanned from where a first run ends,
/// so that no run is cut by where the outline happens to begin.
fn straight_runs(pts: &[Point], min_len: f64) -> Vec<(Px, Px)> {
    let n = pts.len();
    if n < 2 {
        return Vec::new();
    }
    let at = |k: usize| {
        let p = pts[if k < n { k } else { k % n }];
        [f64::from(p.x), f64::from(p.y)]
    };
    let cross = |u: Px, v: Px| u[0] * v[1] - u[1] * v[0];
    let eps2 = JOINED_EPS_PX * JOINED_EPS_PX;
    // The index (from `from`, at most `n` on) of the last point of the run starting there.
    let run_end = |from: usize| -> usize {
        let a = at(from);
        // The cone: its clockwise and counter-clockwise edge directions
        // (not unit vectors), or none yet.
        let mut cone: Option<(Px, Px)> = None;
        let mut last = from + 1;
        let mut idx = from % n;
        for k in from + 1..=from + n {
            idx += 1;
            if idx == n {
                idx = 0;
            }
            let p = pts[idx];
            let d = [f64::from(p.x) - a[0], f64::from(p.y) - a[1]];
            let r2 = d[0] * d[0] + d[1] * d[1];
            if r2 <= eps2 {
                last = k;
                continue;
            }
            if let Some((lo, hi)) = cone {
                if cross(lo, d) < 0.0 || cross(d, hi) < 0.0 {
                    break;
                }
            }
            // d turned either way by asin(eps / r), scaled by r.
            let c = (r2 - eps2).sqrt();
            let e = JOINED_EPS_PX;
            let lo2 = [d[0] * c + d[1] * e, d[1] * c - d[0] * e];
            let hi2 = [d[0] * c - d[1] * e, d[1] * c + d[0] * e];
            cone = Some(match cone {
                None => (lo2, hi2),
                Some((lo, hi)) => (
                    if cross(lo, lo2) > 0.0 { lo2 } else { lo },
                    if cross(hi2, hi) > 0.0 { hi2 } else { hi },
                ),
            });
            last = k;
        }
        last
    };
    let start = run_end(0) % n;
    let mut runs = Vec::new();
    let mut i = start;
    while i < start + n {
        let j = run_end(i).min(start + n);
        let (a, b) = (at(i), at(j));
        if (b[0] - a[0]).powi(2) + (b[1] - a[1]).powi(2) >= min_len * min_len {
            runs.push((a, b));
        }
        i = j;
    }
    runs
}

/// The quad whose sides lie on the lines of the four runs `sides` (each
/// from its first point to its second, in order around the quad) and the
/// share of its sides the runs cover, when it is convex with no corner
/// sharper than [`JOINED_MIN_CORNER_SIN`], every side at least `min_side`
/// long, and each run covering [`JOINED_MIN_COVER`] of its side, in the
/// side's direction, within [`JOINED_MAX_OVERHANG`] of it.
fn quad_of_runs(sides: &[(Px, Px); 4], min_side: f64) -> Option<([Px; 4], f64)> {
    use super::geom::{dist, Line};
    let lines: Vec<Line> = sides
        .iter()
        .map(|&(p, q)| Line::through(p, q))
        .collect::<Option<_>>()?;
    // Corner i is where side i-1 meets side i.
    let mut q = [[0.0; 2]; 4];
    for i in 0..4 {
        q[i] = lines[(i + 3) % 4].intersect(&lines[i])?;
    }
    let turn = |i: usize| {
        let (a, b, c) = (q[i], q[(i + 1) % 4], q[(i + 2) % 4]);
        (b[0] - a[0]) * (c[1] - b[1]) - (b[1] - a[1]) * (c[0] - b[0])
    };
    let turns = [turn(0), turn(1), turn(2), turn(3)];
    if !(turns.iter().all(|&t| t > 0.0) || turns.iter().all(|&t| t < 0.0)) {
        return None;
    }
    let mut cover = 0.0;
    for (i, &(p0, p1)) in sides.iter().enumerate() {
        let (a, b, c) = (q[i], q[(i + 1) % 4], q[(i + 2) % 4]);
        let len = dist(a, b);
        // Four runs of one ragged line cross in slivers.
        if len < min_side || turns[i].abs() < JOINED_MIN_CORNER_SIN * len * dist(b, c) {
            return None;
        }
        let along =
            |p: Px| ((p[0] - a[0]) * (b[0] - a[0]) + (p[1] - a[1]) * (b[1] - a[1])) / (len * len);
        let (t0, t1) = (along(p0), along(p1));
        if t1 - t0 < JOINED_MIN_COVER || t0 < -JOINED_MAX_OVERHANG || t1 > 1.0 + JOINED_MAX_OVERHANG
        {
            return None;
        }
        cover += t1.min(1.0) - t0.max(0.0);
    }
    Some((q, cover / 4.0))
}

/// Where a quad's sides stand out as a marker's do: the image just inside
/// them (a twentieth of the quad in, within any code's black border, but
/// at least a pixel) darker, on the mean over the middle of every side,
/// than just outside (as far out: the quiet zone) by `min_contrast` grey
/// levels or more. A light cell of a grid or a hole in a dark region
/// (its outline traced along the dark around it) is not.
fn dark_inside(view: &GrayView<'_>, q: &[Px; 4], min_contrast: f64) -> bool {
    let depth = (1.0 / min_side(q).max(1.0)).max(0.05);
    // The quad's bilinear map: (0, 0) at q[0], (1, 0) at q[1], (1, 1) at q[2].
    let at = |u: f64, v: f64| {
        let w = [(1.0 - u) * (1.0 - v), u * (1.0 - v), u * v, (1.0 - u) * v];
        let x: f64 = (0..4).map(|k| w[k] * q[k][0]).sum();
        let y: f64 = (0..4).map(|k| w[k] * q[k][1]).sum();
        view.sample(x, y)
    };
    let (mut inside, mut outside) = (0.0, 0.0);
    for t in [0.3, 0.4, 0.5, 0.6, 0.7] {
        // The four sides: v = 0, u = 1, v = 1, u = 0; inside at ±depth.
        for (uv_in, uv_out) in [
            ((t, depth), (t, -depth)),
            ((1.0 - depth, t), (1.0 + depth, t)),
            ((t, 1.0 - depth), (t, 1.0 + depth)),
            ((depth, t), (-depth, t)),
        ] {
            inside += at(uv_in.0, uv_in.1);
            outside += at(uv_out.0, uv_out.1);
        }
    }
    (outside - inside) / 20.0 >= min_contrast
}

/// The per-marker pyramid level: on a downsampled frame a small marker's
/// code square (a module of 2 px or less) blurs into its frame and no
/// contour separates them, while the frame's outline is still found. Every
/// such small quad of `undecoded` (it read no code) is searched again at
/// full resolution in a window around it (at most
/// [`DetectParams::max_full_res_regions`], smallest first: the large ones
/// were readable at the level); so is every blob of the level
/// ([`find_quads_and_blobs`]), passed among `undecoded`. Returns the quads
/// not already in `quads`, but for those of `undecoded` themselves: found
/// again at full resolution, their corners are a level's half pixel
/// sharper, which is what a module of ~1.5 px at the level needs to read
/// (a 100 mm marker from 3.5 m on, 1440x1080, 60°).
pub fn full_res_quads(
    params: &DetectParams,
    view: &GrayView<'_>,
    undecoded: &[Quad],
    quads: &[Quad],
) -> Result<Vec<Quad>, DetectError> {
    let max_side = params.full_res_region_max_side_px;
    let mut small: Vec<(bool, f64, &Quad)> = undecoded
        .iter()
        .map(|q| (mean_side(&q.pts), q))
        .filter(|(s, _)| *s <= max_side)
        .map(|(s, q)| (!dark_inside(view, &q.pts, params.min_contrast), s, q))
        .collect();
    // Quads not darker inside than around last (the light cells of a
    // grid, holes in a dark region: no marker's outer square), then those
    // pieced from a larger region's outline (many on a textured frame,
    // and rarely a marker); smallest first.
    small.sort_by(|a, b| {
        (a.0, a.2.exact_only, a.1)
            .partial_cmp(&(b.0, b.2.exact_only, b.1))
            .unwrap_or(std::cmp::Ordering::Equal)
    });
    let (cols, rows) = (view.width as i32, view.height as i32);
    let mut done: Vec<opencv::core::Rect> = Vec::new();
    let mut extra: Vec<Quad> = Vec::new();
    let mut frame_noise: Option<f64> = None;
    for (_, side, q) in small.into_iter().take(params.max_full_res_regions) {
        let pad = 0.5 * side + 4.0;
        let x0 = q.pts.iter().map(|c| c[0]).fold(f64::INFINITY, f64::min) - pad;
        let y0 = q.pts.iter().map(|c| c[1]).fold(f64::INFINITY, f64::min) - pad;
        let x1 = q.pts.iter().map(|c| c[0]).fold(f64::NEG_INFINITY, f64::max) + pad;
        let y1 = q.pts.iter().map(|c| c[1]).fold(f64::NEG_INFINITY, f64::max) + pad;
        let (x0, y0) = ((x0.floor() as i32).max(0), (y0.floor() as i32).max(0));
        let (x1, y1) = ((x1.ceil() as i32).min(cols), (y1.ceil() as i32).min(rows));
        if x1 - x0 < 8 || y1 - y0 < 8 {
            continue;
        }
        let rect = opencv::core::Rect::new(x0, y0, x1 - x0, y1 - y0);
        // Nested quads (a frame's outer and inner outline) share one window.
        if done.iter().any(|d| (*d & rect) == rect) {
            continue;
        }
        done.push(rect);
        let mut data = Vec::with_capacity((rect.width * rect.height) as usize);
        for y in y0..y1 {
            data.extend_from_slice(&view.row(y as usize)[x0 as usize..x1 as usize]);
        }
        let roi = crate::mat::gray_to_mat(&shoal_proto::image::GrayImage {
            width: rect.width as u32,
            height: rect.height as u32,
            data,
        })?;
        let mut found = Found::default();
        // The frame's noise, not the window's: a far marker's 2 px modules
        // fill its window with edges a local estimate would take for noise.
        let noise = *frame_noise.get_or_insert_with(|| noise_sigma_dn(view));
        // A region the window cuts is measured against the frame's outline,
        // not the window's: a marker joined to the background at half size
        // is still joined to some of it here.
        let at = Place {
            scale: 1.0,
            offset: [f64::from(x0), f64::from(y0)],
            frame_outline: 2.0 * f64::from(cols + rows),
        };
        quads_of_level(params, &roi, at, Some(noise), None, &mut found)?;
        // A quad pieced from an outline here is either the queued quad
        // found again (sharper; a joined one's corners move by a few
        // pixels, so: the two overlapping by half or more) or a piece of
        // something the window's edge cuts (a neighbour's half, read by
        // chance): only the former counts.
        for f in found
            .quads
            .into_iter()
            .filter(|f| !f.exact_only || box_overlap(&q.pts, &f.pts) >= 0.5)
        {
            let known = quads.iter().any(|o| o.same_as(&f.pts))
                && !undecoded.iter().any(|o| o.same_as(&f.pts));
            if !known && !extra.iter().any(|o| o.same_as(&f.pts)) {
                extra.push(f);
            }
        }
    }
    Ok(extra)
}

/// The intersection over union of the two quads' bounding boxes (0 when
/// apart, 1 when the same).
fn box_overlap(a: &[Px; 4], b: &[Px; 4]) -> f64 {
    let bounds = |q: &[Px; 4]| {
        q.iter().fold(
            [
                f64::INFINITY,
                f64::INFINITY,
                f64::NEG_INFINITY,
                f64::NEG_INFINITY,
            ],
            |r, c| {
                [
                    r[0].min(c[0]),
                    r[1].min(c[1]),
                    r[2].max(c[0]),
                    r[3].max(c[1]),
                ]
            },
        )
    };
    let (p, q) = (bounds(a), bounds(b));
    let area = |r: [f64; 4]| (r[2] - r[0]).max(0.0) * (r[3] - r[1]).max(0.0);
    let inter = area([
        p[0].max(q[0]),
        p[1].max(q[1]),
        p[2].min(q[2]),
        p[3].min(q[3]),
    ]);
    let union = area(p) + area(q) - inter;
    if union > 0.0 {
        inter / union
    } else {
        0.0
    }
}

/// True when two quads have the same corners (in any cyclic order) within `tol`.
pub fn same_quad(a: &[Px; 4], b: &[Px; 4], tol: f64) -> bool {
    a.iter()
        .all(|p| b.iter().any(|q| super::geom::dist(*p, *q) < tol))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every contour of `bin` with more than one point, in order.
    fn contours_of(bin: &Mat) -> Vec<Vec<(i32, i32)>> {
        let mut contours: Vector<Vector<Point>> = Vector::new();
        imgproc::find_contours(
            bin,
            &mut contours,
            imgproc::RETR_LIST,
            imgproc::CHAIN_APPROX_SIMPLE,
            Point::new(0, 0),
        )
        .unwrap();
        contours
            .iter()
            .map(|c| c.iter().map(|p| (p.x, p.y)).collect::<Vec<_>>())
            .filter(|c| c.len() > 1)
            .collect()
    }

    /// A `w` x `h` grey image: a horizontal ramp from 60 to 80 (the
    /// vignetting and haze of a frame), with Gaussian noise of `sigma` grey
    /// levels, rounded.
    fn noisy_ramp(w: i32, h: i32, sigma: f64, seed: u64) -> Mat {
        use opencv::core::{Scalar, CV_8UC1};
        let mut rng = shoal_proto::splitmix::SplitMix64::new(seed);
        let mut img = Mat::new_rows_cols_with_default(h, w, CV_8UC1, Scalar::all(0.0)).unwrap();
        for y in 0..h {
            for x in 0..w {
                let (u1, u2) = (rng.unit().max(1e-12), rng.unit());
                let n = (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos();
                let v = 60.0 + 20.0 * f64::from(x) / f64::from(w) + sigma * n;
                *img.at_2d_mut::<u8>(y, x).unwrap() = v.round().clamp(0.0, 255.0) as u8;
            }
        }
        img
    }

    #[test]
    fn the_noise_estimate_is_the_pixel_noise_and_ignores_edges() {
        use opencv::core::{Rect, Scalar};
        for (sigma, seed) in [(0.7, 1), (1.2, 2), (2.5, 3), (6.0, 4)] {
            let mut img = noisy_ramp(720, 540, sigma, seed);
            let clean = noise_sigma_dn(&GrayView::new(&img).unwrap());
            // Markers' edges over a tenth of the frame do not move it much.
            for k in 0..12 {
                imgproc::rectangle(
                    &mut img,
                    Rect::new(20 + 58 * k, 200, 30, 30),
                    Scalar::all(20.0),
                    2,
                    imgproc::LINE_8,
                    0,
                )
                .unwrap();
            }
            let edged = noise_sigma_dn(&GrayView::new(&img).unwrap());
            // Rounding to integers adds 1/12 of a level² of variance.
            let expected = (sigma * sigma + 1.0 / 12.0).sqrt();
            for (what, got) in [("clean", clean), ("with edges", edged)] {
                assert!(
                    (got / expected - 1.0).abs() < 0.08,
                    "σ {sigma} {what}: estimated {got:.3}, expected {expected:.3}"
                );
            }
        }
        assert_eq!(
            noise_sigma_dn(&GrayView::new(&noisy_ramp(1, 10, 1.0, 1)).unwrap()),
            0.0
        );
    }

    /// An empty frame's noise is not traced: flat against the noise, its
    /// pixels need the floor to be dark. With flat judged in grey levels
    /// alone (the rule before), noise of 1.2 levels spans ~7 levels, the
    /// offset drops to 1 and a quarter of the frame is dark. (The ramp here
    /// adds ~1 level over the flat test's 36 px; one of 40 levels across
    /// the level adds 2, the range reaches 8σ on half the tiles and the
    /// rule before applies there: `docs/detector.md`, *Flat is relative to
    /// the noise*.)
    #[test]
    fn an_empty_noisy_frame_is_flat_against_its_noise() {
        let params = DetectParams::default();
        let absolute = DetectParams {
            contrast_offset: params
                .contrast_offset
                .map(|c| super::super::ContrastOffset {
                    flat_below_sigmas: 0.0,
                    ..c
                }),
            ..DetectParams::default()
        };
        let img = noisy_ramp(720, 540, 1.2, 9);
        let noise = noise_sigma_dn(&GrayView::new(&img).unwrap());
        // The dark share, and the contours long enough to be tried as a
        // quad (perimeter of four minimum sides at half size).
        let traced = |p: &DetectParams| {
            let mut bin = Mat::default();
            binarize(p, &img, 19, noise, &mut bin).unwrap();
            let share = f64::from(opencv::core::count_non_zero(&bin).unwrap()) / (720.0 * 540.0);
            let long = contours_of(&bin)
                .iter()
                .filter(|c| {
                    let pts: Vector<Point> = c.iter().map(|&(x, y)| Point::new(x, y)).collect();
                    imgproc::arc_length(&pts, true).unwrap() >= 2.0 * p.min_code_side_px
                })
                .count();
            (share, long)
        };
        let (now, before) = (traced(&params), traced(&absolute));
        // The floor, 2σ ≈ 2.4 levels, floored to 2: dark below −1.5 levels
        // in integers, ~11 % of the pixels, in small clusters.
        assert!(now.0 < 0.13, "dark share {:.3} with the noise rule", now.0);
        assert!(
            before.0 > 0.25,
            "dark share {:.3} with flat in grey levels",
            before.0
        );
        assert!(
            now.1 * 10 < before.1,
            "contours to try: {} with the noise rule, {} before",
            now.1,
            before.1
        );
    }

    /// [`closed_length`] is `cv::arcLength(_, true)` to the bit, on the
    /// contours of a noisy frame (speckle, long outlines, every direction
    /// of step) and on the degenerate cases.
    #[test]
    fn the_closed_length_is_opencvs_arc_length_to_the_bit() {
        let img = noisy_ramp(360, 270, 6.0, 5);
        let mut bin = Mat::default();
        imgproc::adaptive_threshold(
            &img,
            &mut bin,
            255.0,
            imgproc::ADAPTIVE_THRESH_MEAN_C,
            imgproc::THRESH_BINARY_INV,
            19,
            1.0,
        )
        .unwrap();
        let mut contours: Vector<Vector<Point>> = Vector::new();
        imgproc::find_contours(
            &bin,
            &mut contours,
            imgproc::RETR_LIST,
            imgproc::CHAIN_APPROX_SIMPLE,
            Point::new(0, 0),
        )
        .unwrap();
        assert!(contours.len() > 500, "{} contours", contours.len());
        let mut long = 0;
        for c in contours.iter() {
            let cv = imgproc::arc_length(&c, true).unwrap();
            assert_eq!(closed_length(c.as_slice()).to_bits(), cv.to_bits(), "{c:?}");
            long += usize::from(cv > 50.0);
        }
        assert!(long > 10, "{long} long contours");
        assert_eq!(closed_length(&[]), 0.0);
        for pts in [
            vec![Point::new(3, 4)],
            vec![Point::new(0, 0), Point::new(3, 4)],
        ] {
            let v: Vector<Point> = pts.iter().copied().collect();
            assert_eq!(
                closed_length(&pts).to_bits(),
                imgproc::arc_length(&v, true).unwrap().to_bits()
            );
        }
    }

    #[test]
    fn dropping_isolated_pixels_leaves_every_other_contour_as_it_was() {
        use opencv::core::{Scalar, CV_8UC1};
        // Speckle at several densities (the sparse one mostly single
        // pixels, the dense one near percolation, clusters everywhere),
        // with squares and frames among it, touching the image border too.
        let mut rng = shoal_proto::splitmix::SplitMix64::new(5);
        for density in [0.02, 0.1, 0.3] {
            let (w, h) = (97, 61);
            let mut bin = Mat::new_rows_cols_with_default(h, w, CV_8UC1, Scalar::all(0.0)).unwrap();
            for y in 0..h {
                for x in 0..w {
                    if rng.unit() < density {
                        *bin.at_2d_mut::<u8>(y, x).unwrap() = 255;
                    }
                }
            }
            for (x, y, s, t) in [(10, 10, 20, -1), (50, 20, 25, 3), (80, 40, 30, -1)] {
                imgproc::rectangle(
                    &mut bin,
                    opencv::core::Rect::new(x, y, s, s),
                    Scalar::all(255.0),
                    t,
                    imgproc::LINE_8,
                    0,
                )
                .unwrap();
            }
            let before = contours_of(&bin);
            let dark_before = opencv::core::count_non_zero(&bin).unwrap();
            drop_isolated(&mut bin).unwrap();
            let dark_after = opencv::core::count_non_zero(&bin).unwrap();
            assert_eq!(contours_of(&bin), before, "density {density}");
            // What went were single-point contours, and there were some.
            let mut all: Vector<Vector<Point>> = Vector::new();
            imgproc::find_contours(
                &bin,
                &mut all,
                imgproc::RETR_LIST,
                imgproc::CHAIN_APPROX_SIMPLE,
                Point::new(0, 0),
            )
            .unwrap();
            assert!(
                all.iter().all(|c| c.len() > 1 || {
                    // A one-point contour left must be a hole, not a pixel.
                    let p = c.get(0).unwrap();
                    *bin.at_2d::<u8>(p.y, p.x).unwrap() == 255
                        && [
                            (-1, -1),
                            (0, -1),
                            (1, -1),
                            (-1, 0),
                            (1, 0),
                            (-1, 1),
                            (0, 1),
                            (1, 1),
                        ]
                        .iter()
                        .any(|(dx, dy)| {
                            let (x, y) = (p.x + dx, p.y + dy);
                            x >= 0
                                && y >= 0
                                && x < w
                                && y < h
                                && *bin.at_2d::<u8>(y, x).unwrap() == 255
                        })
                }),
                "an isolated pixel survived at density {density}"
            );
            assert!(
                dark_after < dark_before,
                "density {density}: nothing dropped"
            );
        }
    }

    #[test]
    fn a_square_side_at_the_minimum_is_kept_though_its_contour_is_a_pixel_shorter() {
        use opencv::core::{Rect, Scalar, CV_8UC1};
        let params = DetectParams::default();
        // A dark 9 x 16 px block (pixel columns 20..29): its contour runs
        // through the centres of the edge pixels, 8 px apart.
        let side = params.min_code_side_px as i32;
        let mut img = Mat::new_rows_cols_with_default(64, 64, CV_8UC1, Scalar::all(200.0)).unwrap();
        imgproc::rectangle(
            &mut img,
            Rect::new(20, 20, side, 16),
            Scalar::all(40.0),
            -1,
            imgproc::LINE_8,
            0,
        )
        .unwrap();
        let quads = find_quads(&params, &img).unwrap();
        assert!(
            quads
                .iter()
                .any(|q| (min_side(&q.pts) - (side - 1) as f64).abs() < 0.5),
            "no quad of traced side {} in {quads:?}",
            side - 1
        );
    }

    /// A tag-like dark square 4 px from the right edge of a frame whose last
    /// column is a bright encoder line: the line is found, and with it
    /// replaced the square is a quad; thresholding the frame as it is merges
    /// the square with the dark band the line makes (the public tank video's
    /// case), so the test fails without the guard.
    #[test]
    fn a_bright_edge_column_does_not_hide_a_square_beside_it() {
        use opencv::core::{Rect, Scalar, CV_8UC1};
        let params = DetectParams::default();
        let mut img =
            Mat::new_rows_cols_with_default(120, 160, CV_8UC1, Scalar::all(60.0)).unwrap();
        // White quiet zone to the edge, the black square 7 px from it.
        let sq = Rect::new(112, 40, 40, 40);
        imgproc::rectangle(
            &mut img,
            Rect::new(104, 32, 56, 56),
            Scalar::all(90.0),
            -1,
            imgproc::LINE_8,
            0,
        )
        .unwrap();
        imgproc::rectangle(&mut img, sq, Scalar::all(30.0), -1, imgproc::LINE_8, 0).unwrap();
        imgproc::rectangle(
            &mut img,
            Rect::new(159, 0, 1, 120),
            Scalar::all(240.0),
            -1,
            imgproc::LINE_8,
            0,
        )
        .unwrap();
        assert_eq!(
            edge_line_artefacts(&img).unwrap(),
            [false, false, false, true]
        );
        // The square's outer edge (its inner one, around the part of the
        // square the threshold leaves light, is another, smaller quad).
        let found = |quads: &[Quad]| {
            quads.iter().any(|q| {
                let c = super::super::geom::centre(&q.pts);
                (c[0] - 131.5).abs() < 1.5 && (c[1] - 59.5).abs() < 1.5 && min_side(&q.pts) > 36.0
            })
        };
        assert!(
            found(&find_quads(&params, &img).unwrap()),
            "the square beside the line"
        );
        // Without the guard (the same search on the frame as it is).
        let mut unguarded = Found::default();
        let at = Place::whole(&img, 1.0);
        quads_of_level(&params, &img, at, None, None, &mut unguarded).unwrap();
        assert!(
            !found(&unguarded.quads),
            "the line's dark band merges with the square"
        );
    }

    /// A faint tag in dim water: black 41 and a 3 px white margin of 53 on
    /// water of 47, blurred (σ 1.2 px) and noisy (σ 1 grey level). Under
    /// the fixed offset of 3 the black square's region leaks through the
    /// margin into the water and no contour is its quad; with the offset
    /// following the local contrast it is found.
    #[test]
    fn a_faint_square_is_found_with_the_offset_that_follows_the_contrast() {
        use opencv::core::{Rect, Scalar, CV_64FC1};
        let mut f = Mat::new_rows_cols_with_default(120, 160, CV_64FC1, Scalar::all(47.0)).unwrap();
        for (r, v) in [
            (Rect::new(50, 30, 60, 60), 53.0),
            (Rect::new(53, 33, 54, 54), 41.0),
        ] {
            imgproc::rectangle(&mut f, r, Scalar::all(v), -1, imgproc::LINE_8, 0).unwrap();
        }
        let mut blurred = Mat::default();
        imgproc::gaussian_blur_def(&f, &mut blurred, Size::new(0, 0), 1.2).unwrap();
        // Gaussian noise from a fixed xorshift sequence (Box–Muller).
        let mut state: u64 = 0x9e37_79b9_7f4a_7c15;
        let mut uniform = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            ((state >> 11) as f64 + 0.5) / (1u64 << 53) as f64
        };
        let mut img =
            Mat::new_rows_cols_with_default(120, 160, opencv::core::CV_8UC1, Scalar::all(0.0))
                .unwrap();
        for y in 0..120 {
            for x in 0..160 {
                let n = (-2.0 * uniform().ln()).sqrt() * (std::f64::consts::TAU * uniform()).cos();
                let v = *blurred.at_2d::<f64>(y, x).unwrap() + n;
                *img.at_2d_mut::<u8>(y, x).unwrap() = v.round().clamp(0.0, 255.0) as u8;
            }
        }
        let found = |params: &DetectParams| {
            find_quads(params, &img).unwrap().iter().any(|q| {
                let c = super::super::geom::centre(&q.pts);
                (c[0] - 79.5).abs() < 2.0 && (c[1] - 59.5).abs() < 2.0 && min_side(&q.pts) > 50.0
            })
        };
        assert!(found(&DetectParams::default()), "relative offset");
        let fixed = DetectParams {
            contrast_offset: None,
            ..DetectParams::default()
        };
        assert!(!found(&fixed), "the fixed offset should lose it");
    }

    /// Where the contrast is high or absent, the relative offset is the
    /// fixed one: the binary image is OpenCV's `adaptiveThreshold`, bit for
    /// bit, on a frame of strong edges and flat regions.
    #[test]
    fn the_relative_offset_is_the_fixed_one_on_strong_edges_and_flats() {
        use opencv::core::{Rect, Scalar, CV_8UC1};
        let mut img =
            Mat::new_rows_cols_with_default(97, 131, CV_8UC1, Scalar::all(120.0)).unwrap();
        imgproc::rectangle(
            &mut img,
            Rect::new(20, 15, 40, 50),
            Scalar::all(20.0),
            -1,
            imgproc::LINE_8,
            0,
        )
        .unwrap();
        imgproc::rectangle(
            &mut img,
            Rect::new(80, 40, 30, 30),
            Scalar::all(230.0),
            -1,
            imgproc::LINE_8,
            0,
        )
        .unwrap();
        let params = DetectParams::default();
        let mut ours = Mat::default();
        binarize(&params, &img, 19, 0.0, &mut ours).unwrap();
        let mut theirs = Mat::default();
        imgproc::adaptive_threshold(
            &img,
            &mut theirs,
            255.0,
            imgproc::ADAPTIVE_THRESH_MEAN_C,
            imgproc::THRESH_BINARY_INV,
            19,
            params.threshold_offset,
        )
        .unwrap();
        assert_eq!(ours.data_bytes().unwrap(), theirs.data_bytes().unwrap());
    }

    /// A square whose quiet zone the frame cuts to one row (the tank
    /// video's tag 3 in frame 151: its black edge 2 px below the top) is a
    /// quad; one cut by the border is not, though its visible part is a
    /// convex quadrilateral.
    #[test]
    fn a_square_a_pixel_from_the_edge_is_kept_and_one_cut_by_it_is_not() {
        use opencv::core::{Rect, Scalar, CV_8UC1};
        let params = DetectParams::default();
        let frame = |top: i32| {
            let mut img =
                Mat::new_rows_cols_with_default(80, 100, CV_8UC1, Scalar::all(200.0)).unwrap();
            imgproc::rectangle(
                &mut img,
                Rect::new(30, top, 30, 30),
                Scalar::all(30.0),
                -1,
                imgproc::LINE_8,
                0,
            )
            .unwrap();
            img
        };
        let near_top = |quads: &[Quad]| {
            quads
                .iter()
                .any(|q| q.pts.iter().any(|c| c[1] < 2.0) && min_side(&q.pts) > 20.0)
        };
        // The quad search itself: a one-row white quiet zone above a flat
        // black square would pass for an edge-line artefact here.
        let search = |params: &DetectParams, img: &Mat| {
            let mut found = Found::default();
            quads_of_level(params, img, Place::whole(img, 1.0), None, None, &mut found).unwrap();
            found.quads
        };
        let whole = frame(1);
        assert!(near_top(&search(&params, &whole)), "whole square at 1 px");
        let old = DetectParams {
            border_margin_px: 2.0,
            ..DetectParams::default()
        };
        assert!(!near_top(&search(&old, &whole)), "a 2 px margin drops it");
        let cut = frame(-10);
        assert!(
            search(&params, &cut)
                .iter()
                .all(|q| min_side(&q.pts) < 15.0),
            "the cut square's visible part is not a quad"
        );
    }

    /// Content that reaches the edge (a dark object cut by the border, a
    /// gradient, noise) is image, not an artefact line.
    #[test]
    fn image_content_at_the_edge_is_not_an_artefact() {
        use opencv::core::{Rect, Scalar, CV_8UC1};
        let mut img = Mat::new_rows_cols_with_default(60, 80, CV_8UC1, Scalar::all(150.0)).unwrap();
        imgproc::rectangle(
            &mut img,
            Rect::new(60, 10, 20, 30),
            Scalar::all(20.0),
            -1,
            imgproc::LINE_8,
            0,
        )
        .unwrap();
        imgproc::rectangle(
            &mut img,
            Rect::new(0, 50, 80, 10),
            Scalar::all(40.0),
            -1,
            imgproc::LINE_8,
            0,
        )
        .unwrap();
        for y in 0..60 {
            for x in 0..80 {
                let v = img.at_2d_mut::<u8>(y, x).unwrap();
                *v = v.saturating_add(((x * 7 + y * 13) % 9) as u8);
            }
        }
        assert_eq!(edge_line_artefacts(&img).unwrap(), [false; 4]);
        assert!(without_edge_artefacts(&img).unwrap().is_none());
    }

    /// Each artefact line is replaced by its neighbour, rows before columns
    /// (a corner pixel takes the value its row's replacement left), and
    /// nothing else changes; a view into a larger image is read as itself.
    #[test]
    fn artefact_lines_are_replaced_by_their_neighbours() {
        use opencv::core::{Rect, Scalar, CV_8UC1};
        let (w, h) = (37, 23);
        let mut img = Mat::new_rows_cols_with_default(h, w, CV_8UC1, Scalar::all(0.0)).unwrap();
        for y in 0..h {
            for x in 0..w {
                *img.at_2d_mut::<u8>(y, x).unwrap() = (100 + (x * 5 + y * 3) % 11) as u8;
            }
        }
        // Lines far from the image beside them: all four edges.
        for x in 0..w {
            *img.at_2d_mut::<u8>(0, x).unwrap() = 250;
            *img.at_2d_mut::<u8>(h - 1, x).unwrap() = 5;
        }
        for y in 0..h {
            *img.at_2d_mut::<u8>(y, 0).unwrap() = 240;
            *img.at_2d_mut::<u8>(y, w - 1).unwrap() = 2;
        }
        assert_eq!(edge_line_artefacts(&img).unwrap(), [true; 4]);
        // The reference: pixel by pixel, in the order top, bottom, left, right.
        let mut want = img.try_clone().unwrap();
        for x in 0..w {
            *want.at_2d_mut::<u8>(0, x).unwrap() = *want.at_2d::<u8>(1, x).unwrap();
        }
        for x in 0..w {
            *want.at_2d_mut::<u8>(h - 1, x).unwrap() = *want.at_2d::<u8>(h - 2, x).unwrap();
        }
        for y in 0..h {
            *want.at_2d_mut::<u8>(y, 0).unwrap() = *want.at_2d::<u8>(y, 1).unwrap();
        }
        for y in 0..h {
            *want.at_2d_mut::<u8>(y, w - 1).unwrap() = *want.at_2d::<u8>(y, w - 2).unwrap();
        }
        // Through a view (not continuous), as a cropped frame would come.
        let mut host =
            Mat::new_rows_cols_with_default(h + 2, w + 9, CV_8UC1, Scalar::all(7.0)).unwrap();
        img.copy_to(&mut Mat::roi_mut(&mut host, Rect::new(4, 1, w, h)).unwrap())
            .unwrap();
        let view = Mat::roi(&host, Rect::new(4, 1, w, h)).unwrap();
        let same = |got: Mat| {
            for y in 0..h {
                for x in 0..w {
                    let (g, e) = (
                        got.at_2d::<u8>(y, x).unwrap(),
                        want.at_2d::<u8>(y, x).unwrap(),
                    );
                    assert_eq!(g, e, "({x}, {y})");
                }
            }
        };
        same(
            without_edge_artefacts(&img)
                .unwrap()
                .expect("four artefact lines"),
        );
        same(
            without_edge_artefacts(&view)
                .unwrap()
                .expect("four artefact lines"),
        );
    }

    #[test]
    fn same_quad_ignores_the_starting_corner() {
        let a = [[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]];
        let b = [a[2], a[3], a[0], a[1]];
        assert!(same_quad(&a, &b, 0.5));
        assert!(!same_quad(
            &a,
            &[[0.0, 0.0], [9.0, 0.0], [10.0, 10.0], [0.0, 10.0]],
            0.5
        ));
    }

    /// The summed-area table's rectangle sums equal the pixels' own, clipped
    /// to the level; a dark square in a bright band is darker than its surround.
    #[test]
    fn sum_table_sums_and_a_dark_squares_contrast() {
        let (w, h) = (37usize, 23usize);
        let data: Vec<u8> = (0..w * h)
            .map(|i| ((i * 7919 + i / w * 31) % 251) as u8)
            .collect();
        let img = shoal_proto::image::GrayImage {
            width: w as u32,
            height: h as u32,
            data: data.clone(),
        };
        let mat = crate::mat::gray_to_mat(&img).unwrap();
        let mut t = SumTable::new(GrayView::new(&mat).unwrap());
        for (x0, y0, x1, y1) in [
            (0, 0, 37, 23),
            (3, 4, 10, 9),
            (-5, -2, 4, 30),
            (30, 20, 50, 40),
            (5, 5, 5, 9),
        ] {
            let (mut s, mut n) = (0u64, 0u64);
            for y in y0.max(0)..y1.min(h as i32) {
                for x in x0.max(0)..x1.min(w as i32) {
                    s += u64::from(data[y as usize * w + x as usize]);
                    n += 1;
                }
            }
            assert_eq!(
                t.sum(x0, y0, x1, y1),
                (s as f64, n as f64),
                "{x0} {y0} {x1} {y1}"
            );
        }
        let mut flat = vec![200u8; w * h];
        for y in 8..14 {
            for x in 15..21 {
                flat[y * w + x] = 120;
            }
        }
        let img = shoal_proto::image::GrayImage {
            width: w as u32,
            height: h as u32,
            data: flat,
        };
        let mat = crate::mat::gray_to_mat(&img).unwrap();
        let mut t = SumTable::new(GrayView::new(&mat).unwrap());
        assert_eq!(t.contrast([15, 8, 6, 6]), 80.0);
        assert_eq!(t.contrast([2, 2, 6, 6]), 0.0);
    }

    /// The outer contour of the dark polygons `polys` (drawn filled on a
    /// light `w` x `h` image) that contains `inside`.
    fn outline_around(w: i32, h: i32, polys: &[Vec<(i32, i32)>], inside: (i32, i32)) -> Vec<Point> {
        use opencv::core::{Scalar, CV_8UC1};
        let mut img = Mat::new_rows_cols_with_default(h, w, CV_8UC1, Scalar::all(0.0)).unwrap();
        let polys: Vector<Vector<Point>> = polys
            .iter()
            .map(|p| p.iter().map(|&(x, y)| Point::new(x, y)).collect())
            .collect();
        imgproc::fill_poly(
            &mut img,
            &polys,
            Scalar::all(255.0),
            imgproc::LINE_8,
            0,
            Point::default(),
        )
        .unwrap();
        let mut contours: Vector<Vector<Point>> = Vector::new();
        imgproc::find_contours(
            &img,
            &mut contours,
            imgproc::RETR_EXTERNAL,
            imgproc::CHAIN_APPROX_SIMPLE,
            Point::new(0, 0),
        )
        .unwrap();
        let p = opencv::core::Point2f::new(inside.0 as f32, inside.1 as f32);
        contours
            .iter()
            .find(|c| imgproc::point_polygon_test(c, p, false).unwrap() > 0.0)
            .expect("a region around the point")
            .to_vec()
    }

    fn near(a: Px, b: Px, tol: f64) -> bool {
        super::super::geom::dist(a, b) < tol
    }

    #[test]
    fn the_straight_runs_of_a_turned_squares_outline_are_its_sides() {
        let sq = [(60, 20), (115, 45), (90, 100), (35, 75)];
        let outline = outline_around(160, 130, &[sq.to_vec()], (75, 60));
        let runs = straight_runs(&outline, 20.0);
        assert_eq!(runs.len(), 4, "{runs:?}");
        // Each side's run spans it within a pixel or two at either end.
        let corners: Vec<Px> = sq
            .iter()
            .map(|&(x, y)| [f64::from(x), f64::from(y)])
            .collect();
        for (a, b) in &runs {
            assert!(corners.iter().any(|c| near(*a, *c, 2.5)), "run {a:?}–{b:?}");
            assert!(corners.iter().any(|c| near(*b, *c, 2.5)), "run {a:?}–{b:?}");
        }
    }

    #[test]
    fn the_runs_looked_up_near_each_other_are_every_pair_that_links() {
        // Runs of every length from a few pixels to hundreds, some starting
        // on one point, many linking; the grid's answer against asking
        // every pair.
        let mut rng = shoal_proto::splitmix::SplitMix64::new(17);
        let mut linked_pairs = 0;
        for trial in 0..48 {
            // Few runs (asked pair by pair) and many (through the grid).
            let m = if trial < 8 {
                4 + 2 * trial
            } else {
                20 + (trial - 8) * 10
            };
            let spread = if trial % 2 == 0 { 60.0 } else { 600.0 };
            let runs: Vec<Run> = (0..m)
                .map(|k| {
                    let a = if k % 7 == 3 {
                        [10.0, 10.0]
                    } else {
                        [rng.unit() * spread, rng.unit() * spread]
                    };
                    let len = 3.0 + rng.unit().powi(3) * 300.0;
                    let ang = rng.unit() * std::f64::consts::TAU;
                    Run::new(a, [a[0] + len * ang.cos(), a[1] + len * ang.sin()])
                })
                .collect();
            let every: Vec<Vec<usize>> = (0..m)
                .map(|i| (0..m).filter(|&j| j != i && follows(&runs, i, j)).collect())
                .collect();
            let near = linked_runs(&runs, JOINED_REACH, |i, j| follows(&runs, i, j));
            assert_eq!(near, every, "trial {trial}");
            linked_pairs += every.iter().map(Vec::len).sum::<usize>();
        }
        // Premise: the runs do link, many times.
        assert!(linked_pairs > 1000, "{linked_pairs}");
    }

    #[test]
    fn the_quad_search_finds_each_cycle_once_and_stops_where_everything_links() {
        // Two quads' runs, 0-1-2-3 and 4-5-6-7, and a run (8) that links on
        // to 0 but closes nothing.
        let mut next = vec![
            vec![1],
            vec![2],
            vec![3],
            vec![0],
            vec![5],
            vec![6],
            vec![7],
        ];
        next.push(vec![4]);
        next.push(vec![0]);
        let mut seen = Vec::new();
        four_cycles(&next, |ks| seen.push(ks));
        assert_eq!(seen, vec![[0, 1, 2, 3], [4, 5, 6, 7]]);
        // Every run linked to every other: ~C(400, 4) cycles and more paths
        // without the bounds.
        let m = 400;
        let every: Vec<Vec<usize>> = (0..m)
            .map(|i| (0..m).filter(|&j| j != i).collect())
            .collect();
        let mut visits = 0;
        let paths = four_cycles(&every, |_| visits += 1);
        assert_eq!(visits, JOINED_MAX_TRIED);
        assert!(paths <= JOINED_MAX_PATHS, "{paths}");
        // Cycles close rarely where the links go only forward: the paths bound it.
        let forward: Vec<Vec<usize>> = (0..m).map(|i| (i + 1..m).collect()).collect();
        let mut visits = 0;
        let paths = four_cycles(&forward, |_| visits += 1);
        assert_eq!(visits, 0);
        assert_eq!(paths, JOINED_MAX_PATHS + 1);
    }

    #[test]
    fn a_run_may_follow_another_only_from_nearby() {
        // Every linked pair starts within JOINED_REACH·(l_i + l_j): the
        // bound `linked_runs` looks runs up by, at its limits.
        let mut rng = shoal_proto::splitmix::SplitMix64::new(23);
        let mut worst: f64 = 0.0;
        let mut linked = 0;
        for _ in 0..200_000 {
            let mut run = || {
                let a = [rng.unit() * 200.0, rng.unit() * 200.0];
                let len = 2.0 + rng.unit() * 100.0;
                let ang = rng.unit() * std::f64::consts::TAU;
                Run::new(a, [a[0] + len * ang.cos(), a[1] + len * ang.sin()])
            };
            let runs = [run(), run()];
            if follows(&runs, 0, 1) {
                linked += 1;
                let d = super::super::geom::dist(runs[0].a, runs[1].a);
                worst = worst.max(d / (JOINED_REACH * (runs[0].len + runs[1].len)));
            }
        }
        assert!(linked > 1000, "{linked}");
        assert!(worst <= 1.0, "{worst}");
        // …and the bound is not loose by much (links reach ~half of it).
        assert!(worst > 0.4, "{worst}");
    }

    #[test]
    fn a_square_joined_to_a_bar_is_found_on_its_outline_and_a_side_along_a_cut_is_none() {
        let sq = vec![(60, 20), (115, 45), (90, 100), (35, 75)];
        let corners: Vec<Px> = sq
            .iter()
            .map(|&(x, y)| [f64::from(x), f64::from(y)])
            .collect();
        let bounds = Rect::new(0, 0, 160, 130);
        // A bar from near the bottom corner down to the frame's last row.
        let bar = vec![(80, 90), (90, 94), (95, 129), (85, 129)];
        let outline = outline_around(160, 130, &[sq.clone(), bar], (75, 60));
        assert!(
            outline.iter().any(|p| p.y == 129),
            "the premise: the region is cut"
        );
        let quads = quads_of_long_edges(&outline, 9.0, bounds);
        assert_eq!(quads.len(), 1, "{quads:?}");
        for c in &corners {
            assert!(
                quads[0].iter().any(|q| near(*q, *c, 1.5)),
                "{c:?} not in {quads:?}"
            );
        }
        // A square whose fourth side lies along the frame's top row has
        // three sides: its outline's run there is the cut, not a side.
        let cut = vec![(30, 0), (90, 0), (90, 50), (30, 50)];
        let outline = outline_around(160, 130, &[cut], (60, 20));
        assert!(quads_of_long_edges(&outline, 9.0, bounds).is_empty());
        // The same square a row lower is found.
        let whole = vec![(30, 1), (90, 1), (90, 50), (30, 50)];
        let outline = outline_around(160, 130, &[whole], (60, 20));
        assert_eq!(quads_of_long_edges(&outline, 9.0, bounds).len(), 1);
    }

    /// A light frame with dark rectangles (x, y, width, height) and light
    /// ones drawn over them, in order.
    fn rects_frame(w: i32, h: i32, dark: &[[i32; 4]], light: &[[i32; 4]]) -> Mat {
        use opencv::core::{Scalar, CV_8UC1};
        let mut img = Mat::new_rows_cols_with_default(h, w, CV_8UC1, Scalar::all(190.0)).unwrap();
        for (rects, v) in [(dark, 50.0), (light, 190.0)] {
            for &[x, y, rw, rh] in rects {
                let r = Rect::new(x, y, rw, rh);
                imgproc::rectangle(&mut img, r, Scalar::all(v), -1, imgproc::LINE_8, 0).unwrap();
            }
        }
        img
    }

    #[test]
    fn a_dark_square_is_dark_inside_and_a_light_cell_of_a_grid_is_not() {
        // A dark square, and a light cell between 2 px lines of a grid.
        let img = rects_frame(
            200,
            100,
            &[
                [20, 20, 50, 50],
                [100, 18, 2, 56],
                [154, 18, 2, 56],
                [100, 18, 56, 2],
                [100, 72, 56, 2],
            ],
            &[],
        );
        let view = GrayView::new(&img).unwrap();
        let square = [[20.0, 20.0], [69.0, 20.0], [69.0, 69.0], [20.0, 69.0]];
        let cell = [[101.0, 19.0], [154.0, 19.0], [154.0, 72.0], [101.0, 72.0]];
        assert!(dark_inside(&view, &square, 6.0));
        assert!(!dark_inside(&view, &cell, 6.0));
        // The square is 140 levels darker: not at a contrast above that.
        assert!(!dark_inside(&view, &square, 141.0));
    }

    #[test]
    fn a_window_keeps_no_piece_of_what_its_edge_cuts() {
        // A dark square read nothing at half size; its full-resolution
        // window cuts into a dark neighbour to its left through a light bar
        // (a marker's white module), whose edge and the neighbour's three
        // other sides make a quad: on a 4x4 code set it read as a marker by
        // chance (the ChArUco board of `photonvision-charuco-lifecam`).
        let img = rects_frame(
            700,
            700,
            &[[510, 486, 72, 68], [445, 494, 56, 53]],
            &[[455, 505, 19, 26]],
        );
        let view = GrayView::new(&img).unwrap();
        let params = DetectParams::default();
        let square = Quad {
            pts: [
                [510.0, 486.0],
                [581.0, 486.0],
                [581.0, 553.0],
                [510.0, 553.0],
            ],
            inset_px: 1.0,
            exact_only: false,
        };
        let piece = |q: &Quad| q.exact_only && q.pts.iter().all(|c| c[0] > 465.0 && c[0] < 505.0);
        // The premise: the window (as `full_res_quads` takes it) gives the piece.
        let pad = 0.5 * mean_side(&square.pts) + 4.0;
        let (x0, y0) = ((510.0 - pad).floor() as i32, (486.0 - pad).floor() as i32);
        let (x1, y1) = ((581.0 + pad).ceil() as i32, (553.0 + pad).ceil() as i32);
        let roi = Mat::roi(&img, Rect::new(x0, y0, x1 - x0, y1 - y0))
            .unwrap()
            .try_clone()
            .unwrap();
        let mut found = Found::default();
        let at = Place {
            scale: 1.0,
            offset: [f64::from(x0), f64::from(y0)],
            frame_outline: 2800.0,
        };
        quads_of_level(&params, &roi, at, Some(0.5), None, &mut found).unwrap();
        assert!(found.quads.iter().any(piece), "{:?}", found.quads);
        let extra = full_res_quads(&params, &view, &[square], &[square]).unwrap();
        assert!(!extra.iter().any(piece), "{extra:?}");
    }
}
