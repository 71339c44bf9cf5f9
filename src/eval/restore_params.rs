//! `--restore-param NAME=VALUE`: one field of [`RestoreParams`] set by its
//! Rust name, for the tuning runs of `docs/restoration.md` (what the former
//! example programs read from `SHOAL_<FIELD>` environment variables).

use super::EvalError;
use shoal_node::restore::{RestoreParams, StageOrder};

/// Apply `NAME=VALUE` to `params`; the error names the field and what it accepts.
pub fn apply(params: &mut RestoreParams, assignment: &str) -> Result<(), EvalError> {
    let bad = |why: String| EvalError::Setup(format!("--restore-param {assignment:?}: {why}"));
    let (name, value) = assignment
        .split_once('=')
        .map(|(n, v)| (n.trim(), v.trim()))
        .ok_or_else(|| bad("expected NAME=VALUE".into()))?;
    let float = || {
        value
            .parse::<f64>()
            .map_err(|_| bad(format!("{value:?} is not a number")))
    };
    let int = || {
        value
            .parse::<i64>()
            .map_err(|_| bad(format!("{value:?} is not an integer")))
    };
    let flag = || match value {
        "true" | "1" => Ok(true),
        "false" | "0" => Ok(false),
        _ => Err(bad(format!("{value:?} is not true/false"))),
    };
    macro_rules! fields {
        (f64: $($f:ident),* ; bool: $($b:ident),* ; u32: $($u:ident),* ; i32: $($i:ident),*) => {
            match name {
                $(stringify!($f) => params.$f = float()?,)*
                $(stringify!($b) => params.$b = flag()?,)*
                $(stringify!($u) => {
                    params.$u = u32::try_from(int()?).map_err(|_| bad("must be >= 0".into()))?
                })*
                $(stringify!($i) => {
                    params.$i = i32::try_from(int()?).map_err(|_| bad("out of range".into()))?
                })*
                "c_per_m" => {
                    params.c_per_m = if value == "none" { None } else { Some(float()?) }
                }
                "order" => {
                    params.order = match value {
                        "paper" => StageOrder::Paper,
                        "physical" => StageOrder::Physical,
                        _ => return Err(bad("order is paper or physical".into())),
                    }
                }
                _ => {
                    let known = [$(stringify!($f),)* $(stringify!($b),)* $(stringify!($u),)* $(stringify!($i),)* "c_per_m", "order"];
                    return Err(bad(format!("unknown field; known: {}", known.join(", "))));
                }
            }
        };
    }
    fields!(
        f64: ambient_sigma_px, ambient_tau_s, ambient_alpha_max, clahe_clip_base,
            clahe_clip_per_c, psf_p_clear, psf_c_half_per_m, psf_px_per_unit,
            psf_min_sigma_px, psf_trust_ratio, deconv_min_c_per_m,
            passthrough_below_c_per_m, nsr_gain, nsr_min, nsr_max, reference_range_m,
            white_over_veil, forward_scatter_fraction, contrast_noise_k, stretch_target, stretch_max_gain,
            edge_snr_target, level_blur_px, denoise_edge_snr, denoise_min_sigma_px,
            denoise_max_sigma_px, clahe_contrast_target, roi_noise_k, roi_rel_threshold,
            roi_min_gradient, roi_background_k, roi_hysteresis, roi_max_fraction,
            baseline_clahe_clip, dcp_omega, dcp_t0, dcp_guided_eps;
        bool: keep_stages, roi_only, psf_sigma_from_image, deconv_when_denoised,
            psf_unscattered, fine_pass, fine_pass_whole_frame;
        u32: denoised_deconv_level, deconv_level, max_pyramid_level;
        i32: clahe_tile_px, min_roi_side_at_level_px, baseline_clahe_grid, dcp_patch,
            dcp_guided_radius
    );
    match params.problem() {
        Some(e) => Err(bad(e.to_string())),
        None => Ok(()),
    }
}

/// [`RestoreParams::default`] with every assignment applied in order.
pub fn from_assignments(assignments: &[String]) -> Result<RestoreParams, EvalError> {
    let mut params = RestoreParams::default();
    for a in assignments {
        apply(&mut params, a)?;
    }
    Ok(params)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sets_fields_of_every_type_by_name() {
        let p = from_assignments(&[
            "psf_px_per_unit=8".into(),
            "deconv_level=1".into(),
            "order=physical".into(),
            "roi_only=false".into(),
            "clahe_tile_px=64".into(),
            "c_per_m=6.12".into(),
        ])
        .unwrap();
        assert_eq!(p.psf_px_per_unit, 8.0);
        assert_eq!(p.deconv_level, 1);
        assert_eq!(p.order, StageOrder::Physical);
        assert!(!p.roi_only);
        assert_eq!(p.clahe_tile_px, 64);
        assert_eq!(p.c_per_m, Some(6.12));
    }

    #[test]
    fn rejects_unknown_fields_bad_values_and_unusable_parameters() {
        for (a, says) in [
            ("psf_px_per_unt=8", "unknown field"),
            ("psf_px_per_unit", "NAME=VALUE"),
            ("psf_px_per_unit=x", "not a number"),
            ("deconv_level=-1", ">= 0"),
            ("psf_px_per_unit=-1", "must be finite and > 0"),
            ("order=sideways", "paper or physical"),
        ] {
            let e = from_assignments(&[a.into()]).unwrap_err().to_string();
            assert!(e.contains(says), "{a}: {e}");
        }
    }
}
