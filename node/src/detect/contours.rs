//! Every contour of a binary image, as `cv::findContours` gives them with
//! `RETR_LIST` and `CHAIN_APPROX_SIMPLE`: the same contours, in the same
//! order, each from the same first point, to the last point (test
//! `the_contours_are_opencvs_to_the_point`).
//!
//! The quad search ([`super::quads`]) traces a thresholded frame whose
//! low-contrast regions give hundreds of contours of noise, most shorter
//! than any marker (~860 of ~990 on a 640x480 tank frame). Through OpenCV
//! each search copied the image into a bordered one, thresholded that
//! copy to 0/1, traced into a linked sequence store and copied every
//! contour out into its own vector: 0.86 ms of a 2.5 ms tank frame. Here
//! the image is copied once (to 0/1, with its zero border), runs of equal
//! pixels are skipped eight at a time, and the contours are written into
//! one buffer.
//!
//! The method is Suzuki and Abe's border following (*Topological
//! structural analysis of digitized binary images by border following*,
//! CVGIP 1985), as OpenCV runs it without a hierarchy: a raster scan that
//! starts an outer border at a 0→1 step and a hole border at a 1→0 step
//! whose left pixel no border has yet closed on its right, follows each
//! border clockwise (outer) or counter-clockwise (hole) through the 8
//! neighbours, and marks the pixels it passes (`VISITED`, or `RIGHT` where
//! the border leaves the region to its right, which ends a run for the
//! scan). A border's chain keeps only the points where its direction
//! turns (the simple approximation).

use crate::mat::GrayView;
use opencv::core::{Point, Rect};

/// The marks of a traced pixel in the 0/1 scan image.
const VISITED: u8 = 2;
/// A traced pixel whose right neighbour is outside the region (OpenCV's
/// `nbd | 0x80`): no hole border starts right of it.
const RIGHT: u8 = 0x82;

/// The eight neighbour steps, counter-clockwise from east (y down): the
/// chain code's directions.
const STEPS: [(i32, i32); 8] = [
    (1, 0),
    (1, -1),
    (0, -1),
    (-1, -1),
    (-1, 0),
    (-1, 1),
    (0, 1),
    (1, 1),
];

/// The contours of one binary image, in `cv::findContours`' order (the
/// last found first), their points in one buffer.
#[derive(Debug, Default, Clone)]
pub struct Contours {
    points: Vec<Point>,
    /// Each contour's end in `points`, in the order they were found.
    ends: Vec<usize>,
    /// The bordered 0/1 image, kept between traces.
    scan: Vec<u8>,
}

impl Contours {
    pub fn new() -> Self {
        Self::default()
    }

    /// How many contours the last trace found.
    pub fn len(&self) -> usize {
        self.ends.len()
    }

    pub fn is_empty(&self) -> bool {
        self.ends.is_empty()
    }

    /// The contours, as `cv::findContours` lists them.
    pub fn iter(&self) -> impl Iterator<Item = &[Point]> + '_ {
        (0..self.ends.len()).rev().map(move |k| {
            let start = if k == 0 { 0 } else { self.ends[k - 1] };
            &self.points[start..self.ends[k]]
        })
    }

    /// Trace every contour of the binary image `bin` (non-zero =
    /// foreground), or of its part `window` only
    /// (as `cv::findContours` on that region of interest: what the window's
    /// edge cuts is closed along it). Points are in the whole image's pixels.
    /// A window outside the image is clipped to it.
    pub fn trace(&mut self, bin: &GrayView<'_>, window: Option<Rect>) {
        self.points.clear();
        self.ends.clear();
        let (iw, ih) = (bin.width as i32, bin.height as i32);
        let r = match window {
            None => Rect::new(0, 0, iw, ih),
            Some(w) => {
                let (x0, y0) = (w.x.max(0), w.y.max(0));
                let (x1, y1) = ((w.x + w.width).min(iw), (w.y + w.height).min(ih));
                Rect::new(x0, y0, x1 - x0, y1 - y0)
            }
        };
        if r.width <= 0 || r.height <= 0 {
            return;
        }
        let (w, h) = (r.width as usize, r.height as usize);
        // The window's pixels as 0/1 inside a border of zeros.
        let step = w + 2;
        self.scan.clear();
        self.scan.resize(step * (h + 2), 0);
        let x0 = r.x as usize;
        for y in 0..h {
            let row = bin.row(r.y as usize + y);
            let dst = &mut self.scan[(y + 1) * step + 1..(y + 1) * step + 1 + w];
            for (d, &s) in dst.iter_mut().zip(&row[x0..x0 + w]) {
                *d = s.min(1);
            }
        }
        let origin = (r.x - 1, r.y - 1);
        let mut border = Border {
            img: &mut self.scan,
            deltas: deltas(step),
        };
        for y in 1..=h {
            let row = y * step;
            let mut x = 1;
            loop {
                x = border.next_start(row, x, w + 1);
                if x > w {
                    break;
                }
                // The pixel left of a border's start is what the scan has
                // passed, as it is now (earlier borders marked it).
                let is_hole = border.img[row + x] == 0;
                let sx = x - usize::from(is_hole);
                let start = Point::new(sx as i32 + origin.0, y as i32 + origin.1);
                border.follow(row + sx, start, is_hole, &mut self.points);
                self.ends.push(self.points.len());
                x += 1;
            }
        }
    }
}

/// The index steps of [`STEPS`] in a scan image `step` bytes wide, twice
/// over (a search around a pixel wraps past east without a modulo).
fn deltas(step: usize) -> [isize; 16] {
    let step = step as isize;
    let mut d = [0isize; 16];
    for (k, &(dx, dy)) in STEPS.iter().enumerate() {
        d[k] = dx as isize + dy as isize * step;
        d[k + 8] = d[k];
    }
    d
}

/// The scan image and its neighbour steps, while borders are followed.
struct Border<'a> {
    img: &'a mut [u8],
    deltas: [isize; 16],
}

impl Border<'_> {
    /// The first `x` in `from..end` (`from` ≥ 1) of the row starting at
    /// `row` where a border starts (`end` when none does): an outer border
    /// at a 0 → 1 step, a hole's at a step from an unmarked or `VISITED`
    /// pixel to 0 (a `RIGHT` pixel's border has passed on its right). The
    /// pixels are 0, 1, `VISITED` or `RIGHT`, so eight pairs are tested at
    /// a time in a `u64`: a byte is non-zero where `nz` has its high bit,
    /// is 1 where its low bit is set, and is 1 or `VISITED` where it is
    /// non-zero with its high bit clear.
    fn next_start(&self, row: usize, from: usize, end: usize) -> usize {
        const LOW7: u64 = 0x7f7f_7f7f_7f7f_7f7f;
        const HIGH: u64 = 0x8080_8080_8080_8080;
        let nz = |v: u64| ((v & LOW7) + LOW7) | v;
        let line = &self.img[row..row + end];
        let word = |x: usize| u64::from_le_bytes(line[x..x + 8].try_into().expect("eight bytes"));
        let mut x = from;
        while x + 8 <= end {
            // Byte k of `left` is pixel x + k − 1, of `this` pixel x + k.
            let (left, this) = (word(x - 1), word(x));
            let (nz_left, nz_this) = (nz(left), nz(this));
            let outer = !nz_left & (this << 7);
            let hole = !nz_this & nz_left & !left;
            let starts = (outer | hole) & HIGH;
            if starts != 0 {
                return x + (starts.trailing_zeros() / 8) as usize;
            }
            x += 8;
        }
        while x < end {
            let (left, this) = (line[x - 1], line[x]);
            if (left == 0 && this == 1) || (this == 0 && (left == 1 || left == VISITED)) {
                return x;
            }
            x += 1;
        }
        x
    }

    fn at(&self, i: usize, d: usize) -> usize {
        i.wrapping_add_signed(self.deltas[d])
    }

    /// Follow the border through the pixel at index `i0` (image point
    /// `pt`), an outer border's or a hole's, marking its pixels and
    /// appending its turning points to `out`.
    fn follow(&mut self, i0: usize, mut pt: Point, is_hole: bool, out: &mut Vec<Point>) {
        // The first neighbour clockwise from where the scan came from.
        let s_first = if is_hole { 0 } else { 4 };
        let mut s = s_first;
        let i1 = loop {
            s = (s + 7) & 7;
            let i1 = self.at(i0, s);
            if self.img[i1] != 0 || s == s_first {
                break i1;
            }
        };
        if s == s_first {
            // A region of one pixel.
            self.img[i0] = RIGHT;
            out.push(pt);
            return;
        }
        let mut i3 = i0;
        let mut prev_s = s ^ 4;
        loop {
            // The next border pixel counter-clockwise from the one before.
            let s_end = s;
            let mut i4;
            loop {
                s += 1;
                i4 = self.at(i3, s);
                if self.img[i4] != 0 || s == 15 {
                    break;
                }
            }
            s &= 7;
            if s.wrapping_sub(1) < s_end {
                self.img[i3] = RIGHT;
            } else if self.img[i3] == 1 {
                self.img[i3] = VISITED;
            }
            if s != prev_s {
                out.push(pt);
                prev_s = s;
            }
            pt.x += STEPS[s].0;
            pt.y += STEPS[s].1;
            if i4 == i0 && i3 == i1 {
                break;
            }
            i3 = i4;
            s = (s + 4) & 7;
        }
    }
}

/// `m` smoothed by a Gaussian of `sigma` px: thresholded, noise smoothed so
/// gives regions with holes within holes (the tests' outlines).
#[cfg(test)]
pub(crate) fn blurred(m: &opencv::core::Mat, sigma: f64) -> opencv::core::Mat {
    let mut out = opencv::core::Mat::default();
    opencv::imgproc::gaussian_blur(
        m,
        &mut out,
        opencv::core::Size::new(0, 0),
        sigma,
        sigma,
        opencv::core::BORDER_REFLECT,
    )
    .expect("a Gaussian blur of a grey image");
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use opencv::core::{Mat, Scalar, Vector, CV_8UC1};
    use opencv::imgproc;
    use opencv::prelude::*;
    use rand::{Rng, SeedableRng};

    /// OpenCV's contours of `bin` (or of its `window`), as point lists.
    fn opencvs(bin: &Mat, window: Option<Rect>) -> Vec<Vec<(i32, i32)>> {
        let mut contours: Vector<Vector<Point>> = Vector::new();
        let (mode, chain) = (imgproc::RETR_LIST, imgproc::CHAIN_APPROX_SIMPLE);
        match window {
            None => {
                imgproc::find_contours(bin, &mut contours, mode, chain, Point::new(0, 0)).unwrap()
            }
            Some(r) => {
                let roi = Mat::roi(bin, r).unwrap();
                imgproc::find_contours(&roi, &mut contours, mode, chain, Point::new(r.x, r.y))
                    .unwrap()
            }
        }
        contours
            .iter()
            .map(|c| c.iter().map(|p| (p.x, p.y)).collect())
            .collect()
    }

    fn ours(bin: &Mat, window: Option<Rect>, traced: &mut Contours) -> Vec<Vec<(i32, i32)>> {
        traced.trace(&GrayView::new(bin).unwrap(), window);
        traced
            .iter()
            .map(|c| c.iter().map(|p| (p.x, p.y)).collect())
            .collect()
    }

    /// A binary image of noise (foreground with probability `density`,
    /// values 1–255), with filled and hollow rectangles drawn over it.
    fn random_image(rng: &mut rand::rngs::StdRng, w: i32, h: i32, density: f64) -> Mat {
        let mut m = Mat::new_rows_cols_with_default(h, w, CV_8UC1, Scalar::all(0.0)).unwrap();
        for y in 0..h {
            for x in 0..w {
                if rng.gen_bool(density) {
                    *m.at_2d_mut::<u8>(y, x).unwrap() = rng.gen_range(1..=255);
                }
            }
        }
        for _ in 0..rng.gen_range(0..6) {
            let (x, y) = (rng.gen_range(-3..w), rng.gen_range(-3..h));
            let (rw, rh) = (rng.gen_range(1..w.max(2)), rng.gen_range(1..h.max(2)));
            let value = if rng.gen_bool(0.7) { 255.0 } else { 0.0 };
            let thickness = if rng.gen_bool(0.5) {
                -1
            } else {
                rng.gen_range(1..4)
            };
            imgproc::rectangle(
                &mut m,
                Rect::new(x, y, rw, rh),
                Scalar::all(value),
                thickness,
                imgproc::LINE_8,
                0,
            )
            .unwrap();
        }
        m
    }

    #[test]
    fn the_contours_are_opencvs_to_the_point() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(7);
        let mut traced = Contours::new();
        let mut compared = 0;
        for case in 0..400 {
            let (w, h) = (rng.gen_range(1..70), rng.gen_range(1..50));
            let density = [0.05, 0.3, 0.5, 0.7, 0.95][case % 5];
            let bin = random_image(&mut rng, w, h, density);
            let want = opencvs(&bin, None);
            assert_eq!(ours(&bin, None, &mut traced), want, "case {case}, {w}x{h}");
            assert_eq!(traced.len(), want.len());
            compared += want.len();
            // A window of it, as the quad search traces one.
            let (x, y) = (rng.gen_range(0..w), rng.gen_range(0..h));
            let r = Rect::new(x, y, rng.gen_range(1..=w - x), rng.gen_range(1..=h - y));
            let want = opencvs(&bin, Some(r));
            assert_eq!(
                ours(&bin, Some(r), &mut traced),
                want,
                "case {case}, window {r:?}"
            );
            compared += want.len();
        }
        // Blobs with holes within holes: smoothed noise, thresholded.
        for case in 0..12 {
            let noise = random_image(&mut rng, 240, 180, 0.5);
            let smooth = blurred(&noise, [1.0, 2.0, 4.0][case % 3]);
            let mut bin = Mat::default();
            let level = rng.gen_range(100.0..160.0);
            imgproc::threshold(&smooth, &mut bin, level, 255.0, imgproc::THRESH_BINARY).unwrap();
            let want = opencvs(&bin, None);
            assert_eq!(ours(&bin, None, &mut traced), want, "blobs {case}");
            compared += want.len();
        }
        // The cases hold contours of every kind, not a few empty images.
        assert!(compared > 15_000, "{compared} contours compared");
    }

    #[test]
    fn a_filled_square_is_its_four_corners_and_a_ring_adds_its_hole() {
        let mut m = Mat::new_rows_cols_with_default(20, 20, CV_8UC1, Scalar::all(0.0)).unwrap();
        let square = Rect::new(3, 4, 10, 8);
        imgproc::rectangle(&mut m, square, Scalar::all(255.0), -1, imgproc::LINE_8, 0).unwrap();
        let mut traced = Contours::new();
        let got = ours(&m, None, &mut traced);
        assert_eq!(got, vec![vec![(3, 4), (3, 11), (12, 11), (12, 4)]]);
        // Hollowed: the hole's border runs through the ring's inner pixels.
        let hole = Rect::new(5, 6, 6, 4);
        imgproc::rectangle(&mut m, hole, Scalar::all(0.0), -1, imgproc::LINE_8, 0).unwrap();
        let got = ours(&m, None, &mut traced);
        assert_eq!(got.len(), 2);
        assert_eq!(got[1], vec![(3, 4), (3, 11), (12, 11), (12, 4)]);
        assert!(got[0].len() >= 4, "{:?}", got[0]);
        assert!(got[0]
            .iter()
            .all(|&(x, y)| (4..=11).contains(&x) && (5..=10).contains(&y)));
        assert_eq!(got, opencvs(&m, None));
        // A window outside the image traces nothing.
        assert!(ours(&m, Some(Rect::new(30, 30, 5, 5)), &mut traced).is_empty());
        assert!(traced.is_empty());
    }
}
