//! Parity of [`shoal_node::metrics::ssim`] with a reference implementation:
//! scikit-image's `structural_similarity`, on three small deterministic image
//! pairs built from integer formulas (no random generator, so Python and Rust
//! build the same pixels).
//!
//! The reference values were computed once with Python 3.11.7, scikit-image
//! 0.26.0, numpy 2.4.6, scipy 1.17.1:
//!
//! ```python
//! from skimage.metrics import structural_similarity as ssim
//! ssim(a.astype(np.float64), b.astype(np.float64), gaussian_weights=True,
//!      sigma=1.5, use_sample_covariance=False, data_range=255.0, K1=0.01, K2=0.03)
//! ```
//!
//! With `gaussian_weights=True, sigma=1.5` scikit-image filters with an
//! 11-tap Gaussian (truncate 3.5 → radius 5) and averages the SSIM map after
//! cropping 5 pixels on each side, which is exactly Wang et al.'s "valid"
//! window; `use_sample_covariance=False` gives their population variances.
//! The pixels, in numpy (`xs`, `ys` from `np.mgrid[0:29, 0:37]`, int64):
//!
//! ```python
//! h = lambda x, y, s: ((((x*73856093) ^ (y*19349663) ^ (s*83492791)) & 0xFFFFFFFF) >> 13) & 255
//! noise_mix:     a = h(xs, ys, 1);  b = (3*h(xs, ys, 1) + 2*h(xs, ys, 2)) // 5
//! checker_blur:  a = np.where(((xs//8) + (ys//8)) % 2 == 0, 40, 210)
//!                b = clip((3x3 box sum of a, edge-replicated) + 4) // 9 + 12, 0, 255)
//! ramp_negative: a = (xs*7 + ys*3) % 256;  b = 255 - a
//! ```

use shoal_node::metrics::ssim;
use shoal_proto::GrayImage;

/// Non-square, so that a swapped row/column stride would change the figures.
const W: usize = 37;
const H: usize = 29;

/// scikit-image 0.26.0's values for the three pairs (see the module doc).
const SKIMAGE_NOISE_MIX: f64 = 0.9278712705310289;
const SKIMAGE_CHECKER_BLUR: f64 = 0.7693519584214968;
const SKIMAGE_RAMP_NEGATIVE: f64 = -0.48193415851132076;

/// Both are double-precision sums over the same 513 windows in a different
/// order (scipy's separable correlation vs ours), so they agree to rounding;
/// 1e-9 leaves room for summation order and nothing else. Measured with
/// scikit-image on these pairs, each plausible slip moves at least one of
/// the three by more than 1e-3: σ 1.4 (3e-2), `K2` 0.02 (0.11), a uniform
/// 7x7 window (0.10), range 256 (1.5e-3), sample variances (1.5e-3).
const SKIMAGE_TOLERANCE: f64 = 1e-9;

fn hash(x: usize, y: usize, s: u64) -> u8 {
    let v = ((x as u64).wrapping_mul(73_856_093)
        ^ (y as u64).wrapping_mul(19_349_663)
        ^ s.wrapping_mul(83_492_791))
        & 0xFFFF_FFFF;
    ((v >> 13) & 255) as u8
}

fn image(f: impl Fn(usize, usize) -> u8) -> GrayImage {
    let mut data = Vec::with_capacity(W * H);
    for y in 0..H {
        for x in 0..W {
            data.push(f(x, y));
        }
    }
    GrayImage {
        width: W as u32,
        height: H as u32,
        data,
    }
}

fn checker(x: usize, y: usize) -> u8 {
    if (x / 8 + y / 8).is_multiple_of(2) {
        40
    } else {
        210
    }
}

fn pairs() -> [(&'static str, GrayImage, GrayImage, f64); 3] {
    let noise_a = image(|x, y| hash(x, y, 1));
    let noise_b = image(|x, y| ((3 * hash(x, y, 1) as u32 + 2 * hash(x, y, 2) as u32) / 5) as u8);
    let checker_a = image(checker);
    let checker_b = image(|x, y| {
        let mut sum = 0u32;
        for dy in -1i64..=1 {
            for dx in -1i64..=1 {
                let xx = (x as i64 + dx).clamp(0, W as i64 - 1) as usize;
                let yy = (y as i64 + dy).clamp(0, H as i64 - 1) as usize;
                sum += checker(xx, yy) as u32;
            }
        }
        ((sum + 4) / 9 + 12).min(255) as u8
    });
    let ramp = |x: usize, y: usize| ((x * 7 + y * 3) % 256) as u8;
    let ramp_a = image(ramp);
    let ramp_b = image(|x, y| 255 - ramp(x, y));
    [
        ("noise_mix", noise_a, noise_b, SKIMAGE_NOISE_MIX),
        ("checker_blur", checker_a, checker_b, SKIMAGE_CHECKER_BLUR),
        ("ramp_negative", ramp_a, ramp_b, SKIMAGE_RAMP_NEGATIVE),
    ]
}

#[test]
fn ssim_matches_scikit_image_on_three_deterministic_pairs() {
    for (name, a, b, reference) in pairs() {
        let ours = ssim(&a, &b).unwrap();
        assert!(
            (ours - reference).abs() < SKIMAGE_TOLERANCE,
            "{name}: shoal {ours:.16}, scikit-image {reference:.16} (diff {:.2e})",
            ours - reference
        );
        // SSIM is symmetric in its arguments.
        let swapped = ssim(&b, &a).unwrap();
        assert!(
            (swapped - ours).abs() < SKIMAGE_TOLERANCE,
            "{name}: not symmetric"
        );
    }
}
