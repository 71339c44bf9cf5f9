//! Baseline detectors behind [`crate::detect::MarkerDetector`]: OpenCV's ArUco
//! detector and AprilTag 3 (Debian's libapriltag).

pub mod apriltag_ffi;

use crate::detect::{CornerChoice, DetectError, Detection, MarkerDetector};
use crate::mat::GrayView;
use apriltag_ffi::{Family, FamilyHandle};
use opencv::aruco;
use opencv::core::{Mat, Point2f, Ptr, Vector};
use opencv::prelude::*;
use shoal_proto::marker::CodeSet;

/// OpenCV's predefined dictionary for a code set (`shoal` reads its code
/// square as ArUco 4x4_50: the enhanced marker's white ring is its quiet
/// zone; the AprilTag families are OpenCV's `DICT_APRILTAG_*`, the same IDs).
pub fn opencv_dictionary(codes: CodeSet) -> Option<aruco::PREDEFINED_DICTIONARY_NAME> {
    use aruco::PREDEFINED_DICTIONARY_NAME as D;
    use CodeSet::*;
    Some(match codes {
        Shoal | Aruco4x4_50 => D::DICT_4X4_50,
        Aruco4x4_100 => D::DICT_4X4_100,
        Aruco4x4_250 => D::DICT_4X4_250,
        Aruco4x4_1000 => D::DICT_4X4_1000,
        Aruco5x5_50 => D::DICT_5X5_50,
        Aruco5x5_100 => D::DICT_5X5_100,
        Aruco5x5_250 => D::DICT_5X5_250,
        Aruco5x5_1000 => D::DICT_5X5_1000,
        Aruco6x6_50 => D::DICT_6X6_50,
        Aruco6x6_100 => D::DICT_6X6_100,
        Aruco6x6_250 => D::DICT_6X6_250,
        Aruco6x6_1000 => D::DICT_6X6_1000,
        AprilTag16h5 => D::DICT_APRILTAG_16h5,
        AprilTag36h11 => D::DICT_APRILTAG_36h11,
    })
}

/// OpenCV 4.6's ArUco detector (`cv::aruco::detectMarkers`, default
/// parameters with `CORNER_REFINE_SUBPIX`). Corners: TL, TR, BR, BL of the
/// upright marker, i.e. [`CodeSet::corners_3d`] order (for `shoal`: the code
/// square, corner IDs 8..12).
pub struct OpenCvAruco {
    codes: CodeSet,
    dict: Ptr<aruco::Dictionary>,
    params: Ptr<aruco::DetectorParameters>,
}

impl OpenCvAruco {
    pub fn new(codes: CodeSet) -> Result<Self, DetectError> {
        let name = opencv_dictionary(codes).ok_or(DetectError::Unsupported {
            detector: "opencv-aruco",
            set: codes.name(),
        })?;
        let dict = aruco::get_predefined_dictionary(name)?;
        let mut params = aruco::DetectorParameters::create()?;
        params.set_corner_refinement_method(aruco::CORNER_REFINE_SUBPIX);
        Ok(Self {
            codes,
            dict,
            params,
        })
    }

    /// The detector parameters, for tuning.
    pub fn parameters_mut(&mut self) -> &mut Ptr<aruco::DetectorParameters> {
        &mut self.params
    }
}

impl MarkerDetector for OpenCvAruco {
    fn name(&self) -> &str {
        "opencv-aruco"
    }

    fn detect(&mut self, gray: &Mat) -> Result<Vec<Detection>, DetectError> {
        GrayView::new(gray)?;
        let mut corners: Vector<Vector<Point2f>> = Vector::new();
        let mut ids: Vector<i32> = Vector::new();
        let mut rejected: Vector<Vector<Point2f>> = Vector::new();
        aruco::detect_markers(
            gray,
            &self.dict,
            &mut corners,
            &mut ids,
            &self.params,
            &mut rejected,
        )?;
        let first_id: u8 = if self.codes == CodeSet::Shoal { 8 } else { 0 };
        let mut out = Vec::with_capacity(ids.len());
        for (c, id) in corners.iter().zip(ids.iter()) {
            let pts: Vec<[f64; 2]> = c.iter().map(|p| [f64::from(p.x), f64::from(p.y)]).collect();
            if pts.len() != 4 || id < 0 {
                continue;
            }
            let side: f64 = (0..4)
                .map(|i| crate::detect::geom::dist(pts[i], pts[(i + 1) % 4]))
                .sum::<f64>()
                / 4.0;
            out.push(Detection {
                codes: self.codes,
                id: id as u32,
                corners_px: pts,
                corner_ids: (first_id..first_id + 4).collect(),
                corner_covariance: None,
                hamming: 0,
                module_px: side / (self.codes.data_side() + 2) as f64,
                corner_fit: CornerChoice::baseline(),
            });
        }
        Ok(out)
    }
}

/// AprilTag 3 (Debian's libapriltag) for `apriltag16h5` / `apriltag36h11`,
/// library defaults (decimate 2, edge refinement on, 2 corrected bits), one thread.
pub struct AprilTag {
    codes: CodeSet,
    td: *mut apriltag_ffi::apriltag_detector_t,
    // Kept alive for the detector, which points at it.
    _family: FamilyHandle,
    buf: Vec<u8>,
}

// SAFETY: the detector and family are owned exclusively by this value and
// only used through `&mut self`, so moving it to another thread is sound.
#[allow(unsafe_code)]
unsafe impl Send for AprilTag {}

impl AprilTag {
    #[allow(unsafe_code)] // FFI to libapriltag.
    pub fn new(codes: CodeSet) -> Result<Self, DetectError> {
        let fam = match codes {
            CodeSet::AprilTag16h5 => Family::Tag16h5,
            CodeSet::AprilTag36h11 => Family::Tag36h11,
            other => {
                return Err(DetectError::Unsupported {
                    detector: "apriltag3",
                    set: other.name(),
                })
            }
        };
        let family = FamilyHandle::new(fam)
            .ok_or_else(|| DetectError::AprilTag("family create failed".into()))?;
        // SAFETY: create returns a valid detector or null (checked); add_family stores the
        // family pointer, which outlives the detector (dropped after it, see Drop).
        let td = unsafe {
            let td = apriltag_ffi::apriltag_detector_create();
            if td.is_null() {
                return Err(DetectError::AprilTag("detector create failed".into()));
            }
            (*td).nthreads = 1;
            apriltag_ffi::apriltag_detector_add_family_bits(
                td,
                family.ptr,
                apriltag_ffi::DEFAULT_BITS_CORRECTED as i32,
            );
            td
        };
        Ok(Self {
            codes,
            td,
            _family: family,
            buf: Vec::new(),
        })
    }
}

impl AprilTag {
    /// libapriltag's `quad_decimate`: 2 (the library default) finds quads on
    /// a half-resolution image; 1 at full resolution, which reads smaller tags
    /// at several times the cost. Values below 1 are taken as 1.
    #[allow(unsafe_code)] // FFI to libapriltag.
    pub fn set_quad_decimate(&mut self, decimate: f32) {
        // SAFETY: `td` is the valid detector created in `new` and destroyed only in Drop.
        unsafe { (*self.td).quad_decimate = decimate.max(1.0) }
    }
}

impl Drop for AprilTag {
    #[allow(unsafe_code)] // FFI to libapriltag.
    fn drop(&mut self) {
        // SAFETY: td came from apriltag_detector_create and is destroyed once, before the family.
        unsafe { apriltag_ffi::apriltag_detector_destroy(self.td) }
    }
}

impl MarkerDetector for AprilTag {
    fn name(&self) -> &str {
        "apriltag3"
    }

    #[allow(unsafe_code)] // FFI to libapriltag.
    fn detect(&mut self, gray: &Mat) -> Result<Vec<Detection>, DetectError> {
        let view = GrayView::new(gray)?;
        self.buf.clear();
        for y in 0..view.height {
            self.buf.extend_from_slice(view.row(y));
        }
        let mut im = apriltag_ffi::image_u8_t {
            width: view.width as i32,
            height: view.height as i32,
            stride: view.width as i32,
            buf: self.buf.as_mut_ptr(),
        };
        let mut out = Vec::new();
        // SAFETY: `im` points at our buffer for the duration of the call; the
        // returned zarray holds `apriltag_detection_t*` elements, read then destroyed.
        unsafe {
            let dets = apriltag_ffi::apriltag_detector_detect(self.td, &mut im);
            if dets.is_null() {
                return Err(DetectError::AprilTag("detect returned null".into()));
            }
            let n = (*dets).size.max(0) as usize;
            let arr = (*dets).data as *const *const apriltag_ffi::apriltag_detection_t;
            for i in 0..n {
                let d = &**arr.add(i);
                // libapriltag wraps the corners counter-clockwise in the image
                // starting at the upright tag's bottom-left: BL, BR, TR, TL.
                let p = d.p;
                let pts = vec![p[3], p[2], p[1], p[0]];
                let side: f64 = (0..4)
                    .map(|k| crate::detect::geom::dist(pts[k], pts[(k + 1) % 4]))
                    .sum::<f64>()
                    / 4.0;
                out.push(Detection {
                    codes: self.codes,
                    id: d.id as u32,
                    corners_px: pts,
                    corner_ids: vec![0, 1, 2, 3],
                    corner_covariance: None,
                    hamming: d.hamming as u32,
                    module_px: side / self.codes.modules() as f64,
                    corner_fit: CornerChoice::baseline(),
                });
            }
            apriltag_ffi::apriltag_detections_destroy(dets);
        }
        Ok(out)
    }
}
