//! Tests of the step-edge model on squares drawn with exact pixel coverage.

use super::*;
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};

#[test]
fn erf_matches_known_values() {
    for (x, e) in [
        (0.0, 0.0),
        (0.5, 0.520_499_877_8),
        (1.0, 0.842_700_792_9),
        (-2.0, -0.995_322_265),
    ] {
        assert!((erf_and_gauss(x).0 - e).abs() < 2e-7, "erf({x})");
    }
}

/// Area of the convex polygon `poly` inside the unit pixel centred at `(x, y)`
/// (Sutherland–Hodgman clipping, then the shoelace formula).
fn coverage(poly: &[Px], x: f64, y: f64) -> f64 {
    let mut pts: Vec<Px> = poly.to_vec();
    // Keep the side where `f(p) >= 0`, for the pixel's four half-planes.
    let planes: [(usize, f64, f64); 4] = [
        (0, 1.0, x - 0.5),
        (0, -1.0, x + 0.5),
        (1, 1.0, y - 0.5),
        (1, -1.0, y + 0.5),
    ];
    for (axis, s, bound) in planes {
        let f = |p: &Px| s * (p[axis] - bound);
        let mut out = Vec::with_capacity(pts.len() + 2);
        for i in 0..pts.len() {
            let (a, b) = (pts[i], pts[(i + 1) % pts.len()]);
            let (fa, fb) = (f(&a), f(&b));
            if fa >= 0.0 {
                out.push(a);
            }
            if (fa >= 0.0) != (fb >= 0.0) {
                let t = fa / (fa - fb);
                out.push([a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1])]);
            }
        }
        pts = out;
        if pts.is_empty() {
            return 0.0;
        }
    }
    0.5 * (0..pts.len())
        .map(|i| {
            let (a, b) = (pts[i], pts[(i + 1) % pts.len()]);
            a[0] * b[1] - b[0] * a[1]
        })
        .sum::<f64>()
        .abs()
}

/// A dark square (grey 50) with corners `quad` on a bright surround (190),
/// integrated exactly over each pixel, blurred by a Gaussian of `blur` px
/// (0: none), plus `ramp` grey levels per pixel down the image, plus
/// Gaussian noise of `noise` grey levels, quantized to 8 bits.
fn render(quad: &[Px; 4], blur: f64, ramp: f64, noise: f64, seed: u64) -> Vec<u8> {
    render_with(
        |x, y| 190.0 - 140.0 * coverage(quad, x, y),
        blur,
        ramp,
        noise,
        seed,
    )
}

/// [`render`] of any scene: `scene(x, y)` is the grey level integrated over pixel (x, y).
fn render_with(
    scene: impl Fn(f64, f64) -> f64,
    blur: f64,
    ramp: f64,
    noise: f64,
    seed: u64,
) -> Vec<u8> {
    let (w, h) = (160usize, 160usize);
    let mut img: Vec<f64> = (0..w * h)
        .map(|i| scene((i % w) as f64, (i / w) as f64))
        .collect();
    if blur > 0.0 {
        let r = (3.0 * blur).ceil() as isize;
        let k: Vec<f64> = (-r..=r)
            .map(|i| (-(i as f64).powi(2) / (2.0 * blur * blur)).exp())
            .collect();
        let ks: f64 = k.iter().sum();
        for pass in 0..2 {
            let src = img.clone();
            for y in 0..h as isize {
                for x in 0..w as isize {
                    let mut acc = 0.0;
                    for (j, kv) in k.iter().enumerate() {
                        let o = j as isize - r;
                        let (sx, sy) = if pass == 0 { (x + o, y) } else { (x, y + o) };
                        let sx = sx.clamp(0, w as isize - 1) as usize;
                        let sy = sy.clamp(0, h as isize - 1) as usize;
                        acc += kv * src[sy * w + sx];
                    }
                    img[y as usize * w + x as usize] = acc / ks;
                }
            }
        }
    }
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let n = Normal::new(0.0, noise.max(1e-9)).expect("normal");
    img.iter()
        .enumerate()
        .map(|(i, v)| {
            let y = (i / w) as f64;
            let e = if noise > 0.0 { n.sample(&mut rng) } else { 0.0 };
            (v + ramp * (y - 80.0) + e).round().clamp(0.0, 255.0) as u8
        })
        .collect()
}

fn view(data: &[u8]) -> GrayView<'_> {
    GrayView {
        data,
        width: 160,
        height: 160,
        stride: 160,
    }
}

/// A 90 px square at a sub-pixel offset, turned by `deg` (clockwise on screen).
fn square(deg: f64) -> [Px; 4] {
    let (c, s) = (deg.to_radians().cos(), deg.to_radians().sin());
    let centre = [80.37, 79.71];
    [[-45.0, -45.0], [45.0, -45.0], [45.0, 45.0], [-45.0, 45.0]]
        .map(|[x, y]| [centre[0] + c * x - s * y, centre[1] + s * x + c * y])
}

fn max_error(a: &[Px; 4], b: &[Px; 4]) -> f64 {
    (0..4).map(|i| dist(a[i], b[i])).fold(0.0, f64::max)
}

/// Raw turbid water on the enhanced marker's nested squares (module
/// 12 px: a dark frame, a white ring, a dark code square): a sharp image
/// (25 % of the light, the unscattered part) plus the same blurred by a
/// wide halo (σ 9 px, the forward-scattered part), noise 2 grey levels.
/// The halo profile must find the code square's sharp edges to a tenth
/// of a pixel rms over eight noise draws (0.087 px measured; one Gaussian
/// 0.105 px). Its gain on the simulator's frames is pinned by
/// `node/tests/detect_corner_fit.rs`,
/// `turbid_corners_fitted_on_the_raw_frame_beat_the_restored_ones`.
#[test]
fn the_halo_profile_finds_the_sharp_step_under_a_wide_halo() {
    let sq = |half: f64| {
        let (c, s) = (7f64.to_radians().cos(), 7f64.to_radians().sin());
        let centre = [80.37, 79.71];
        [[-half, -half], [half, -half], [half, half], [-half, half]]
            .map(|[x, y]| [centre[0] + c * x - s * y, centre[1] + s * x + c * y])
    };
    let (outer, inner, code) = (sq(60.0), sq(48.0), sq(36.0));
    let scene = |x: f64, y: f64| {
        let dark = coverage(&outer, x, y) - coverage(&inner, x, y) + coverage(&code, x, y);
        190.0 - 140.0 * dark
    };
    let sharp = render_with(scene, 0.5, 0.0, 0.0, 1);
    let wide = render_with(scene, 9.0, 0.0, 0.0, 1);
    let start = code.map(|p| [p[0] + 0.4, p[1] - 0.3]);
    let n = Normal::new(0.0, 2.0).expect("normal");
    let (mut err_halo, mut err_blurred) = (0.0, 0.0);
    for seed in 0..8 {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let img: Vec<u8> = sharp
            .iter()
            .zip(&wide)
            .map(|(&a, &b)| {
                let v = 0.25 * f64::from(a) + 0.75 * f64::from(b) + n.sample(&mut rng);
                v.round().clamp(0.0, 255.0) as u8
            })
            .collect();
        for (profile, err) in [
            (Profile::Halo, &mut err_halo),
            (Profile::Blurred, &mut err_blurred),
        ] {
            let fit = fit_square(&view(&img), &start, 12.0, 1.0, profile).expect("fit");
            let c = fit.corners(None).expect("corners");
            *err += (0..4).map(|i| dist(c[i], code[i]).powi(2)).sum::<f64>();
        }
    }
    let (rms_halo, rms_blurred) = ((err_halo / 32.0).sqrt(), (err_blurred / 32.0).sqrt());
    eprintln!("corner rms: halo {rms_halo:.3} px, blurred {rms_blurred:.3} px");
    assert!(
        rms_halo < 0.1,
        "halo {rms_halo:.3} px (one Gaussian {rms_blurred:.3} px)"
    );
}

#[test]
fn recovers_an_axis_aligned_square_to_a_hundredth_of_a_pixel() {
    // All pixels of a side at the same sub-pixel phase: where a gradient
    // peak locks to the pixel grid. Start 0.4 px off.
    let truth = square(0.0);
    let img = render(&truth, 0.0, 0.0, 0.0, 1);
    let start = truth.map(|p| [p[0] + 0.4, p[1] - 0.3]);
    let fit = refine_by_edge_model(&view(&img), &start, 15.0, 1.0).expect("fit");
    assert!(max_error(&fit, &truth) < 0.01, "{fit:?} vs {truth:?}");
}

#[test]
fn recovers_a_blurred_noisy_turned_square() {
    let truth = square(7.0);
    let img = render(&truth, 1.5, 0.0, 4.0, 2);
    let start = truth.map(|p| [p[0] - 0.5, p[1] + 0.4]);
    let fit = refine_by_edge_model(&view(&img), &start, 15.0, 1.0).expect("fit");
    assert!(max_error(&fit, &truth) < 0.08, "{fit:?} vs {truth:?}");
}

#[test]
fn does_not_move_exact_corners_away() {
    for (k, deg) in [0.3, 12.0, 31.0].into_iter().enumerate() {
        let truth = square(deg);
        let img = render(&truth, 0.8, 0.0, 1.0, 10 + k as u64);
        let fit = refine_by_edge_model(&view(&img), &truth, 15.0, 1.0).expect("fit");
        // A sampled Gaussian kernel is not exactly the model's continuous
        // blur: a few hundredths of a pixel of mismatch remain.
        assert!(
            max_error(&fit, &truth) < 0.05,
            "{deg}°: {fit:?} vs {truth:?}"
        );
    }
}

#[test]
fn a_brightness_ramp_along_the_sides_does_not_tilt_them() {
    // 0.3 grey levels per pixel down the image (a veil brighter at the top
    // in turbid water) against a contrast of 140: the left and right
    // sides see it along their length.
    let truth = square(0.5);
    let img = render(&truth, 1.2, -0.3, 0.0, 3);
    let fit = refine_by_edge_model(&view(&img), &truth, 15.0, 1.0).expect("fit");
    assert!(max_error(&fit, &truth) < 0.03, "{fit:?} vs {truth:?}");
}

#[test]
fn finds_no_edge_in_a_flat_image_or_with_the_wrong_polarity() {
    let flat = vec![120u8; 160 * 160];
    assert!(refine_by_edge_model(&view(&flat), &square(3.0), 15.0, 1.0).is_none());
    let truth = square(3.0);
    let img = render(&truth, 0.0, 0.0, 0.0, 4);
    assert!(refine_by_edge_model(&view(&img), &truth, 15.0, -1.0).is_none());
}
