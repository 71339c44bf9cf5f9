//! Camera calibration from views of a board ([`crate::board`]): which views
//! to keep and why the others are not kept, the fit (OpenCV 4.6's
//! `cv::calibrateCameraExtended` for plumb-bob and rational lenses,
//! `cv::fisheye::calibrate` for equidistant ones), per-view reprojection
//! errors through shoal's own lens model, where in the image corners were
//! seen, and warnings where the views cannot pin the model down.

use crate::board::BoardPoint;
use opencv::core::{Mat, Point2f, Point3f, Size, TermCriteria, TermCriteria_Type, Vector};
use opencv::prelude::*;
use opencv::{calib3d, imgcodecs, imgproc};
use shoal_proto::camera::{CameraModel, Distortion};
use shoal_proto::geometry::Pose;

/// The lens model to fit (ROS names).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LensKind {
    PlumbBob,
    Rational,
    Equidistant,
}

impl std::str::FromStr for LensKind {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "plumb_bob" => Ok(LensKind::PlumbBob),
            "rational_polynomial" => Ok(LensKind::Rational),
            "equidistant" | "fisheye" => Ok(LensKind::Equidistant),
            other => Err(format!(
                "lens model `{other}`: expected plumb_bob, rational_polynomial or equidistant"
            )),
        }
    }
}

/// What the calibration is asked for.
#[derive(Debug, Clone, Copy)]
pub struct CalibrateOptions {
    pub lens: LensKind,
    /// Fewest board points a view must show.
    pub min_points: usize,
    /// A view whose points moved less than this (median, px) from the last
    /// kept view is a repeat (a still camera in a video) and not kept.
    pub min_motion_px: f64,
    /// A view whose reprojection RMS is over `outlier_factor` times the
    /// median (and over 1 px) is dropped and the fit repeated once.
    pub outlier_factor: f64,
}

impl Default for CalibrateOptions {
    fn default() -> Self {
        CalibrateOptions {
            lens: LensKind::PlumbBob,
            min_points: 8,
            min_motion_px: 8.0,
            outlier_factor: 3.0,
        }
    }
}

/// Why a view was not used.
#[derive(Debug, Clone, PartialEq)]
pub enum Rejection {
    /// Fewer board points than the fit needs from one view.
    TooFewPoints { found: usize, need: usize },
    /// The points lie on (nearly) one line: no pose, no constraint.
    Collinear,
    /// Nearly the view kept before it.
    Repeat { of: String, moved_px: f64 },
    /// Its reprojection error is far above the other views'.
    Outlier { rms_px: f64, median_px: f64 },
    /// `cv::fisheye::calibrate` finds its extrinsics ill-conditioned (a
    /// view too oblique, too small or too far out for its start).
    IllConditioned,
    /// The frame could not be read or searched.
    Unreadable(String),
}

impl std::fmt::Display for Rejection {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Rejection::TooFewPoints { found, need } => {
                write!(f, "{found} board points, at least {need} needed")
            }
            Rejection::Collinear => f.write_str("the board points lie on one line"),
            Rejection::Repeat { of, moved_px } => {
                write!(f, "the same view as {of} (points moved {moved_px:.1} px)")
            }
            Rejection::Outlier { rms_px, median_px } => write!(
                f,
                "reprojection RMS {rms_px:.2} px, over 3x the views' median {median_px:.2} px (a blurred or misread view)"
            ),
            Rejection::IllConditioned => f.write_str(
                "cv::fisheye finds this view ill-conditioned (too oblique, small or far out for its start)",
            ),
            Rejection::Unreadable(why) => f.write_str(why),
        }
    }
}

/// Views gathered for a calibration.
#[derive(Debug, Default)]
pub struct Views {
    pub kept: Vec<(String, Vec<BoardPoint>)>,
    pub rejected: Vec<(String, Rejection)>,
}

impl Views {
    /// Offer a view (`name`: file and frame); it is kept or rejected with the reason.
    pub fn offer(&mut self, name: String, points: Vec<BoardPoint>, opts: &CalibrateOptions) {
        if points.len() < opts.min_points {
            self.rejected.push((
                name,
                Rejection::TooFewPoints {
                    found: points.len(),
                    need: opts.min_points,
                },
            ));
            return;
        }
        if collinear(&points) {
            self.rejected.push((name, Rejection::Collinear));
            return;
        }
        if let Some((prev_name, prev)) = self.kept.last() {
            if let Some(moved) = median_motion(prev, &points) {
                if moved < opts.min_motion_px {
                    let of = prev_name.clone();
                    self.rejected.push((
                        name,
                        Rejection::Repeat {
                            of,
                            moved_px: moved,
                        },
                    ));
                    return;
                }
            }
        }
        self.kept.push((name, points));
    }

    pub fn reject(&mut self, name: String, why: Rejection) {
        self.rejected.push((name, why));
    }
}

/// True when the board points span (nearly) no area: the smaller principal
/// spread is under 2 % of the larger.
fn collinear(points: &[BoardPoint]) -> bool {
    let n = points.len() as f64;
    let (mx, my) = points.iter().fold((0.0, 0.0), |(a, b), p| {
        (a + p.board[0] / n, b + p.board[1] / n)
    });
    let (mut sxx, mut syy, mut sxy) = (0.0, 0.0, 0.0);
    for p in points {
        let (dx, dy) = (p.board[0] - mx, p.board[1] - my);
        sxx += dx * dx;
        syy += dy * dy;
        sxy += dx * dy;
    }
    let tr = sxx + syy;
    let det = sxx * syy - sxy * sxy;
    let disc = (tr * tr / 4.0 - det).max(0.0).sqrt();
    let (big, small) = (tr / 2.0 + disc, (tr / 2.0 - disc).max(0.0));
    big <= 0.0 || (small / big).sqrt() < 0.02
}

/// Median image motion of the points two views share; `None` if they share
/// fewer than 4.
fn median_motion(a: &[BoardPoint], b: &[BoardPoint]) -> Option<f64> {
    let mut d: Vec<f64> = b
        .iter()
        .filter_map(|p| {
            let q = a.iter().find(|q| q.id == p.id)?;
            Some((p.image[0] - q.image[0]).hypot(p.image[1] - q.image[1]))
        })
        .collect();
    if d.len() < 4 || d.len() * 2 < b.len() {
        return None;
    }
    d.sort_by(f64::total_cmp);
    Some(d[d.len() / 2])
}

/// One kept view after the fit.
#[derive(Debug, Clone)]
pub struct ViewFit {
    pub name: String,
    pub points: usize,
    pub rms_px: f64,
    /// Board pose in the camera frame.
    pub camera_from_board: Pose,
    /// Angle between the board's normal and the optical axis (degrees).
    pub tilt_deg: f64,
}

/// A calibration and what can be said about it.
#[derive(Debug, Clone)]
pub struct Calibration {
    pub model: CameraModel,
    /// Reprojection RMS over every point of the kept views (px).
    pub rms_px: f64,
    /// OpenCV's standard deviations of fx, fy, cx, cy (px); `None` for
    /// `cv::fisheye`, which does not give them.
    pub std_intrinsics: Option<[f64; 4]>,
    pub views: Vec<ViewFit>,
    pub rejected: Vec<(String, Rejection)>,
    pub coverage: Coverage,
    pub warnings: Vec<String>,
}

/// Where in the image board points were seen: counts over a grid of cells.
#[derive(Debug, Clone)]
pub struct Coverage {
    pub cols: usize,
    pub rows: usize,
    pub counts: Vec<usize>,
}

impl Coverage {
    const COLS: usize = 8;
    const ROWS: usize = 6;

    fn of(views: &[(String, Vec<BoardPoint>)], width: u32, height: u32) -> Coverage {
        let mut counts = vec![0; Self::COLS * Self::ROWS];
        for (_, pts) in views {
            for p in pts {
                let c = ((p.image[0] + 0.5) / f64::from(width) * Self::COLS as f64).floor();
                let r = ((p.image[1] + 0.5) / f64::from(height) * Self::ROWS as f64).floor();
                if (0.0..Self::COLS as f64).contains(&c) && (0.0..Self::ROWS as f64).contains(&r) {
                    counts[r as usize * Self::COLS + c as usize] += 1;
                }
            }
        }
        Coverage {
            cols: Self::COLS,
            rows: Self::ROWS,
            counts,
        }
    }

    /// Fraction of cells with at least one point.
    pub fn fraction(&self) -> f64 {
        self.counts.iter().filter(|c| **c > 0).count() as f64 / self.counts.len() as f64
    }

    /// Names of the image corners (the outer cells) with no point.
    pub fn empty_corners(&self) -> Vec<&'static str> {
        let (c, r) = (self.cols - 1, self.rows - 1);
        [
            ("top-left", 0, 0),
            ("top-right", c, 0),
            ("bottom-left", 0, r),
            ("bottom-right", c, r),
        ]
        .into_iter()
        .filter(|(_, x, y)| self.counts[y * self.cols + x] == 0)
        .map(|(n, _, _)| n)
        .collect()
    }
}

/// Errors of the calibration.
#[derive(Debug, thiserror::Error)]
pub enum CalibrateError {
    #[error(
        "{kept} views kept, at least {need} needed ({rejected} rejected; see the reasons above)"
    )]
    TooFewViews {
        kept: usize,
        need: usize,
        rejected: usize,
    },
    #[error("the fit gives no usable camera: {0}")]
    Implausible(String),
    /// An input (folder, video, camera) that cannot be read at all.
    #[error("{0}")]
    Input(String),
    #[error("OpenCV: {0}")]
    OpenCv(#[from] opencv::Error),
}

/// The view `cv::fisheye::calibrate` names in its "ill-conditioned" error.
fn ill_conditioned_view(e: &CalibrateError) -> Option<usize> {
    let CalibrateError::OpenCv(e) = e else {
        return None;
    };
    let rest = e
        .message
        .split("Ill-conditioned matrix for input array ")
        .nth(1)?;
    rest.split(|c: char| !c.is_ascii_digit())
        .next()?
        .parse()
        .ok()
}

/// Fewest views a calibration is attempted from.
pub const MIN_VIEWS: usize = 4;
/// Fewer kept views than this give a warning.
pub const ADVISED_VIEWS: usize = 10;

/// Fit `opts.lens` to the kept views of a `width` x `height` camera;
/// outlier views are dropped once and the fit repeated.
pub fn calibrate(
    views: Views,
    width: u32,
    height: u32,
    opts: &CalibrateOptions,
) -> Result<Calibration, CalibrateError> {
    let Views {
        mut kept,
        mut rejected,
    } = views;
    let need = MIN_VIEWS;
    if kept.len() < need {
        return Err(CalibrateError::TooFewViews {
            kept: kept.len(),
            need,
            rejected: rejected.len(),
        });
    }
    let mut fit = fit_dropping_ill_conditioned(&mut kept, &mut rejected, width, height, opts.lens)?;
    let mut rms: Vec<f64> = fit.views.iter().map(|v| v.rms_px).collect();
    rms.sort_by(f64::total_cmp);
    let median = rms[rms.len() / 2];
    let limit = (opts.outlier_factor * median).max(1.0);
    if fit.views.iter().any(|v| v.rms_px > limit) && kept.len() > need {
        let bad: Vec<usize> = (0..kept.len())
            .filter(|i| fit.views[*i].rms_px > limit)
            .collect();
        for &i in bad.iter().rev() {
            let (name, _) = kept.remove(i);
            rejected.push((
                name,
                Rejection::Outlier {
                    rms_px: fit.views[i].rms_px,
                    median_px: median,
                },
            ));
        }
        if kept.len() < need {
            return Err(CalibrateError::TooFewViews {
                kept: kept.len(),
                need,
                rejected: rejected.len(),
            });
        }
        fit = fit_dropping_ill_conditioned(&mut kept, &mut rejected, width, height, opts.lens)?;
    }
    if let Some(p) = fit.model.problem() {
        return Err(CalibrateError::Implausible(p));
    }
    let coverage = Coverage::of(&kept, width, height);
    let warnings = warnings(&fit, &coverage, kept.len());
    Ok(Calibration {
        model: fit.model,
        rms_px: fit.rms_px,
        std_intrinsics: fit.std_intrinsics,
        views: fit.views,
        rejected,
        coverage,
        warnings,
    })
}

/// [`fit_once`], dropping each view `cv::fisheye` calls ill-conditioned
/// (with the reason) until the fit succeeds or too few views are left.
fn fit_dropping_ill_conditioned(
    kept: &mut Vec<(String, Vec<BoardPoint>)>,
    rejected: &mut Vec<(String, Rejection)>,
    width: u32,
    height: u32,
    lens: LensKind,
) -> Result<Fit, CalibrateError> {
    loop {
        match fit_once(kept, width, height, lens) {
            Ok(fit) => return Ok(fit),
            Err(e) => {
                let Some(i) = ill_conditioned_view(&e).filter(|i| *i < kept.len()) else {
                    return Err(e);
                };
                let (name, _) = kept.remove(i);
                rejected.push((name, Rejection::IllConditioned));
                if kept.len() < MIN_VIEWS {
                    return Err(CalibrateError::TooFewViews {
                        kept: kept.len(),
                        need: MIN_VIEWS,
                        rejected: rejected.len(),
                    });
                }
            }
        }
    }
}

fn warnings(fit: &Fit, coverage: &Coverage, kept: usize) -> Vec<String> {
    let mut w = Vec::new();
    if kept < ADVISED_VIEWS {
        w.push(format!(
            "only {kept} views: {ADVISED_VIEWS} or more, at different places, distances and tilts, pin a lens down"
        ));
    }
    let frac = coverage.fraction();
    if frac < 0.6 {
        w.push(format!(
            "board points cover {:.0} % of the image (in {}x{} cells): show the board near the edges too, or the distortion there is a guess",
            frac * 100.0,
            coverage.cols,
            coverage.rows
        ));
    }
    let empty = coverage.empty_corners();
    if !empty.is_empty() {
        w.push(format!(
            "no board point in the image's {} corner{}: the lens model is extrapolated there",
            empty.join(", "),
            if empty.len() > 1 { "s" } else { "" }
        ));
    }
    let max_tilt = fit.views.iter().map(|v| v.tilt_deg).fold(0.0, f64::max);
    if max_tilt < 20.0 {
        w.push(format!(
            "the board is never tilted more than {max_tilt:.0}° to the camera: focal length and distance trade off; tilt it 30–45° in some views"
        ));
    }
    if fit.rms_px > 1.0 {
        w.push(format!(
            "reprojection RMS {:.2} px: over 1 px, the board is blurred, not flat, misprinted or the lens model too simple",
            fit.rms_px
        ));
    }
    w
}

struct Fit {
    model: CameraModel,
    rms_px: f64,
    std_intrinsics: Option<[f64; 4]>,
    views: Vec<ViewFit>,
}

fn fit_once(
    kept: &[(String, Vec<BoardPoint>)],
    width: u32,
    height: u32,
    lens: LensKind,
) -> Result<Fit, CalibrateError> {
    let mut obj: Vector<Vector<Point3f>> = Vector::new();
    let mut img: Vector<Vector<Point2f>> = Vector::new();
    for (_, pts) in kept {
        obj.push(
            pts.iter()
                .map(|p| Point3f::new(p.board[0] as f32, p.board[1] as f32, p.board[2] as f32))
                .collect(),
        );
        img.push(
            pts.iter()
                .map(|p| Point2f::new(p.image[0] as f32, p.image[1] as f32))
                .collect(),
        );
    }
    let size = Size::new(width as i32, height as i32);
    let mut k = Mat::default();
    let mut d = Mat::default();
    let mut rvecs: Vector<Mat> = Vector::new();
    let mut tvecs: Vector<Mat> = Vector::new();
    let criteria = TermCriteria::new(
        TermCriteria_Type::COUNT as i32 + TermCriteria_Type::EPS as i32,
        200,
        1e-12,
    )?;
    let mut std_intrinsics = None;
    match lens {
        LensKind::PlumbBob | LensKind::Rational => {
            let flags = if lens == LensKind::Rational {
                calib3d::CALIB_RATIONAL_MODEL
            } else {
                0
            };
            let (mut sd_in, mut sd_ex, mut per_view) =
                (Mat::default(), Mat::default(), Mat::default());
            calib3d::calibrate_camera_extended(
                &obj,
                &img,
                size,
                &mut k,
                &mut d,
                &mut rvecs,
                &mut tvecs,
                &mut sd_in,
                &mut sd_ex,
                &mut per_view,
                flags,
                criteria,
            )?;
            let s = |i: i32| sd_in.at::<f64>(i).copied().unwrap_or(f64::NAN);
            std_intrinsics = Some([s(0), s(1), s(2), s(3)]);
        }
        LensKind::Equidistant => {
            let flags = calib3d::Fisheye_CALIB_RECOMPUTE_EXTRINSIC
                | calib3d::Fisheye_CALIB_FIX_SKEW
                | calib3d::Fisheye_CALIB_CHECK_COND;
            calib3d::calibrate(
                &obj, &img, size, &mut k, &mut d, &mut rvecs, &mut tvecs, flags, criteria,
            )?;
        }
    }
    let kv = |r: i32, c: i32| k.at_2d::<f64>(r, c).copied();
    let coeffs: Vec<f64> = (0..d.total() as i32)
        .map(|i| d.at::<f64>(i).copied())
        .collect::<Result<_, _>>()?;
    let distortion = match lens {
        LensKind::PlumbBob => {
            Distortion::from_ros(Some("plumb_bob"), &coeffs[..5.min(coeffs.len())])
        }
        LensKind::Rational => {
            Distortion::from_ros(Some("rational_polynomial"), &coeffs[..8.min(coeffs.len())])
        }
        LensKind::Equidistant => {
            Distortion::from_ros(Some("equidistant"), &coeffs[..4.min(coeffs.len())])
        }
    }
    .map_err(CalibrateError::Implausible)?;
    let model = CameraModel {
        width,
        height,
        fx: kv(0, 0)?,
        fy: kv(1, 1)?,
        cx: kv(0, 2)?,
        cy: kv(1, 2)?,
        distortion,
    };
    let (views, rms_px) = view_fits(&model, kept, &rvecs, &tvecs)?;
    Ok(Fit {
        model,
        rms_px,
        std_intrinsics,
        views,
    })
}

/// Each view's reprojection RMS through shoal's own lens model, its board
/// pose and tilt; and the RMS over every point.
fn view_fits(
    model: &CameraModel,
    kept: &[(String, Vec<BoardPoint>)],
    rvecs: &Vector<Mat>,
    tvecs: &Vector<Mat>,
) -> Result<(Vec<ViewFit>, f64), CalibrateError> {
    let mut views = Vec::with_capacity(kept.len());
    let (mut ssr, mut n) = (0.0, 0usize);
    for (i, (name, pts)) in kept.iter().enumerate() {
        let (r, t) = (rvecs.get(i)?, tvecs.get(i)?);
        let g = |m: &Mat, j: i32| m.at::<f64>(j).copied();
        let pose = Pose::from_parts(
            nalgebra::Translation3::new(g(&t, 0)?, g(&t, 1)?, g(&t, 2)?),
            nalgebra::UnitQuaternion::from_scaled_axis(nalgebra::Vector3::new(
                g(&r, 0)?,
                g(&r, 1)?,
                g(&r, 2)?,
            )),
        );
        let mut view_ssr = 0.0;
        for p in pts {
            let q =
                model.project(&(pose * nalgebra::Point3::new(p.board[0], p.board[1], p.board[2])));
            view_ssr += q.map_or(1e6, |q| {
                (q.x - p.image[0]).powi(2) + (q.y - p.image[1]).powi(2)
            });
        }
        ssr += view_ssr;
        n += pts.len();
        let normal = pose.rotation * nalgebra::Vector3::z();
        views.push(ViewFit {
            name: name.clone(),
            points: pts.len(),
            rms_px: (view_ssr / pts.len() as f64).sqrt(),
            camera_from_board: pose,
            tilt_deg: normal.z.abs().clamp(0.0, 1.0).acos().to_degrees(),
        });
    }
    Ok((views, (ssr / n.max(1) as f64).sqrt()))
}

/// A picture of where corners were seen: the image area (scaled to at most
/// 960 px wide) with each cell shaded by its count, every kept point as a
/// green dot, and the outline of each view's points.
pub fn coverage_png(
    kept: &[(String, Vec<BoardPoint>)],
    width: u32,
    height: u32,
) -> Result<Vec<u8>, CalibrateError> {
    use opencv::core::{Point, Scalar, CV_8UC3};
    let scale = (960.0 / f64::from(width)).min(1.0);
    let (w, h) = (
        (f64::from(width) * scale).round() as i32,
        (f64::from(height) * scale).round() as i32,
    );
    let mut img = Mat::new_rows_cols_with_default(h, w, CV_8UC3, Scalar::all(40.0))?;
    let cov = Coverage::of(kept, width, height);
    let peak = cov.counts.iter().copied().max().unwrap_or(1).max(1) as f64;
    for r in 0..cov.rows {
        for c in 0..cov.cols {
            let n = cov.counts[r * cov.cols + c] as f64;
            let shade = if n == 0.0 {
                0.0
            } else {
                60.0 + 120.0 * (n / peak)
            };
            let x0 = (c as f64 * f64::from(w) / cov.cols as f64) as i32;
            let y0 = (r as f64 * f64::from(h) / cov.rows as f64) as i32;
            let x1 = ((c + 1) as f64 * f64::from(w) / cov.cols as f64) as i32;
            let y1 = ((r + 1) as f64 * f64::from(h) / cov.rows as f64) as i32;
            let colour = if n == 0.0 {
                Scalar::new(40.0, 40.0, 110.0, 0.0) // empty cells: dull red
            } else {
                Scalar::all(shade)
            };
            imgproc::rectangle_points(
                &mut img,
                Point::new(x0, y0),
                Point::new(x1 - 1, y1 - 1),
                colour,
                -1,
                imgproc::LINE_8,
                0,
            )?;
        }
    }
    for (_, pts) in kept {
        for p in pts {
            let at = Point::new(
                (p.image[0] * scale).round() as i32,
                (p.image[1] * scale).round() as i32,
            );
            imgproc::circle(
                &mut img,
                at,
                2,
                Scalar::new(60.0, 220.0, 60.0, 0.0),
                -1,
                imgproc::LINE_AA,
                0,
            )?;
        }
    }
    let mut buf = Vector::<u8>::new();
    imgcodecs::imencode(".png", &img, &mut buf, &Vector::new())?;
    Ok(buf.to_vec())
}

/// Where calibration frames come from.
#[derive(Debug, Clone, PartialEq)]
pub enum CalibrationInput {
    /// An image file, a folder of images (sorted by name), or a video file.
    Path(std::path::PathBuf),
    /// A live camera (OpenCV `VideoCapture` device index), read for `frames` frames.
    Camera { device: i32, frames: u32 },
}

/// Read every frame of `inputs`, find the board in each and offer it to a
/// [`Views`]; `progress` is called after each frame with its name and how
/// many views are kept so far. The frames' size is returned with the views;
/// a frame of another size is rejected (one calibration is one camera mode).
pub fn gather_views(
    inputs: &[CalibrationInput],
    detector: &mut crate::board::BoardDetector,
    opts: &CalibrateOptions,
    mut progress: impl FnMut(&str, usize),
) -> Result<(Views, Option<(u32, u32)>), CalibrateError> {
    let mut views = Views::default();
    let mut size: Option<(u32, u32)> = None;
    let mut one = |name: String, frame: Result<Mat, String>, views: &mut Views| {
        let gray = match frame {
            Ok(g) => g,
            Err(why) => {
                views.reject(name, Rejection::Unreadable(why));
                return;
            }
        };
        let this = (gray.cols().max(0) as u32, gray.rows().max(0) as u32);
        match size {
            None => size = Some(this),
            Some(s) if s != this => {
                views.reject(
                    name,
                    Rejection::Unreadable(format!(
                        "{}x{} frame, the first was {}x{} (one calibration is one camera mode)",
                        this.0, this.1, s.0, s.1
                    )),
                );
                return;
            }
            Some(_) => {}
        }
        match detector.detect(&gray) {
            Ok(points) => views.offer(name.clone(), points, opts),
            Err(e) => views.reject(name.clone(), Rejection::Unreadable(e.to_string())),
        }
        progress(&name, views.kept.len());
    };
    for input in inputs {
        match input {
            CalibrationInput::Path(p) if p.is_dir() => {
                let files = crate::source::image_files(p)
                    .map_err(|e| CalibrateError::Input(e.to_string()))?;
                for f in files {
                    let frame =
                        crate::image_file::read_gray(&f, crate::image_file::MAX_IMAGE_PIXELS)
                            .map(|g| g.gray)
                            .map_err(|e| e.to_string());
                    one(f.display().to_string(), frame, &mut views);
                }
            }
            CalibrationInput::Path(p) if crate::detect::paths::is_video(p) => {
                let (mut cap, _) =
                    crate::image_file::open_video(p, crate::image_file::MAX_IMAGE_PIXELS)
                        .map_err(|e| CalibrateError::Input(e.to_string()))?;
                let mut k = 0u64;
                loop {
                    let mut frame = Mat::default();
                    if !opencv::videoio::VideoCaptureTrait::read(&mut cap, &mut frame)
                        .unwrap_or(false)
                        || frame.empty()
                    {
                        break;
                    }
                    one(
                        format!("{} frame {k}", p.display()),
                        crate::source::to_gray(&frame).map_err(|e| e.to_string()),
                        &mut views,
                    );
                    k += 1;
                }
            }
            CalibrationInput::Path(p) => {
                let frame = crate::image_file::read_gray(p, crate::image_file::MAX_IMAGE_PIXELS)
                    .map(|g| g.gray)
                    .map_err(|e| e.to_string());
                one(p.display().to_string(), frame, &mut views);
            }
            CalibrationInput::Camera { device, frames } => {
                let mut cap =
                    opencv::videoio::VideoCapture::new(*device, opencv::videoio::CAP_ANY)?;
                if !cap.is_opened().unwrap_or(false) {
                    return Err(CalibrateError::Input(format!(
                        "camera {device} does not open"
                    )));
                }
                for k in 0..*frames {
                    let mut frame = Mat::default();
                    if !opencv::videoio::VideoCaptureTrait::read(&mut cap, &mut frame)
                        .unwrap_or(false)
                        || frame.empty()
                    {
                        views.reject(
                            format!("camera {device} frame {k}"),
                            Rejection::Unreadable("the camera gave no frame".into()),
                        );
                        break;
                    }
                    one(
                        format!("camera {device} frame {k}"),
                        crate::source::to_gray(&frame).map_err(|e| e.to_string()),
                        &mut views,
                    );
                }
            }
        }
    }
    Ok((views, size))
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Point3;

    /// Views of a 9x6 grid of points (30 mm) seen by a known camera from
    /// varied poses, with 0.1 px noise: the fit recovers the camera.
    fn synthetic(cam: &CameraModel, noise_px: f64) -> Views {
        let mut rng = 12345u64;
        let mut noise = || {
            // xorshift, uniform ±noise·√3 (σ = noise)
            rng ^= rng << 13;
            rng ^= rng >> 7;
            rng ^= rng << 17;
            ((rng >> 11) as f64 / (1u64 << 53) as f64 - 0.5) * 2.0 * noise_px * 3f64.sqrt()
        };
        let mut views = Views::default();
        let opts = CalibrateOptions::default();
        let mut k = 0;
        let tilts = [
            (0.5f64, 0.0f64),
            (-0.4, 0.3),
            (0.1, -0.6),
            (0.3, 0.45),
            (-0.2, -0.5),
            (0.6, 0.2),
        ];
        for (n, (x, y)) in [-0.26, -0.13, 0.0, 0.13, 0.26]
            .iter()
            .flat_map(|x| [-0.17, 0.0, 0.17].map(|y| (*x, y)))
            .enumerate()
        {
            let z = if n % 2 == 0 { 0.5 } else { 0.65 };
            for &(rx, ry) in &[tilts[n % 6], tilts[(n + 3) % 6]] {
                let pose = shoal_proto::geometry::pose_from_xyz_rpy(
                    [x - 0.12, y - 0.075, z],
                    [rx, ry, 0.1],
                );
                let mut pts = Vec::new();
                for j in 0..6 {
                    for i in 0..9 {
                        let b = [f64::from(i) * 0.03, f64::from(j) * 0.03, 0.0];
                        let Some(q) = cam.project(&(pose * Point3::new(b[0], b[1], b[2]))) else {
                            continue;
                        };
                        if q.x < 0.0
                            || q.y < 0.0
                            || q.x > f64::from(cam.width) - 1.0
                            || q.y > f64::from(cam.height) - 1.0
                        {
                            continue;
                        }
                        pts.push(BoardPoint {
                            id: (j * 9 + i) as u32,
                            board: b,
                            image: [q.x + noise(), q.y + noise()],
                        });
                    }
                }
                views.offer(format!("view{k}"), pts, &opts);
                k += 1;
            }
        }
        views
    }

    #[test]
    fn every_lens_model_is_recovered_from_clean_views() {
        for (lens, distortion) in [
            (
                LensKind::PlumbBob,
                Distortion::PlumbBob([-0.08, 0.02, 0.0005, -0.0003, 0.0]),
            ),
            (
                LensKind::Rational,
                Distortion::Rational([0.4, -0.1, 0.0, 0.0, 0.0, 0.5, 0.0, 0.0]),
            ),
            (
                LensKind::Equidistant,
                Distortion::Equidistant([-0.02, 0.01, 0.0, 0.0]),
            ),
        ] {
            let cam = CameraModel {
                width: 1280,
                height: 960,
                fx: 900.0,
                fy: 905.0,
                cx: 650.0,
                cy: 470.0,
                distortion,
            };
            let views = synthetic(&cam, 0.1);
            let opts = CalibrateOptions {
                lens,
                ..CalibrateOptions::default()
            };
            let c = calibrate(views, 1280, 960, &opts).unwrap();
            let m = c.model;
            assert!(
                (m.fx / cam.fx - 1.0).abs() < 0.002 && (m.fy / cam.fy - 1.0).abs() < 0.002,
                "{lens:?}: {m:?}"
            );
            assert!(
                (m.cx - cam.cx).abs() < 1.5 && (m.cy - cam.cy).abs() < 1.5,
                "{lens:?}: {m:?}"
            );
            // Within OpenCV's stated error (3σ): the principal point trades
            // off against the tangential terms, σ(cx) ~0.7 px here.
            if let Some(sd) = c.std_intrinsics {
                let got = [m.fx, m.fy, m.cx, m.cy];
                let want = [cam.fx, cam.fy, cam.cx, cam.cy];
                for i in 0..4 {
                    assert!(
                        (got[i] - want[i]).abs() < 3.0 * sd[i],
                        "{lens:?}: parameter {i} {} vs {} (σ {})",
                        got[i],
                        want[i],
                        sd[i]
                    );
                }
            }
            assert!(c.rms_px < 0.2, "{lens:?}: rms {}", c.rms_px);
            assert_eq!(
                std::mem::discriminant(&m.distortion),
                std::mem::discriminant(&cam.distortion)
            );
            // Where the views saw the board, every pixel maps as the true
            // lens does, to 1.5 px (2σ of the principal point).
            for &(u, v) in &[
                (200.0, 150.0),
                (640.0, 480.0),
                (1080.0, 810.0),
                (200.0, 810.0),
                (1080.0, 150.0),
            ] {
                let (x, y) = cam.ray(u, v);
                let q = m.project(&Point3::new(x, y, 1.0)).unwrap();
                assert!(
                    (q.x - u).hypot(q.y - v) < 1.5,
                    "{lens:?} at ({u}, {v}): {q:?}"
                );
            }
        }
    }

    #[test]
    fn views_are_rejected_with_their_reason() {
        let opts = CalibrateOptions::default();
        let mut views = Views::default();
        let line: Vec<BoardPoint> = (0..10)
            .map(|i| BoardPoint {
                id: i,
                board: [f64::from(i) * 0.03, 0.0, 0.0],
                image: [f64::from(i) * 10.0, 5.0],
            })
            .collect();
        views.offer("line".into(), line, &opts);
        views.offer(
            "few".into(),
            vec![
                BoardPoint {
                    id: 0,
                    board: [0.0; 3],
                    image: [0.0; 2]
                };
                3
            ],
            &opts,
        );
        let grid: Vec<BoardPoint> = (0..12)
            .map(|i| BoardPoint {
                id: i,
                board: [f64::from(i % 4) * 0.03, f64::from(i / 4) * 0.03, 0.0],
                image: [f64::from(i % 4) * 30.0, f64::from(i / 4) * 30.0],
            })
            .collect();
        views.offer("a".into(), grid.clone(), &opts);
        let nudged: Vec<BoardPoint> = grid
            .iter()
            .map(|p| BoardPoint {
                image: [p.image[0] + 1.0, p.image[1]],
                ..*p
            })
            .collect();
        views.offer("b".into(), nudged, &opts);
        assert_eq!(views.kept.len(), 1);
        let why: Vec<String> = views
            .rejected
            .iter()
            .map(|(n, r)| format!("{n}: {r}"))
            .collect();
        assert!(
            why[0].starts_with("line: ") && why[0].contains("one line"),
            "{why:?}"
        );
        assert!(why[1].contains("3 board points, at least 8"), "{why:?}");
        assert!(why[2].contains("the same view as a"), "{why:?}");
        let e = calibrate(views, 640, 480, &opts).unwrap_err().to_string();
        assert!(e.contains("1 views kept, at least 4"), "{e}");
    }

    #[test]
    fn a_misread_view_is_dropped_as_an_outlier() {
        let cam = CameraModel {
            width: 1280,
            height: 960,
            fx: 900.0,
            fy: 900.0,
            cx: 640.0,
            cy: 480.0,
            distortion: Distortion::NONE,
        };
        let mut views = synthetic(&cam, 0.1);
        // One view's points shuffled by 6 px: a misread.
        for p in &mut views.kept[5].1 {
            p.image[0] += if p.id % 2 == 0 { 6.0 } else { -6.0 };
        }
        let c = calibrate(views, 1280, 960, &CalibrateOptions::default()).unwrap();
        assert!(
            c.rejected
                .iter()
                .any(|(n, r)| n == "view5" && matches!(r, Rejection::Outlier { .. })),
            "{:?}",
            c.rejected
        );
        assert!((c.model.fx / 900.0 - 1.0).abs() < 0.002);
    }
}
