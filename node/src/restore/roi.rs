//! Where markers can be: regions of high local contrast on a coarse level.
//!
//! Deconvolving a whole 1440x1080 frame costs far more than the 10 ms
//! budget, and only the markers need sharp edges. A marker's black frame
//! against its white ring or the water is the strongest local contrast in
//! an underwater frame even when heavily veiled, and it survives 8x area
//! averaging (which divides the noise by 8). So on the 1/8 level — in f32
//! ([`coarse_level_f32`]), smoothed (σ 1 coarse px) and less its local mean
//! (σ 3 coarse px), so that the veil's slopes and the 8-bit level's rounding
//! rings do not count — we take the morphological gradient (3x3 max − min),
//! keep pixels above `max(k·σ_noise, rel·max_gradient, floor,
//! k_bg·median)`, grow them by hysteresis over neighbours above a fraction of
//! that, join neighbours, and return the bounding boxes of the connected
//! groups, scaled to full resolution, grown by a margin and merged where
//! they overlap.

use super::{RestoreError, RestoreParams};
use opencv::core::{Mat, Point, Rect, Scalar, Size, BORDER_CONSTANT, CV_32F, CV_32S, CV_8U};
use opencv::imgproc;
use opencv::prelude::*;

/// σ (coarse pixels) of the smoothing before the coarse gradient.
const COARSE_SMOOTH_PX: f64 = 1.0;

/// Width (coarse pixels) of the frame border ignored.
const BORDER_PX: i32 = 2;

/// σ (coarse pixels) of the local mean taken out before the gradient.
const BACKGROUND_SIGMA_PX: f64 = 3.0;

/// Coarse components smaller than this many coarse pixels are noise specks.
const MIN_COMPONENT_AREA: i32 = 8;

/// The morphological gradient of the coarse level's detail (lightly
/// smoothed, less its local mean), with a frame of [`BORDER_PX`] coarse
/// pixels cleared.
fn detail_gradient(coarse: &Mat, kernel: &Mat) -> Result<Mat, RestoreError> {
    // In f32 and lightly smoothed: the 8-bit coarse level's rounding turns a
    // smooth veil into 1-level steps, as strong as a turbid marker's edges.
    let mut coarse_f = Mat::default();
    coarse.convert_to(&mut coarse_f, CV_32F, 1.0, 0.0)?;
    let mut smooth = Mat::default();
    imgproc::gaussian_blur(
        &coarse_f,
        &mut smooth,
        Size::new(0, 0),
        COARSE_SMOOTH_PX,
        COARSE_SMOOTH_PX,
        opencv::core::BORDER_REPLICATE,
    )?;
    // Less its local mean (σ = 3 coarse px): the veil's slopes (vignetting,
    // light from above) vanish, a marker's steps stay.
    let mut background = Mat::default();
    imgproc::gaussian_blur(
        &smooth,
        &mut background,
        Size::new(0, 0),
        BACKGROUND_SIGMA_PX,
        BACKGROUND_SIGMA_PX,
        opencv::core::BORDER_REPLICATE,
    )?;
    let mut detail = Mat::default();
    opencv::core::subtract(
        &smooth,
        &background,
        &mut detail,
        &opencv::core::no_array(),
        -1,
    )?;
    let smooth = detail;
    let mut grad = Mat::default();
    imgproc::morphology_ex(
        &smooth,
        &mut grad,
        imgproc::MORPH_GRADIENT,
        kernel,
        Point::new(-1, -1),
        1,
        BORDER_CONSTANT,
        imgproc::morphology_default_border_value()?,
    )?;
    // The border of a constant-border gradient is spurious, and the
    // vignetting's fall-off curves most there: clear a frame of
    // `BORDER_PX` coarse pixels (a marker that close to the edge is
    // unreadable anyway).
    imgproc::rectangle(
        &mut grad,
        Rect::new(0, 0, coarse.cols(), coarse.rows()),
        Scalar::all(0.0),
        2 * BORDER_PX - 1,
        imgproc::LINE_8,
        0,
    )?;
    Ok(grad)
}

/// Regions of interest at full resolution (`full` is the frame size,
/// `factor` the coarse level's down-sampling, `noise_full` the frame's noise σ).
/// Empty when nothing stands out; the whole frame when the regions would
/// cover more than `roi_max_fraction` of it.
pub fn find_rois(
    coarse: &Mat,
    factor: i32,
    full: Size,
    noise_full: f64,
    margin_px: i32,
    params: &RestoreParams,
) -> Result<Vec<Rect>, RestoreError> {
    let kernel =
        imgproc::get_structuring_element(imgproc::MORPH_RECT, Size::new(3, 3), Point::new(-1, -1))?;
    let grad = detail_gradient(coarse, &kernel)?;
    let mut max_grad = 0.0;
    opencv::core::min_max_loc(
        &grad,
        None,
        Some(&mut max_grad),
        None,
        None,
        &opencv::core::no_array(),
    )?;
    // Noise of the coarse level, then of its smoothed copy.
    let noise_coarse = noise_full
        / factor as f64
        / (2.0 * std::f64::consts::PI.sqrt() * COARSE_SMOOTH_PX).max(1.0);
    let thr = (params.roi_noise_k * noise_coarse)
        .max(params.roi_rel_threshold * max_grad)
        .max(params.roi_min_gradient)
        .max(params.roi_background_k * median_f32(&grad)?);
    if max_grad <= thr {
        return Ok(Vec::new());
    }
    // Hysteresis: groups of pixels above a lower threshold, kept when they
    // hold one above `thr` (a marker's faint side joins its strong ones).
    let thr_low = thr * params.roi_hysteresis.clamp(0.0, 1.0);
    let mut mask_f = Mat::default();
    imgproc::threshold(&grad, &mut mask_f, thr_low, 255.0, imgproc::THRESH_BINARY)?;
    let mut mask = Mat::default();
    mask_f.convert_to(&mut mask, CV_8U, 1.0, 0.0)?;
    let mut joined = Mat::default();
    imgproc::dilate(
        &mask,
        &mut joined,
        &kernel,
        Point::new(-1, -1),
        1,
        BORDER_CONSTANT,
        imgproc::morphology_default_border_value()?,
    )?;
    let (mut labels, mut stats, mut centroids) = (Mat::default(), Mat::default(), Mat::default());
    let n = imgproc::connected_components_with_stats(
        &joined,
        &mut labels,
        &mut stats,
        &mut centroids,
        8,
        CV_32S,
    )?;
    let frame = Rect::new(0, 0, full.width, full.height);
    let sx = full.width as f64 / coarse.cols() as f64;
    let sy = full.height as f64 / coarse.rows() as f64;
    let mut strong = vec![false; n.max(0) as usize];
    for y in 0..grad.rows() {
        let g = grad.at_row::<f32>(y)?;
        let l = labels.at_row::<i32>(y)?;
        for (gv, &lv) in g.iter().zip(l) {
            if f64::from(*gv) > thr && lv > 0 {
                strong[lv as usize] = true;
            }
        }
    }
    let mut rects = Vec::new();
    for i in 1..n {
        let s = |c: i32| stats.at_2d::<i32>(i, c).copied();
        if !strong[i as usize] || s(imgproc::CC_STAT_AREA)? < MIN_COMPONENT_AREA {
            continue;
        }
        let (x, y) = (s(imgproc::CC_STAT_LEFT)?, s(imgproc::CC_STAT_TOP)?);
        let (w, h) = (s(imgproc::CC_STAT_WIDTH)?, s(imgproc::CC_STAT_HEIGHT)?);
        let x0 = (x as f64 * sx).floor() as i32 - margin_px;
        let y0 = (y as f64 * sy).floor() as i32 - margin_px;
        let x1 = ((x + w) as f64 * sx).ceil() as i32 + margin_px;
        let y1 = ((y + h) as f64 * sy).ceil() as i32 + margin_px;
        let r = Rect::new(x0, y0, x1 - x0, y1 - y0) & frame;
        if r.width > 0 && r.height > 0 {
            rects.push(r);
        }
    }
    let rects = merge_overlapping(rects);
    let area: i64 = rects.iter().map(|r| r.area() as i64).sum();
    if area as f64 > params.roi_max_fraction * frame.area() as f64 {
        return Ok(vec![frame]);
    }
    Ok(rects)
}

/// The frame area-averaged to `size` in f32 (via its 8-bit half level,
/// whose noise still dithers the rounding): the 8-bit 1/8 level rounds a
/// smooth veil into whole-level rings whose gradient rivals a turbid marker's.
pub fn coarse_level_f32(gray: &Mat, size: Size) -> Result<Mat, RestoreError> {
    let mut half = Mat::default();
    imgproc::resize(
        gray,
        &mut half,
        Size::new((gray.cols() / 2).max(1), (gray.rows() / 2).max(1)),
        0.0,
        0.0,
        imgproc::INTER_AREA,
    )?;
    let mut half_f = Mat::default();
    half.convert_to(&mut half_f, CV_32F, 1.0, 0.0)?;
    let mut out = Mat::default();
    imgproc::resize(&half_f, &mut out, size, 0.0, 0.0, imgproc::INTER_AREA)?;
    Ok(out)
}

/// Median of a non-negative f32 Mat (a 1/64-level histogram up to 64).
fn median_f32(m: &Mat) -> Result<f64, RestoreError> {
    const BINS: usize = 4096;
    const STEP: f64 = 1.0 / 64.0;
    let mut hist = vec![0u32; BINS];
    let mut n = 0u64;
    for y in 0..m.rows() {
        for &v in m.at_row::<f32>(y)? {
            hist[((f64::from(v) / STEP) as usize).min(BINS - 1)] += 1;
            n += 1;
        }
    }
    let mut acc = 0u64;
    for (i, &h) in hist.iter().enumerate() {
        acc += u64::from(h);
        if 2 * acc >= n {
            return Ok((i as f64 + 0.5) * STEP);
        }
    }
    Ok(0.0)
}

/// Replace overlapping rectangles by their bounding box until none overlap.
pub fn merge_overlapping(mut rects: Vec<Rect>) -> Vec<Rect> {
    loop {
        let mut merged = false;
        'outer: for i in 0..rects.len() {
            for j in i + 1..rects.len() {
                let inter = rects[i] & rects[j];
                if inter.width > 0 && inter.height > 0 {
                    rects[i] = rects[i] | rects[j];
                    rects.swap_remove(j);
                    merged = true;
                    break 'outer;
                }
            }
        }
        if !merged {
            return rects;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use opencv::core::{CV_32FC1, CV_8UC1};

    #[test]
    fn overlapping_rectangles_merge_and_disjoint_ones_stay() {
        let r = merge_overlapping(vec![
            Rect::new(0, 0, 10, 10),
            Rect::new(5, 5, 10, 10),
            Rect::new(100, 100, 5, 5),
        ]);
        assert_eq!(r.len(), 2);
        assert!(r.contains(&Rect::new(0, 0, 15, 15)));
        assert!(r.contains(&Rect::new(100, 100, 5, 5)));
    }

    #[test]
    fn finds_one_region_around_a_dark_square_and_none_in_a_flat_frame() {
        let params = RestoreParams::default();
        let mut coarse =
            Mat::new_rows_cols_with_default(135, 180, CV_8UC1, Scalar::all(150.0)).unwrap();
        let flat = find_rois(&coarse, 8, Size::new(1440, 1080), 2.0, 16, &params).unwrap();
        assert!(flat.is_empty());
        imgproc::rectangle(
            &mut coarse,
            Rect::new(60, 40, 30, 30),
            Scalar::all(40.0),
            -1,
            imgproc::LINE_8,
            0,
        )
        .unwrap();
        let rois = find_rois(&coarse, 8, Size::new(1440, 1080), 2.0, 16, &params).unwrap();
        assert_eq!(rois.len(), 1);
        let r = rois[0];
        // The square spans x 480..720, y 320..560 at full resolution.
        assert!(r.x <= 480 - 16 && r.y <= 320 - 16, "{r:?}");
        assert!(
            r.x + r.width >= 720 + 16 && r.y + r.height >= 560 + 16,
            "{r:?}"
        );
        // The smoothing and the local-mean removal spread the square's
        // response by a few coarse pixels: at most 80 px on each side.
        assert!(r.width < 400 && r.height < 400, "{r:?}");
    }

    /// A veil sloping by 40 grey levels across the frame (vignetting, light
    /// from above) raises the 3x3 gradient everywhere about as much as a
    /// faint marker does; with the local mean taken out only the marker's
    /// square is found.
    #[test]
    fn a_sloping_veil_is_no_region_but_a_faint_square_on_it_is() {
        let params = RestoreParams::default();
        let mut coarse =
            Mat::new_rows_cols_with_default(135, 180, CV_32FC1, Scalar::all(0.0)).unwrap();
        for y in 0..135 {
            for (x, v) in coarse.at_row_mut::<f32>(y).unwrap().iter_mut().enumerate() {
                *v = 110.0 + 40.0 * y as f32 / 135.0 + 10.0 * x as f32 / 180.0;
            }
        }
        let full = Size::new(1440, 1080);
        assert!(find_rois(&coarse, 8, full, 1.0, 16, &params)
            .unwrap()
            .is_empty());
        for y in 50..80 {
            for v in &mut coarse.at_row_mut::<f32>(y).unwrap()[70..100] {
                *v -= 2.0;
            }
        }
        let rois = find_rois(&coarse, 8, full, 1.0, 16, &params).unwrap();
        assert_eq!(rois.len(), 1, "{rois:?}");
        let r = rois[0];
        assert!(r.x <= 560 && r.x + r.width >= 800, "{r:?}");
        assert!(r.y <= 400 && r.y + r.height >= 640, "{r:?}");
    }
}
