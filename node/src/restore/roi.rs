//! Where markers can be: regions of high local contrast on a coarse level.
//!
//! Deconvolving a whole 1440x1080 frame costs far more than the 10 ms
//! budget, and only the markers need sharp edges. A marker's black frame
//! against its white ring or the water is the strongest local contrast in
//! an underwater frame even when heavily veiled, and it survives 8x area
//! averaging (which divides the noise by 8). So on the 1/8 level we take the
//! morphological gradient (3x3 max − min), keep pixels above
//! `max(k·σ_coarse, rel·max_gradient, 3)` grey levels, join neighbours,
//! and return the bounding boxes of the connected groups, scaled to full
//! resolution, grown by a margin and merged where they overlap.

use super::{RestoreError, RestoreParams};
use opencv::core::{Mat, Point, Rect, Scalar, Size, BORDER_CONSTANT, CV_32S};
use opencv::imgproc;
use opencv::prelude::*;

/// Coarse components smaller than this many coarse pixels are noise specks.
const MIN_COMPONENT_AREA: i32 = 8;

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
    let mut grad = Mat::default();
    imgproc::morphology_ex(
        coarse,
        &mut grad,
        imgproc::MORPH_GRADIENT,
        &kernel,
        Point::new(-1, -1),
        1,
        BORDER_CONSTANT,
        imgproc::morphology_default_border_value()?,
    )?;
    // The border of a constant-border gradient is spurious: clear a 1-px frame.
    imgproc::rectangle(
        &mut grad,
        Rect::new(0, 0, coarse.cols(), coarse.rows()),
        Scalar::all(0.0),
        1,
        imgproc::LINE_8,
        0,
    )?;
    let mut max_grad = 0.0;
    opencv::core::min_max_loc(
        &grad,
        None,
        Some(&mut max_grad),
        None,
        None,
        &opencv::core::no_array(),
    )?;
    let noise_coarse = noise_full / factor as f64;
    let thr = (params.roi_noise_k * noise_coarse)
        .max(params.roi_rel_threshold * max_grad)
        .max(3.0);
    if max_grad <= thr {
        return Ok(Vec::new());
    }
    let mut mask = Mat::default();
    imgproc::threshold(&grad, &mut mask, thr, 255.0, imgproc::THRESH_BINARY)?;
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
    let mut rects = Vec::new();
    for i in 1..n {
        let s = |c: i32| stats.at_2d::<i32>(i, c).copied();
        if s(imgproc::CC_STAT_AREA)? < MIN_COMPONENT_AREA {
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
    use opencv::core::CV_8UC1;

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
        assert!(r.width < 320 && r.height < 320, "{r:?}");
    }
}
