//! Marker pose from its corners (paper §5, "iterative PnP") with an honest
//! 6x6 covariance, keeping both planar hypotheses.
//!
//! 1. **IPPE** (`cv::solvePnPGeneric` with `SOLVEPNP_IPPE`) gives the two
//!    poses a planar target admits (the "flip" ambiguity); for non-planar
//!    points EPnP gives one.
//! 2. Each is refined by **Levenberg–Marquardt** on the reprojection error,
//!    through the camera's full distortion model ([`CameraModel::project`]),
//!    parameterized directly in shoal's perturbation convention
//!    (`t = t̂ + δt, R = Exp(δθ)·R̂`, see `proto::geometry`), so the
//!    Jacobian at the optimum gives the covariance in that convention without
//!    any conversion from OpenCV's rvec parameterization.
//!    With a flat port ([`estimate_pose_with`]) the residual is through the
//!    port's refraction ([`FlatPort::project`]) and the starts come from the
//!    in-water directions of the corners' rays (the paraxial in-water
//!    pinhole: the lens's focal length times n_water).
//! 3. **Covariance** `Σ = σ² (JᵀJ)⁻¹` with the corner noise σ given, or
//!    estimated from the residuals (`σ̂² = SSR / (2n − 6)`).
//! 4. When the corners' errors are correlated (one whole-pattern fit gave
//!    them all), [`corner_covariance`] gives the pose error their stated
//!    covariance causes; the node adds it to both hypotheses.
//! 5. When the camera's calibration is uncertain ([`CalibrationSigma`]),
//!    [`calibration_covariance`] gives the pose error an error of the
//!    intrinsics causes (systematic across the corners, so the residuals do
//!    not show it); the node adds it to both hypotheses.
//!
//! Both hypotheses are returned, best (lowest RMS) first: the fusion service
//! resolves the flip with other observations.

use nalgebra::{DMatrix, DVector, Matrix6, Point3, Vector6};
use opencv::core::{Mat, Vector};
use opencv::prelude::*;
use shoal_proto::camera::{CalibrationSigma, CameraModel, Distortion, FlatPort};
use shoal_proto::geometry::{difference, perturb, Cov6, Pose};

/// Errors of pose estimation.
#[derive(Debug, thiserror::Error)]
pub enum PoseError {
    #[error("need at least {required} corners, got {actual}")]
    TooFewPoints { required: usize, actual: usize },
    #[error("{object} object points but {image} image points")]
    CountMismatch { object: usize, image: usize },
    #[error("a corner coordinate is not finite")]
    NonFinite,
    #[error("camera model is unusable: {0}")]
    Camera(String),
    #[error("corner noise sigma must be positive and finite, got {0}")]
    BadSigma(f64),
    #[error("no pose found (degenerate configuration)")]
    NoSolution,
    #[error("OpenCV: {0}")]
    OpenCv(#[from] opencv::Error),
}

/// One pose hypothesis.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hypothesis {
    pub camera_from_marker: Pose,
    /// Over `(δt, δθ)` in the camera frame, shoal's convention.
    pub covariance: Cov6,
    /// Root-mean-square reprojection error over all coordinates (px).
    pub rms_px: f64,
}

/// The best hypothesis and, for planar targets, the flipped alternative.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PoseSolution {
    pub best: Hypothesis,
    pub alternative: Option<Hypothesis>,
}

/// Smallest corner noise used when σ is estimated from residuals (px): a
/// perfect fit must not claim infinite precision.
const MIN_ESTIMATED_SIGMA_PX: f64 = 0.05;

/// Estimate `camera_from_marker` from ≥ 4 correspondences, `cam` taken as
/// the camera's in-water calibration (a pinhole with its lens model).
pub fn estimate_pose(
    cam: &CameraModel,
    object_pts: &[Point3<f64>],
    image_pts: &[[f64; 2]],
    corner_sigma_px: Option<f64>,
) -> Result<PoseSolution, PoseError> {
    estimate_pose_with(cam, None, object_pts, image_pts, corner_sigma_px)
}

/// The camera a PnP projects through: the lens alone, or the lens behind a
/// flat port.
#[derive(Debug, Clone, Copy)]
struct Lens<'a> {
    cam: &'a CameraModel,
    port: Option<&'a FlatPort>,
}

impl Lens<'_> {
    #[inline]
    fn project(&self, p: &Point3<f64>) -> Option<nalgebra::Point2<f64>> {
        shoal_proto::port::project(self.cam, self.port, p)
    }
}

/// [`estimate_pose`] through a flat port when `port` is given: `cam` is then
/// the lens's in-air calibration and every residual is through the port's
/// refraction ([`FlatPort::project`]).
pub fn estimate_pose_with(
    cam: &CameraModel,
    port: Option<&FlatPort>,
    object_pts: &[Point3<f64>],
    image_pts: &[[f64; 2]],
    corner_sigma_px: Option<f64>,
) -> Result<PoseSolution, PoseError> {
    if object_pts.len() != image_pts.len() {
        return Err(PoseError::CountMismatch {
            object: object_pts.len(),
            image: image_pts.len(),
        });
    }
    if object_pts.len() < 4 {
        return Err(PoseError::TooFewPoints {
            required: 4,
            actual: object_pts.len(),
        });
    }
    if !object_pts
        .iter()
        .all(|p| p.coords.iter().all(|v| v.is_finite()))
        || !image_pts
            .iter()
            .all(|p| p[0].is_finite() && p[1].is_finite())
    {
        return Err(PoseError::NonFinite);
    }
    // Per detection: the lens was checked where the camera entered (fleet
    // file, calibration, command line, wire).
    if let Some(problem) = cam.parameter_problem() {
        return Err(PoseError::Camera(problem));
    }
    if let Some(problem) = port.and_then(FlatPort::problem) {
        return Err(PoseError::Camera(problem));
    }
    if let Some(s) = corner_sigma_px {
        if !(s.is_finite() && s > 0.0) {
            return Err(PoseError::BadSigma(s));
        }
    }
    let lens = Lens { cam, port };
    let mut hyps: Vec<Hypothesis> = Vec::new();
    for init in initial_poses(cam, port, object_pts, image_pts)? {
        let Some(pose) = refine_lm(lens, object_pts, image_pts, init) else {
            continue;
        };
        if hyps
            .iter()
            .any(|h| difference(&h.camera_from_marker, &pose).norm() < 1e-6)
        {
            continue;
        }
        if let Some(h) = hypothesis(lens, object_pts, image_pts, pose, corner_sigma_px) {
            hyps.push(h);
        }
    }
    hyps.sort_by(|a, b| a.rms_px.total_cmp(&b.rms_px));
    let mut it = hyps.into_iter();
    let best = it.next().ok_or(PoseError::NoSolution)?;
    Ok(PoseSolution {
        best,
        alternative: it.next(),
    })
}

/// IPPE's two planar solutions (or EPnP's one for non-planar points). With
/// a port, from the corners' in-water ray directions (their origins on the
/// port, a centimetre or two off the lens centre, are left to the refinement).
fn initial_poses(
    cam: &CameraModel,
    port: Option<&FlatPort>,
    obj: &[Point3<f64>],
    img: &[[f64; 2]],
) -> Result<Vec<Pose>, PoseError> {
    use opencv::calib3d::{self, SolvePnPMethod};
    use opencv::core::{Point2d, Point3d};
    let planar = obj.iter().all(|p| p.z.abs() < 1e-12);
    let o: Vector<Point3d> = obj.iter().map(|p| Point3d::new(p.x, p.y, p.z)).collect();
    // OpenCV starts from the ideal pinhole image (the lens taken out by shoal's
    // model, whichever it is); the refinement below uses the full model.
    let i: Vector<Point2d> = img
        .iter()
        .map(|p| {
            let (mut x, mut y) = cam.ray(p[0], p[1]);
            if let Some(port) = port {
                (_, (x, y)) = port.refract(x, y);
            }
            Point2d::new(cam.fx * x + cam.cx, cam.fy * y + cam.cy)
        })
        .collect();
    let k = Mat::from_slice_2d(&[
        [cam.fx, 0.0, cam.cx],
        [0.0, cam.fy, cam.cy],
        [0.0, 0.0, 1.0],
    ])?;
    let d = Mat::default();
    let mut rvecs: Vector<Mat> = Vector::new();
    let mut tvecs: Vector<Mat> = Vector::new();
    let method = if planar {
        SolvePnPMethod::SOLVEPNP_IPPE
    } else {
        SolvePnPMethod::SOLVEPNP_EPNP
    };
    let mut reproj = Mat::default();
    let n = calib3d::solve_pnp_generic(
        &o,
        &i,
        &k,
        &d,
        &mut rvecs,
        &mut tvecs,
        false,
        method,
        &Mat::default(),
        &Mat::default(),
        &mut reproj,
    )
    .unwrap_or(0);
    let mut out = Vec::new();
    for s in 0..n.max(0) as usize {
        let (r, t) = (rvecs.get(s)?, tvecs.get(s)?);
        let rv = [*r.at::<f64>(0)?, *r.at::<f64>(1)?, *r.at::<f64>(2)?];
        let tv = [*t.at::<f64>(0)?, *t.at::<f64>(1)?, *t.at::<f64>(2)?];
        if rv.iter().chain(tv.iter()).all(|v| v.is_finite()) {
            out.push(Pose::from_parts(
                nalgebra::Translation3::new(tv[0], tv[1], tv[2]),
                nalgebra::UnitQuaternion::from_scaled_axis(nalgebra::Vector3::new(
                    rv[0], rv[1], rv[2],
                )),
            ));
        }
    }
    Ok(out)
}

/// Residuals `project(pose · X) − u` (2n), `None` if a point is behind the camera.
fn residuals(
    lens: Lens<'_>,
    obj: &[Point3<f64>],
    img: &[[f64; 2]],
    pose: &Pose,
) -> Option<DVector<f64>> {
    let mut r = DVector::zeros(2 * obj.len());
    for (k, (p, u)) in obj.iter().zip(img).enumerate() {
        let q = lens.project(&(pose * p))?;
        r[2 * k] = q.x - u[0];
        r[2 * k + 1] = q.y - u[1];
    }
    Some(r)
}

/// Jacobian of the residuals w.r.t. the perturbation ξ = (δt, δθ) (central differences).
fn jacobian(
    lens: Lens<'_>,
    obj: &[Point3<f64>],
    img: &[[f64; 2]],
    pose: &Pose,
) -> Option<DMatrix<f64>> {
    let mut j = DMatrix::zeros(2 * obj.len(), 6);
    let scale = pose.translation.vector.norm().max(1e-3);
    for c in 0..6 {
        // Steps relative to the problem's scale: 1e-6 of the distance, 1e-6 rad.
        let h = if c < 3 { 1e-6 * scale } else { 1e-6 };
        let mut d = Vector6::zeros();
        d[c] = h;
        let rp = residuals(lens, obj, img, &perturb(pose, &d))?;
        d[c] = -h;
        let rm = residuals(lens, obj, img, &perturb(pose, &d))?;
        j.set_column(c, &((rp - rm) / (2.0 * h)));
    }
    Some(j)
}

/// Levenberg–Marquardt on the reprojection error (our own, so that the
/// parameterization is shoal's perturbation and the full distortion is used).
fn refine_lm(lens: Lens<'_>, obj: &[Point3<f64>], img: &[[f64; 2]], init: Pose) -> Option<Pose> {
    let mut pose = init;
    let mut r = residuals(lens, obj, img, &pose)?;
    let mut cost = r.norm_squared();
    let mut lambda = 1e-3;
    for _ in 0..50 {
        let j = jacobian(lens, obj, img, &pose)?;
        let jtj = j.transpose() * &j;
        let g = j.transpose() * &r;
        let mut improved = false;
        for _ in 0..10 {
            let mut a = jtj.clone();
            for i in 0..6 {
                a[(i, i)] += lambda * jtj[(i, i)].max(1e-12);
            }
            let Some(step) = a.lu().solve(&(-&g)) else {
                lambda *= 10.0;
                continue;
            };
            let xi = Vector6::from_iterator(step.iter().copied());
            let cand = perturb(&pose, &xi);
            if let Some(rc) = residuals(lens, obj, img, &cand) {
                let c = rc.norm_squared();
                if c < cost {
                    let rel = (cost - c) / cost.max(1e-300);
                    pose = cand;
                    r = rc;
                    cost = c;
                    lambda = (lambda * 0.3).max(1e-9);
                    improved = true;
                    // Converged: the cost no longer changes at a level that matters (1e-9 relative).
                    if rel < 1e-9 || xi.norm() < 1e-10 {
                        return Some(pose);
                    }
                    break;
                }
            }
            lambda *= 10.0;
        }
        if !improved {
            break;
        }
    }
    Some(pose)
}

fn hypothesis(
    lens: Lens<'_>,
    obj: &[Point3<f64>],
    img: &[[f64; 2]],
    pose: Pose,
    sigma: Option<f64>,
) -> Option<Hypothesis> {
    let r = residuals(lens, obj, img, &pose)?;
    let n = r.len();
    let ssr = r.norm_squared();
    let rms_px = (ssr / n as f64).sqrt();
    let sigma = match sigma {
        Some(s) => s,
        None if n > 6 => (ssr / (n - 6) as f64).sqrt().max(MIN_ESTIMATED_SIGMA_PX),
        None => rms_px.max(MIN_ESTIMATED_SIGMA_PX),
    };
    let j = jacobian(lens, obj, img, &pose)?;
    let jtj: Matrix6<f64> = Matrix6::from_iterator((j.transpose() * &j).iter().copied());
    let inv = jtj.try_inverse()?;
    let mut covariance = inv * (sigma * sigma);
    covariance = 0.5 * (covariance + covariance.transpose());
    covariance
        .iter()
        .all(|v| v.is_finite())
        .then_some(Hypothesis {
            camera_from_marker: pose,
            covariance,
            rms_px,
        })
}

/// What [`linearized`] gives.
struct Linearized {
    img: Vec<[f64; 2]>,
    j: DMatrix<f64>,
    inv: Matrix6<f64>,
}

/// The least-squares problem linearized at `pose`: the corners where `lens`
/// projects `object_pts` (so the residuals are zero there and only their
/// derivatives matter), the residuals' Jacobian `J` in the pose, and
/// `(JᵀJ)⁻¹`. `None` if a corner is behind the camera or `JᵀJ` is singular.
fn linearized(lens: Lens<'_>, object_pts: &[Point3<f64>], pose: &Pose) -> Option<Linearized> {
    let img: Vec<[f64; 2]> = object_pts
        .iter()
        .map(|p| lens.project(&(pose * p)).map(|q| [q.x, q.y]))
        .collect::<Option<_>>()?;
    let j = jacobian(lens, object_pts, &img, pose)?;
    let jtj: Matrix6<f64> = Matrix6::from_iterator((j.transpose() * &j).iter().copied());
    let inv = jtj.try_inverse()?;
    Some(Linearized { img, j, inv })
}

/// Why a hypothesis' stated covariance ([`stated_covariance`]) could not be formed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum StatedCovarianceError {
    #[error("no calibration covariance (degenerate geometry)")]
    Calibration,
    #[error("no corner covariance ({corners} corners, a {rows}x{cols} covariance)")]
    Corners {
        corners: usize,
        rows: usize,
        cols: usize,
    },
}

/// The covariance the node states for hypothesis `h`: PnP's own (from its
/// residuals), plus what an uncertain calibration adds ([`calibration_covariance`],
/// when the camera states its `calibration_sigma`) and what correlated
/// corner errors add ([`corner_covariance`], when the detector gave the
/// corners' covariance). Both are systematic over the corners, so the
/// residuals cannot show them. `cam`, `port` and `object_pts` as in
/// [`estimate_pose_with`].
pub fn stated_covariance(
    cam: &CameraModel,
    port: Option<&FlatPort>,
    object_pts: &[Point3<f64>],
    h: &Hypothesis,
    calibration_sigma: Option<&CalibrationSigma>,
    corners_cov: Option<&DMatrix<f64>>,
) -> Result<Cov6, StatedCovarianceError> {
    let pose = &h.camera_from_marker;
    let calibration = match calibration_sigma {
        None => Cov6::zeros(),
        Some(sigma) => calibration_covariance(cam, port, object_pts, pose, sigma)
            .ok_or(StatedCovarianceError::Calibration)?,
    };
    let corners = match corners_cov {
        None => Cov6::zeros(),
        Some(cov) => corner_covariance(cam, port, object_pts, pose, cov).ok_or(
            StatedCovarianceError::Corners {
                corners: object_pts.len(),
                rows: cov.nrows(),
                cols: cov.ncols(),
            },
        )?,
    };
    Ok(h.covariance + calibration + corners)
}

/// The pose covariance that correlated corner errors add at `pose`: the
/// least-squares pose moves by `−(JᵀJ)⁻¹ Jᵀ δu` for an error `δu` of the
/// image corners, so a covariance `Σ_u` of the corners (px², x then y of
/// each, `2n`x`2n`) gives the pose `A Σ_u Aᵀ`, `A = (JᵀJ)⁻¹ Jᵀ`. For the
/// corners of one whole-pattern fit ([`crate::detect::Detection::corner_covariance`]):
/// they move together, so the residuals stay small while the pose moves.
/// `cam` and `port` as in [`estimate_pose_with`]. `None` if the sizes do not
/// match, `Σ_u` is not finite or the geometry is degenerate.
pub fn corner_covariance(
    cam: &CameraModel,
    port: Option<&FlatPort>,
    object_pts: &[Point3<f64>],
    pose: &Pose,
    corners_cov: &DMatrix<f64>,
) -> Option<Cov6> {
    let n = 2 * object_pts.len();
    if object_pts.len() < 3
        || corners_cov.shape() != (n, n)
        || !corners_cov.iter().all(|v| v.is_finite())
    {
        return None;
    }
    let lens = Lens { cam, port };
    let Linearized { j, inv, .. } = linearized(lens, object_pts, pose)?;
    let jt = j.transpose();
    let middle = &jt * corners_cov * &j;
    let c = inv * Matrix6::from_iterator(middle.iter().copied()) * inv.transpose();
    let c = 0.5 * (c + c.transpose());
    c.iter().all(|v| v.is_finite()).then_some(c)
}

/// The pose covariance an uncertain calibration adds at `pose`: to first
/// order, an error `δk` of the intrinsics (fx, fy relative; cx, cy; k1)
/// moves the least-squares pose by `−(JᵀJ)⁻¹ Jᵀ J_k δk`, where `J` is the
/// residuals' Jacobian in the pose and `J_k` in the intrinsics; with the
/// intrinsics' covariance `Σ_k` (diagonal, from `sigma`) the pose's is
/// `A Σ_k Aᵀ`, `A = (JᵀJ)⁻¹ Jᵀ J_k`. `cam` and `port` as in
/// [`estimate_pose_with`]. `None` if the geometry is degenerate (a corner
/// behind the camera, `JᵀJ` singular) or `sigma` is invalid.
pub fn calibration_covariance(
    cam: &CameraModel,
    port: Option<&FlatPort>,
    object_pts: &[Point3<f64>],
    pose: &Pose,
    sigma: &CalibrationSigma,
) -> Option<Cov6> {
    if sigma.problem().is_some() || object_pts.len() < 3 {
        return None;
    }
    let lens = Lens { cam, port };
    let Linearized { img, j, inv } = linearized(lens, object_pts, pose)?;
    // Intrinsics: fx and fy by a relative step, cx and cy in px, k1.
    let terms: [(f64, f64); 5] = [
        (1e-6, sigma.focal_rel),
        (1e-6, sigma.focal_rel),
        (1e-3, sigma.principal_px),
        (1e-3, sigma.principal_px),
        (1e-6, sigma.k1),
    ];
    let moved = |c: usize, h: f64| -> CameraModel {
        let mut m = *cam;
        match c {
            0 => m.fx *= 1.0 + h,
            1 => m.fy *= 1.0 + h,
            2 => m.cx += h,
            3 => m.cy += h,
            _ => match &mut m.distortion {
                Distortion::PlumbBob(k) => k[0] += h,
                Distortion::Rational(k) => k[0] += h,
                Distortion::Equidistant(k) => k[0] += h,
            },
        }
        m
    };
    let mut jk = DMatrix::zeros(2 * object_pts.len(), 5);
    for (c, (h, s)) in terms.iter().enumerate() {
        if *s == 0.0 {
            continue;
        }
        let (plus, minus) = (moved(c, *h), moved(c, -*h));
        let rp = residuals(Lens { cam: &plus, port }, object_pts, &img, pose)?;
        let rm = residuals(Lens { cam: &minus, port }, object_pts, &img, pose)?;
        // Scaled by σ: the column is the residuals' change for a 1-σ error.
        jk.set_column(c, &((rp - rm) * (*s / (2.0 * h))));
    }
    let a =
        inv * Matrix6::from_iterator(
            (j.transpose() * jk.clone() * jk.transpose() * &j)
                .iter()
                .copied(),
        ) * inv;
    let cov = 0.5 * (a + a.transpose());
    cov.iter().all(|v| v.is_finite()).then_some(cov)
}
