//! Calibration boards: their geometry, their printable pages, and finding
//! their points in an image.
//!
//! Two kinds:
//! - **ChArUco** on one of OpenCV's ArUco dictionaries: a chessboard whose
//!   white squares hold markers, laid out exactly as OpenCV 4.6's
//!   `cv::aruco::CharucoBoard` (the top-left square black, markers numbered
//!   row by row from the top). Its points are the inner chessboard corners,
//!   found by `cv::aruco::detectMarkers` and
//!   `cv::aruco::interpolateCornersCharuco`.
//! - **A grid of shoal markers**: `cols x rows` enhanced markers, numbered
//!   row by row from `first_id`, each giving its 12 corners (three squares)
//!   through shoal's own detector — three times the points of a ChArUco
//!   marker, and the very corners the node measures poses with.
//!
//! Board frame: origin at the board's top-left corner, x to the right, y
//! down, z into the board (metres).

use crate::detect::{CornerFit, DetectParams, MarkerDetector, ShoalDetector};
use opencv::core::{Mat, Point2f, Ptr, Vector};
use opencv::prelude::*;
use opencv::{aruco, imgcodecs};
use shoal_proto::marker::{CodeSet, MarkerError};
use std::fmt::Write as _;

/// A calibration board.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Board {
    /// `cols x rows` squares of `square_m`, markers of `marker_m` from `codes`
    /// (an ArUco dictionary) in the white squares.
    Charuco {
        cols: u32,
        rows: u32,
        square_m: f64,
        marker_m: f64,
        codes: CodeSet,
    },
    /// `cols x rows` enhanced markers of footprint `side_m`, `gap_m` apart
    /// (edge to edge), IDs from `first_id` row by row.
    ShoalGrid {
        cols: u32,
        rows: u32,
        side_m: f64,
        gap_m: f64,
        first_id: u32,
    },
}

/// Errors of boards.
#[derive(Debug, thiserror::Error)]
pub enum BoardError {
    #[error("board: {0}")]
    Invalid(String),
    #[error(transparent)]
    Marker(#[from] MarkerError),
    #[error("OpenCV: {0}")]
    OpenCv(#[from] opencv::Error),
}

/// One board point seen in an image: its ID on the board (ChArUco: the
/// corner's index; shoal grid: `12 · marker index + corner`), where it is on
/// the board and where it is in the image.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BoardPoint {
    pub id: u32,
    pub board: [f64; 3],
    pub image: [f64; 2],
}

/// White margin around a printed board, for its label (mm).
const MARGIN_MM: f64 = 12.0;

impl Board {
    /// Why the board cannot be made or found, or `Ok`.
    pub fn validate(&self) -> Result<(), BoardError> {
        let bad = |m: String| Err(BoardError::Invalid(m));
        match *self {
            Board::Charuco {
                cols,
                rows,
                square_m,
                marker_m,
                codes,
            } => {
                if !(2..=64).contains(&cols) || !(2..=64).contains(&rows) {
                    return bad(format!(
                        "a ChArUco board has 2 to 64 squares a side, got {cols}x{rows}"
                    ));
                }
                if !(square_m.is_finite()
                    && square_m > 0.0
                    && marker_m.is_finite()
                    && marker_m > 0.0)
                {
                    return bad(format!(
                        "square {square_m} m and marker {marker_m} m must be positive"
                    ));
                }
                if marker_m >= square_m {
                    return bad(format!(
                        "the marker ({:.1} mm) must be smaller than its square ({:.1} mm)",
                        marker_m * 1e3,
                        square_m * 1e3
                    ));
                }
                if crate::baseline::opencv_dictionary(codes).is_none()
                    || matches!(
                        codes,
                        CodeSet::Shoal | CodeSet::AprilTag16h5 | CodeSet::AprilTag36h11
                    )
                {
                    return bad(format!("a ChArUco board needs an ArUco dictionary (aruco4x4_50 … aruco6x6_1000), got {codes}"));
                }
                let markers = (cols * rows) / 2;
                if markers as usize > codes.len() {
                    return bad(format!(
                        "{cols}x{rows} squares hold {markers} markers, {codes} has {}",
                        codes.len()
                    ));
                }
            }
            Board::ShoalGrid {
                cols,
                rows,
                side_m,
                gap_m,
                first_id,
            } => {
                if !(1..=16).contains(&cols) || !(1..=16).contains(&rows) || cols * rows < 2 {
                    return bad(format!(
                        "a shoal grid has 1 to 16 markers a side and at least 2, got {cols}x{rows}"
                    ));
                }
                if !(side_m.is_finite() && side_m > 0.0 && gap_m.is_finite()) {
                    return bad(format!(
                        "side {side_m} m must be positive, gap {gap_m} m finite"
                    ));
                }
                // Each marker needs its one-module white quiet zone.
                let module = side_m / CodeSet::Shoal.modules() as f64;
                if gap_m < 2.0 * module - 1e-12 {
                    return bad(format!(
                        "the gap ({:.1} mm) must hold two quiet zones of one module ({:.1} mm each)",
                        gap_m * 1e3,
                        module * 1e3
                    ));
                }
                let last = u64::from(first_id) + u64::from(cols * rows) - 1;
                if last >= CodeSet::Shoal.len() as u64 {
                    return bad(format!(
                        "IDs {first_id}..={last} do not all exist: the shoal code set has {}",
                        CodeSet::Shoal.len()
                    ));
                }
            }
        }
        Ok(())
    }

    /// Width and height of the board's pattern (m).
    pub fn size_m(&self) -> (f64, f64) {
        match *self {
            Board::Charuco {
                cols,
                rows,
                square_m,
                ..
            } => (f64::from(cols) * square_m, f64::from(rows) * square_m),
            Board::ShoalGrid {
                cols,
                rows,
                side_m,
                gap_m,
                ..
            } => (
                f64::from(cols) * side_m + f64::from(cols - 1) * gap_m,
                f64::from(rows) * side_m + f64::from(rows - 1) * gap_m,
            ),
        }
    }

    /// One line saying what the board is.
    pub fn describe(&self) -> String {
        match *self {
            Board::Charuco {
                cols,
                rows,
                square_m,
                marker_m,
                codes,
            } => format!(
                "ChArUco {cols}x{rows}, squares {:.2} mm, markers {:.2} mm, {codes}",
                square_m * 1e3,
                marker_m * 1e3
            ),
            Board::ShoalGrid {
                cols,
                rows,
                side_m,
                gap_m,
                first_id,
            } => format!(
                "shoal grid {cols}x{rows}, markers {:.2} mm, gaps {:.2} mm, IDs {first_id}..={}",
                side_m * 1e3,
                gap_m * 1e3,
                first_id + cols * rows - 1
            ),
        }
    }

    /// Centres (board frame) and IDs of the shoal grid's markers; empty for ChArUco.
    pub fn shoal_markers(&self) -> Vec<(u32, [f64; 2])> {
        let Board::ShoalGrid {
            cols,
            rows,
            side_m,
            gap_m,
            first_id,
        } = *self
        else {
            return Vec::new();
        };
        let mut out = Vec::new();
        for r in 0..rows {
            for c in 0..cols {
                out.push((
                    first_id + r * cols + c,
                    [
                        f64::from(c) * (side_m + gap_m) + side_m / 2.0,
                        f64::from(r) * (side_m + gap_m) + side_m / 2.0,
                    ],
                ));
            }
        }
        out
    }

    /// The black rectangles `[x, y, w, h]` (m, board frame) of the pattern
    /// on white: what is printed, and what the tests compare with OpenCV's
    /// own drawing.
    pub fn black_rects(&self) -> Result<Vec<[f64; 4]>, BoardError> {
        self.validate()?;
        let mut out = Vec::new();
        match *self {
            Board::Charuco {
                cols,
                rows,
                square_m,
                marker_m,
                codes,
            } => {
                let mut id = 0u32;
                let inset = (square_m - marker_m) / 2.0;
                for r in 0..rows {
                    for c in 0..cols {
                        let (x, y) = (f64::from(c) * square_m, f64::from(r) * square_m);
                        if (r + c) % 2 == 0 {
                            out.push([x, y, square_m, square_m]);
                        } else {
                            marker_rects(codes, id, x + inset, y + inset, marker_m, &mut out)?;
                            id += 1;
                        }
                    }
                }
            }
            Board::ShoalGrid { side_m, .. } => {
                for (id, [cx, cy]) in self.shoal_markers() {
                    let h = side_m / 2.0;
                    marker_rects(CodeSet::Shoal, id, cx - h, cy - h, side_m, &mut out)?;
                }
            }
        }
        Ok(out)
    }

    /// The board as an SVG page whose user unit is the millimetre (print at
    /// 100 %), with its description in the margin.
    pub fn svg(&self) -> Result<String, BoardError> {
        let rects = self.black_rects()?;
        let (w, h) = self.size_m();
        let (pw, ph) = (w * 1e3 + 2.0 * MARGIN_MM, h * 1e3 + 2.0 * MARGIN_MM);
        let mut s = String::new();
        let _ = writeln!(s, r#"<?xml version="1.0" encoding="UTF-8"?>"#);
        let _ = writeln!(
            s,
            r#"<svg xmlns="http://www.w3.org/2000/svg" width="{pw:.3}mm" height="{ph:.3}mm" viewBox="0 0 {pw:.3} {ph:.3}" shape-rendering="crispEdges">"#
        );
        let _ = writeln!(
            s,
            r#"<rect x="0" y="0" width="{pw:.3}" height="{ph:.3}" fill="white"/>"#
        );
        for [x, y, rw, rh] in rects {
            let _ = writeln!(
                s,
                r#"<rect x="{:.4}" y="{:.4}" width="{:.4}" height="{:.4}" fill="black"/>"#,
                MARGIN_MM + x * 1e3,
                MARGIN_MM + y * 1e3,
                rw * 1e3,
                rh * 1e3
            );
        }
        let _ = writeln!(
            s,
            r#"<text x="{MARGIN_MM:.3}" y="{:.3}" font-family="sans-serif" font-size="3.5" fill="black">{}  (print at 100 %; measure a square before you calibrate)</text>"#,
            ph - MARGIN_MM / 2.5,
            self.describe()
        );
        let _ = writeln!(s, "</svg>");
        Ok(s)
    }

    /// The board's pattern as a grey image at `px_per_m` (no margin): each
    /// pixel black where its centre is in a black rectangle.
    pub fn raster(&self, px_per_m: f64) -> Result<Mat, BoardError> {
        let rects = self.black_rects()?;
        let (w, h) = self.size_m();
        let (wp, hp) = ((w * px_per_m).round() as i32, (h * px_per_m).round() as i32);
        if wp < 8 || hp < 8 || i64::from(wp) * i64::from(hp) > 200_000_000 {
            return Err(BoardError::Invalid(format!(
                "a {wp}x{hp} pixel image of the board is too small or too large"
            )));
        }
        let mut img = Mat::new_rows_cols_with_default(
            hp,
            wp,
            opencv::core::CV_8UC1,
            opencv::core::Scalar::all(255.0),
        )?;
        let data = img.data_bytes_mut()?;
        for [x, y, rw, rh] in rects {
            // Pixels whose centres ((i + 0.5) / px_per_m) fall inside.
            let span = |a: f64, len: f64, max: i32| {
                let lo = ((a * px_per_m - 0.5).ceil().max(0.0)) as i32;
                let hi = (((a + len) * px_per_m - 0.5).ceil().min(f64::from(max))) as i32;
                lo..hi
            };
            for row in span(y, rh, hp) {
                for col in span(x, rw, wp) {
                    data[row as usize * wp as usize + col as usize] = 0;
                }
            }
        }
        Ok(img)
    }

    /// The board as a PNG page at `dpi`, with a white margin.
    pub fn png(&self, dpi: f64) -> Result<Vec<u8>, BoardError> {
        if !(72.0..=2400.0).contains(&dpi) {
            return Err(BoardError::Invalid(format!(
                "resolution must be between 72 and 2400 dpi, got {dpi}"
            )));
        }
        let px_per_m = dpi / 0.0254;
        let pattern = self.raster(px_per_m)?;
        let margin = (MARGIN_MM * 1e-3 * px_per_m).round() as i32;
        let mut page = Mat::default();
        opencv::core::copy_make_border(
            &pattern,
            &mut page,
            margin,
            margin,
            margin,
            margin,
            opencv::core::BORDER_CONSTANT,
            opencv::core::Scalar::all(255.0),
        )?;
        let mut buf = Vector::<u8>::new();
        imgcodecs::imencode(".png", &page, &mut buf, &Vector::new())?;
        Ok(buf.to_vec())
    }
}

/// The black modules of marker `id` of `codes` whose black square's top-left
/// is at `(x, y)`, side `side` (board frame), merged into horizontal runs.
fn marker_rects(
    codes: CodeSet,
    id: u32,
    x: f64,
    y: f64,
    side: f64,
    out: &mut Vec<[f64; 4]>,
) -> Result<(), BoardError> {
    let grid = codes.module_grid(id)?;
    let n = codes.modules();
    let m = side / n as f64;
    for r in 0..n {
        let mut c = 0;
        while c < n {
            if grid[r * n + c] {
                c += 1;
                continue;
            }
            let start = c;
            while c < n && !grid[r * n + c] {
                c += 1;
            }
            out.push([
                x + start as f64 * m,
                y + r as f64 * m,
                (c - start) as f64 * m,
                m,
            ]);
        }
    }
    Ok(())
}

/// Refine chessboard corners to their saddle points (`cv::cornerSubPix`).
/// OpenCV 4.6's `interpolateCornersCharuco` returns them half a pixel off
/// on a sharp synthetic board (200.0 for a saddle at 199.5; its window is
/// chosen from the markers); a window of a fifth of the corner spacing
/// (2–10 px) on the grey image converges to 199.5.
fn refine_saddles(gray: &Mat, corners: &mut Vector<Point2f>) -> Result<(), BoardError> {
    if corners.len() < 2 {
        return Ok(());
    }
    let pts = corners.to_vec();
    let mut nearest: Vec<f32> = pts
        .iter()
        .enumerate()
        .map(|(i, p)| {
            pts.iter()
                .enumerate()
                .filter(|(j, _)| *j != i)
                .map(|(_, q)| (p.x - q.x).hypot(p.y - q.y))
                .fold(f32::INFINITY, f32::min)
        })
        .collect();
    nearest.sort_by(f32::total_cmp);
    let spacing = nearest[nearest.len() / 2];
    let half = (spacing / 5.0).round().clamp(2.0, 10.0) as i32;
    opencv::imgproc::corner_sub_pix(
        gray,
        corners,
        opencv::core::Size::new(half, half),
        opencv::core::Size::new(-1, -1),
        opencv::core::TermCriteria::new(
            opencv::core::TermCriteria_Type::COUNT as i32
                + opencv::core::TermCriteria_Type::EPS as i32,
            50,
            1e-4,
        )?,
    )?;
    Ok(())
}

/// Finds a board's points in grey images.
pub struct BoardDetector {
    board: Board,
    finder: Finder,
}

enum Finder {
    Charuco {
        board: Ptr<aruco::CharucoBoard>,
        dictionary: Ptr<aruco::Dictionary>,
        params: Ptr<aruco::DetectorParameters>,
    },
    Shoal(Box<ShoalDetector>),
}

impl BoardDetector {
    pub fn new(board: Board) -> Result<BoardDetector, BoardError> {
        board.validate()?;
        let finder = match board {
            Board::Charuco {
                cols,
                rows,
                square_m,
                marker_m,
                codes,
            } => {
                let name = crate::baseline::opencv_dictionary(codes).ok_or_else(|| {
                    BoardError::Invalid(format!("{codes} is no OpenCV dictionary"))
                })?;
                let dictionary = aruco::get_predefined_dictionary(name)?;
                let board = aruco::CharucoBoard::create(
                    cols as i32,
                    rows as i32,
                    square_m as f32,
                    marker_m as f32,
                    &dictionary,
                )?;
                let mut params = aruco::DetectorParameters::create()?;
                params.set_corner_refinement_method(aruco::CORNER_REFINE_SUBPIX);
                Finder::Charuco {
                    board,
                    dictionary,
                    params,
                }
            }
            Board::ShoalGrid { .. } => Finder::Shoal(Box::new(ShoalDetector::new(
                CodeSet::Shoal,
                DetectParams::default(),
            ))),
        };
        Ok(BoardDetector { board, finder })
    }

    pub fn board(&self) -> &Board {
        &self.board
    }

    /// The board points seen in `gray` (an 8-bit grey image), in ID order.
    pub fn detect(&mut self, gray: &Mat) -> Result<Vec<BoardPoint>, BoardError> {
        let mut out = match &mut self.finder {
            Finder::Charuco {
                board,
                dictionary,
                params,
            } => {
                let mut corners: Vector<Vector<Point2f>> = Vector::new();
                let mut ids: Vector<i32> = Vector::new();
                let mut rejected: Vector<Vector<Point2f>> = Vector::new();
                aruco::detect_markers(
                    gray,
                    dictionary,
                    &mut corners,
                    &mut ids,
                    params,
                    &mut rejected,
                )?;
                if ids.is_empty() {
                    return Ok(Vec::new());
                }
                let mut ch_corners: Vector<Point2f> = Vector::new();
                let mut ch_ids: Vector<i32> = Vector::new();
                aruco::interpolate_corners_charuco_def(
                    &corners,
                    &ids,
                    gray,
                    board,
                    &mut ch_corners,
                    &mut ch_ids,
                )?;
                refine_saddles(gray, &mut ch_corners)?;
                let chess = board.chessboard_corners();
                let mut v = Vec::with_capacity(ch_ids.len());
                for (id, p) in ch_ids.iter().zip(ch_corners.iter()) {
                    let Ok(q) = chess.get(id.max(0) as usize) else {
                        continue;
                    };
                    v.push(BoardPoint {
                        id: id as u32,
                        board: [f64::from(q.x), f64::from(q.y), 0.0],
                        image: [f64::from(p.x), f64::from(p.y)],
                    });
                }
                v
            }
            Finder::Shoal(det) => {
                let markers = self.board.shoal_markers();
                let side = match self.board {
                    Board::ShoalGrid { side_m, .. } => side_m,
                    Board::Charuco { .. } => {
                        unreachable!("a shoal finder is made for shoal grids only")
                    }
                };
                let found = det
                    .detect(gray)
                    .map_err(|e| BoardError::Invalid(format!("shoal detector: {e}")))?;
                let corners = CodeSet::Shoal.corners_3d(side);
                let mut v = Vec::new();
                for d in &found {
                    let Some(k) = markers.iter().position(|(id, _)| *id == d.id) else {
                        continue; // a marker that is not on this board
                    };
                    // Contour-polygon corners are whole pixels (a square
                    // clipped by the image border, or without a sub-pixel
                    // fit): not calibration points.
                    if matches!(
                        d.corner_fit.fit,
                        CornerFit::Contour | CornerFit::CoarseLines
                    ) {
                        continue;
                    }
                    let [cx, cy] = markers[k].1;
                    for (&i, px) in d.corner_ids.iter().zip(&d.corners_px) {
                        let c = corners[i as usize];
                        // Marker frame (x right, y up) to board frame (x right, y down).
                        v.push(BoardPoint {
                            id: (12 * k + usize::from(i)) as u32,
                            board: [cx + c.x, cy - c.y, 0.0],
                            image: *px,
                        });
                    }
                }
                v
            }
        };
        out.sort_by_key(|p| p.id);
        out.dedup_by_key(|p| p.id);
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn charuco() -> Board {
        Board::Charuco {
            cols: 5,
            rows: 7,
            square_m: 0.04,
            marker_m: 0.03,
            codes: CodeSet::Aruco4x4_50,
        }
    }

    /// shoal's own geometry of a ChArUco board against OpenCV's drawing of
    /// the same board (`CharucoBoard::draw`), pixel for pixel away from edges.
    #[test]
    fn charuco_pattern_is_opencvs() {
        for board in [
            charuco(),
            Board::Charuco {
                cols: 8,
                rows: 8,
                square_m: 0.0254,
                marker_m: 0.01905,
                codes: CodeSet::Aruco4x4_1000,
            },
            Board::Charuco {
                cols: 6,
                rows: 5,
                square_m: 0.03,
                marker_m: 0.02,
                codes: CodeSet::Aruco6x6_250,
            },
        ] {
            let Board::Charuco {
                cols,
                rows,
                square_m,
                marker_m,
                codes,
            } = board
            else {
                unreachable!()
            };
            let px_per_m = 2000.0 / square_m / f64::from(cols.max(rows)) * 0.5;
            let ours = board.raster(px_per_m).unwrap();
            let dict = aruco::get_predefined_dictionary(
                crate::baseline::opencv_dictionary(codes).unwrap(),
            )
            .unwrap();
            let mut cv = aruco::CharucoBoard::create(
                cols as i32,
                rows as i32,
                square_m as f32,
                marker_m as f32,
                &dict,
            )
            .unwrap();
            let mut theirs = Mat::default();
            cv.draw(ours.size().unwrap(), &mut theirs, 0, 1).unwrap();
            assert_eq!(theirs.size().unwrap(), ours.size().unwrap());
            let (a, b) = (ours.data_bytes().unwrap(), theirs.data_bytes().unwrap());
            let w = ours.cols() as usize;
            let h = ours.rows() as usize;
            // Pixels within 2 px of an edge of ours may round differently
            // (OpenCV resizes each marker to whole pixels); every other
            // pixel must agree.
            let (mut compared, mut differ) = (0usize, 0usize);
            for y in 2..h - 2 {
                for x in 2..w - 2 {
                    let v = a[y * w + x] < 128;
                    let uniform = (y - 2..=y + 2)
                        .all(|yy| (x - 2..=x + 2).all(|xx| (a[yy * w + xx] < 128) == v));
                    if uniform {
                        compared += 1;
                        differ += usize::from(v != (b[y * w + x] < 128));
                    }
                }
            }
            assert!(
                compared > a.len() / 2,
                "{compared} of {} pixels compared",
                a.len()
            );
            assert_eq!(
                differ,
                0,
                "{}: {differ} of {compared} pixels differ",
                board.describe()
            );
        }
    }

    #[test]
    fn a_rendered_charuco_board_gives_its_corners() {
        let board = charuco();
        let img = board.raster(4000.0).unwrap(); // 0.25 mm per pixel, 160 px squares
        let mut padded = Mat::default();
        opencv::core::copy_make_border(
            &img,
            &mut padded,
            40,
            40,
            40,
            40,
            opencv::core::BORDER_CONSTANT,
            opencv::core::Scalar::all(255.0),
        )
        .unwrap();
        // A camera's blur: on a binary image a saddle point is anywhere
        // within its pixel.
        let mut blurred = Mat::default();
        opencv::imgproc::gaussian_blur_def(
            &padded,
            &mut blurred,
            opencv::core::Size::new(0, 0),
            1.5,
        )
        .unwrap();
        let mut det = BoardDetector::new(board).unwrap();
        let pts = det.detect(&blurred).unwrap();
        assert_eq!(pts.len(), 4 * 6, "every inner corner of a 5x7 board");
        for p in &pts {
            // Board (m) to image (px): 4000 px/m, 40 px border, pixel centres at +0.5.
            let want = [
                p.board[0] * 4000.0 + 40.0 - 0.5,
                p.board[1] * 4000.0 + 40.0 - 0.5,
            ];
            let err = (p.image[0] - want[0]).hypot(p.image[1] - want[1]);
            assert!(
                err < 0.1,
                "corner {} at {:?}, expected {want:?}",
                p.id,
                p.image
            );
        }
    }

    #[test]
    fn bad_boards_are_refused_with_the_reason() {
        let e = Board::Charuco {
            cols: 5,
            rows: 7,
            square_m: 0.03,
            marker_m: 0.04,
            codes: CodeSet::Aruco4x4_50,
        }
        .validate()
        .unwrap_err()
        .to_string();
        assert!(e.contains("smaller than its square"), "{e}");
        let e = Board::Charuco {
            cols: 12,
            rows: 12,
            square_m: 0.04,
            marker_m: 0.03,
            codes: CodeSet::Aruco4x4_50,
        }
        .validate()
        .unwrap_err()
        .to_string();
        assert!(e.contains("72 markers") && e.contains("50"), "{e}");
        let e = Board::ShoalGrid {
            cols: 3,
            rows: 2,
            side_m: 0.1,
            gap_m: 0.01,
            first_id: 0,
        }
        .validate()
        .unwrap_err()
        .to_string();
        assert!(e.contains("quiet zones"), "{e}");
        let e = Board::Charuco {
            cols: 5,
            rows: 7,
            square_m: 0.04,
            marker_m: 0.03,
            codes: CodeSet::Shoal,
        }
        .validate()
        .unwrap_err()
        .to_string();
        assert!(e.contains("ArUco dictionary"), "{e}");
    }

    #[test]
    fn the_svg_page_is_true_size() {
        let svg = charuco().svg().unwrap();
        // 5x7 squares of 40 mm plus two 12 mm margins.
        assert!(
            svg.contains(r#"width="224.000mm" height="304.000mm""#),
            "{}",
            &svg[..300]
        );
        let black = svg.matches(r#"fill="black"/>"#).count();
        assert!(black > 18, "{black} black rectangles");
    }
}
