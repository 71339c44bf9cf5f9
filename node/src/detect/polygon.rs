//! A closed contour's polygon as `cv::approxPolyDP(contour, eps, true)`
//! gives it for integer points: the same vertices in the same order (test
//! `the_polygon_is_opencvs_to_the_point`), without a call into OpenCV and a
//! copy of the contour per call. The quad search asks it of every contour
//! long enough to be a marker (~125 on a 640x480 tank frame).
//!
//! The method is Ramer–Douglas–Peucker as OpenCV runs it on a closed curve:
//! two roughly farthest points (three rounds of "farthest from the last
//! one", from the first point), each half split at its point farthest
//! from its chord while that is more than `eps` off, then one pass that
//! drops a vertex lying within `eps / √2` of the line through its
//! neighbours, between them, on a side neither horizontal nor vertical.
//!
//! Also `cv::isContourConvex` ([`is_convex`]) and `cv::boundingRect`
//! ([`bounding_box`]) of integer points, which the quad search asks of
//! every such contour (~1 900 a frame through the realistic camera's
//! noise), each an allocation and a call into OpenCV before.

use opencv::core::{Point, Rect};

/// Whether the closed polygon `pts` is convex as `cv::isContourConvex`
/// decides it: every turn between consecutive sides the same way, none
/// straight (a repeated point or three in a line is not convex); no point
/// is (nor are one or two points: their turns are straight).
pub fn is_convex(pts: &[Point]) -> bool {
    let n = pts.len();
    if n == 0 {
        return false;
    }
    let (mut prev, mut cur) = (pts[(2 * n - 2) % n], pts[n - 1]);
    let (mut dx0, mut dy0) = (cur.x - prev.x, cur.y - prev.y);
    let mut orientation = 0u8;
    for &p in pts {
        (prev, cur) = (cur, p);
        let (dx, dy) = (cur.x - prev.x, cur.y - prev.y);
        let (dxdy0, dydx0) = (
            i64::from(dx) * i64::from(dy0),
            i64::from(dy) * i64::from(dx0),
        );
        orientation |= match dydx0.cmp(&dxdy0) {
            std::cmp::Ordering::Greater => 1,
            std::cmp::Ordering::Less => 2,
            std::cmp::Ordering::Equal => 3,
        };
        if orientation == 3 {
            return false;
        }
        (dx0, dy0) = (dx, dy);
    }
    true
}

/// The smallest upright rectangle holding every point of `pts`, as
/// `cv::boundingRect` gives it (width and height count pixels: one point
/// is 1x1; none is empty).
pub fn bounding_box(pts: &[Point]) -> Rect {
    let Some(first) = pts.first() else {
        return Rect::new(0, 0, 0, 0);
    };
    let (mut x0, mut y0, mut x1, mut y1) = (first.x, first.y, first.x, first.y);
    for p in &pts[1..] {
        (x0, x1) = (x0.min(p.x), x1.max(p.x));
        (y0, y1) = (y0.min(p.y), y1.max(p.y));
    }
    Rect::new(x0, y0, x1 - x0 + 1, y1 - y0 + 1)
}

/// The polygon of the closed contour `pts` at tolerance `eps` (pixels),
/// written to `out` (cleared first).
pub fn approx_closed(pts: &[Point], eps: f64, out: &mut Vec<Point>) {
    out.clear();
    let count = pts.len();
    if count == 0 {
        return;
    }
    let eps2 = eps * eps;
    let next = |i: usize| if i + 1 >= count { 0 } else { i + 1 };
    let diff = |a: Point, b: Point| (f64::from(a.x - b.x), f64::from(a.y - b.y));

    // 1. Two roughly farthest points: from the first point, the one
    //    farthest from it, then farthest from that, then from that.
    let (mut start, mut far) = (0usize, 0usize);
    let mut within_eps = false;
    for _ in 0..3 {
        start = (start + far) % count;
        let a = pts[start];
        let mut max_dist = 0.0;
        let mut pos = next(start);
        for j in 1..count {
            let (dx, dy) = diff(pts[pos], a);
            let d = dx * dx + dy * dy;
            if d > max_dist {
                max_dist = d;
                far = j;
            }
            pos = next(pos);
        }
        within_eps = max_dist <= eps2;
    }
    // Ranges `(from, to)` of indices, wrapping past the end.
    let mut stack: Vec<(usize, usize)> = Vec::new();
    if within_eps {
        out.push(pts[start]);
    } else {
        let far = (far + start) % count;
        stack.push((far, start));
        stack.push((start, far));
    }

    // 2. Split each range at its point farthest from its chord.
    let mut split = 0usize;
    while let Some((from, to)) = stack.pop() {
        let a = pts[from];
        let mut pos = next(from);
        let within = if pos == to {
            true
        } else {
            let (dx, dy) = diff(pts[to], a);
            let mut max_dist = 0.0;
            while pos != to {
                let (px, py) = diff(pts[pos], a);
                let d = (py * dx - px * dy).abs();
                if d > max_dist {
                    max_dist = d;
                    split = pos;
                }
                pos = next(pos);
            }
            max_dist * max_dist <= eps2 * (dx * dx + dy * dy)
        };
        if within {
            out.push(a);
        } else {
            stack.push((split, to));
            stack.push((from, split));
        }
    }

    // 3. Drop vertices within eps/√2 of their neighbours' line, between
    //    them, where that line is neither horizontal nor vertical; in
    //    place, reading on as the writes overtake (as OpenCV does).
    let count = out.len();
    let mut new_count = count;
    let wrap = |i: usize| if i + 1 >= count { 0 } else { i + 1 };
    let mut pos = count - 1;
    let mut start = out[pos];
    pos = wrap(pos);
    let mut wpos = pos;
    let mut pt = out[pos];
    pos = wrap(pos);
    let mut i = 0;
    while i < count && new_count > 2 {
        let end = out[pos];
        pos = wrap(pos);
        let (dx, dy) = diff(end, start);
        let (px, py) = diff(pt, start);
        let dist = (px * dy - py * dx).abs();
        let inner = i64::from(pt.x - start.x) * i64::from(end.x - pt.x)
            + i64::from(pt.y - start.y) * i64::from(end.y - pt.y);
        if dist * dist <= 0.5 * eps2 * (dx * dx + dy * dy) && dx != 0.0 && dy != 0.0 && inner >= 0 {
            new_count -= 1;
            out[wpos] = end;
            start = end;
            wpos = wrap(wpos);
            pt = out[pos];
            pos = wrap(pos);
            i += 2;
            continue;
        }
        out[wpos] = pt;
        start = pt;
        wpos = wrap(wpos);
        pt = end;
        i += 1;
    }
    out.truncate(new_count);
}

#[cfg(test)]
mod tests {
    use super::*;
    use opencv::core::Vector;
    use opencv::imgproc;
    use rand::{Rng, SeedableRng};

    fn opencvs(pts: &[Point], eps: f64) -> Vec<(i32, i32)> {
        let mut approx: Vector<Point> = Vector::new();
        imgproc::approx_poly_dp(&Vector::<Point>::from_slice(pts), &mut approx, eps, true).unwrap();
        approx.iter().map(|p| (p.x, p.y)).collect()
    }

    fn ours(pts: &[Point], eps: f64) -> Vec<(i32, i32)> {
        let mut out = Vec::new();
        approx_closed(pts, eps, &mut out);
        out.iter().map(|p| (p.x, p.y)).collect()
    }

    #[test]
    fn the_polygon_is_opencvs_to_the_point() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(11);
        let mut contours = super::super::contours::Contours::new();
        let mut compared = 0usize;
        let mut quads = 0usize;
        // Real contours: every outline of thresholded smoothed noise and of
        // turned rectangles, at the quad search's tolerance and others.
        for case in 0..60 {
            let (w, h) = (rng.gen_range(20..160), rng.gen_range(20..120));
            let mut m = opencv::core::Mat::new_rows_cols_with_default(
                h,
                w,
                opencv::core::CV_8UC1,
                opencv::core::Scalar::all(0.0),
            )
            .unwrap();
            for y in 0..h {
                for x in 0..w {
                    *opencv::prelude::MatTrait::at_2d_mut::<u8>(&mut m, y, x).unwrap() =
                        rng.gen_range(0..=255);
                }
            }
            let mut smooth = super::super::contours::blurred(&m, [1.0, 2.5, 4.0][case % 3]);
            let centre = opencv::core::Point2f::new(w as f32 / 2.0, h as f32 / 2.0);
            let size = opencv::core::Size2f::new(w as f32 * 0.4, h as f32 * 0.3);
            let angle = rng.gen_range(0.0..90.0);
            let rect = opencv::core::RotatedRect::new(centre, size, angle).unwrap();
            let mut corners = [opencv::core::Point2f::default(); 4];
            rect.points(&mut corners).unwrap();
            let poly: Vector<Point> = corners
                .iter()
                .map(|c| Point::new(c.x.round() as i32, c.y.round() as i32))
                .collect();
            imgproc::fill_convex_poly(
                &mut smooth,
                &poly,
                opencv::core::Scalar::all(0.0),
                imgproc::LINE_8,
                0,
            )
            .unwrap();
            let mut bin = opencv::core::Mat::default();
            imgproc::threshold(&smooth, &mut bin, 127.0, 255.0, imgproc::THRESH_BINARY_INV)
                .unwrap();
            contours.trace(&crate::mat::GrayView::new(&bin).unwrap(), None);
            for c in contours.iter() {
                for eps in [0.5, 1.0, 0.05 * super::super::quads::closed_length(c), 3.7] {
                    let want = opencvs(c, eps);
                    assert_eq!(ours(c, eps), want, "case {case}, eps {eps}, {c:?}");
                    compared += 1;
                    quads += usize::from(want.len() == 4);
                }
            }
        }
        // Hand-made: one point, two, a straight line there and back,
        // collinear runs.
        let p = |v: &[(i32, i32)]| v.iter().map(|&(x, y)| Point::new(x, y)).collect::<Vec<_>>();
        for pts in [
            p(&[(3, 4)]),
            p(&[(3, 4), (9, 4)]),
            p(&[(0, 0), (5, 0), (10, 0), (5, 0)]),
            p(&[(0, 0), (4, 1), (8, 2), (8, 9), (4, 9), (0, 9)]),
            p(&[(0, 0), (0, 0), (6, 6)]),
        ] {
            for eps in [0.0, 1.0, 10.0] {
                assert_eq!(ours(&pts, eps), opencvs(&pts, eps), "{pts:?} at {eps}");
            }
        }
        assert!(
            compared > 3_000 && quads > 50,
            "{compared} compared, {quads} quads"
        );
    }

    #[test]
    fn convexity_and_bounding_box_are_opencvs() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(12);
        let (mut convex, mut not) = (0usize, 0usize);
        // Random quads in a small grid (so straight turns and repeated
        // points come up), random polygons of 3–8 points, and the empty,
        // one- and two-point cases.
        for case in 0..20_000 {
            let n = match case % 10 {
                0 => rng.gen_range(0..3),
                1..=6 => 4,
                _ => rng.gen_range(3..9),
            };
            let side = [3, 6, 40][case % 3];
            let pts: Vec<Point> = (0..n)
                .map(|_| Point::new(rng.gen_range(-side..side), rng.gen_range(-side..side)))
                .collect();
            if n == 0 {
                // OpenCV 4.6 asserts on an empty contour (its 4.x source
                // returns false for none).
                assert!(!is_convex(&pts));
                continue;
            }
            let v = Vector::<Point>::from_slice(&pts);
            let want = imgproc::is_contour_convex(&v).unwrap();
            assert_eq!(is_convex(&pts), want, "{pts:?}");
            if n >= 3 {
                if want {
                    convex += 1;
                } else {
                    not += 1;
                }
            }
            assert_eq!(
                bounding_box(&pts),
                imgproc::bounding_rect(&v).unwrap(),
                "{pts:?}"
            );
        }
        // Convex quads in both orientations, straight turns, repeats.
        let p = |v: &[(i32, i32)]| v.iter().map(|&(x, y)| Point::new(x, y)).collect::<Vec<_>>();
        for pts in [
            p(&[(0, 0), (4, 0), (4, 4), (0, 4)]),
            p(&[(0, 0), (0, 4), (4, 4), (4, 0)]),
            p(&[(0, 0), (2, 0), (4, 0), (0, 4)]),
            p(&[(0, 0), (0, 0), (4, 4), (0, 4)]),
            p(&[(0, 0), (4, 4), (4, 0), (0, 4)]),
        ] {
            let v = Vector::<Point>::from_slice(&pts);
            assert_eq!(
                is_convex(&pts),
                imgproc::is_contour_convex(&v).unwrap(),
                "{pts:?}"
            );
        }
        assert!(convex > 2_000 && not > 2_000, "{convex} convex, {not} not");
    }
}
