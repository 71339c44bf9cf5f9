//! The water: every parameter of the underwater image-formation model of
//! `docs/water-model.md`, and the presets of `configs/water.toml` keyed by
//! the paper's measured attenuation coefficients (paper §6.1, Table 5,
//! Figs. 11–17: 0.126 … 14.20 /m).
//!
//! One [`WaterParams`] is everything the renderer needs to degrade a clean
//! view; [`WaterKnobs`] are the few global multipliers an evaluation step
//! tunes so that its detector reproduces the paper's detection rates
//! (applied to every preset by [`WaterPresets::get`]).

use crate::error::SimError;
use serde::Deserialize;
use std::path::Path;

/// The shipped presets file, compiled in as the built-in default.
const SHIPPED_PRESETS: &str = include_str!("../../configs/water.toml");

/// All parameters of the water model for one water body (see
/// `docs/water-model.md` for the equations each one enters).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WaterParams {
    /// Beam attenuation coefficient `c` (per metre): direct light is `e^(−c·r)`.
    pub c_per_m: f64,
    /// Fraction `s` of the attenuation that is small-angle forward scattering:
    /// that light is not lost but spread by the PSF, so the total transmitted
    /// light is `e^(−(1−s)·c·r)` of which `e^(−c·r)` is unscattered.
    pub forward_scatter: f64,
    /// Shape exponent `p` of the paper's generalized-Gaussian PSF, Eq. (14)
    /// (2 = Gaussian, 1 = Laplacian-like heavy tails in turbid water).
    pub psf_shape_p: f64,
    /// Angular width of the PSF per square root of optical depth (rad):
    /// width = `psf_angle_rad · sqrt(c·r)` (multiple small-angle scattering).
    pub psf_angle_rad: f64,
    /// Veiling light at infinite range `B∞`, relative to the radiance of a
    /// white Lambertian surface under the ambient light (Eq. (6)'s `A`).
    pub backscatter_inf: f64,
    /// How much brighter the veiling light is looking straight up than
    /// horizontally (downwelling light): `B∞·(1 + gain·cos(zenith))`.
    pub backscatter_up_gain: f64,
    /// Relative amplitude of the slow spatial pattern of the ambient light (0..1).
    pub ambient_spatial: f64,
    /// Relative amplitude of the slow temporal fluctuation of the ambient light (0..1).
    pub ambient_temporal: f64,
    /// Period of the ambient fluctuation (s).
    pub ambient_period_s: f64,
    /// Fixes the ambient pattern's phases (the water's, not the frame's, seed).
    pub ambient_seed: u64,
    /// Natural illumination of objects relative to the nominal ambient light.
    pub illumination: f64,
    /// Artificial light at the camera: radiance it gives a white surface at
    /// 1 m in clear water, relative to the ambient light (0 = off).
    pub lamp_power: f64,
    /// Fraction of the lamp's light back-scattered into the camera per metre
    /// of lit water (scaled by `1/z²`, see the docs).
    pub lamp_backscatter: f64,
    /// Scene radiance to digital number: `DN = 255 · exposure · L`.
    pub exposure: f64,
    /// Vignetting strength (0: none, 1: full `cos⁴θ` fall-off).
    pub vignetting: f64,
    /// Photon-transfer gain (electrons per DN): shot noise `σ² = DN / gain` (DN²).
    pub gain_e_per_dn: f64,
    /// Gaussian read noise (DN, standard deviation); 0 with `gain` ∞ = no noise.
    pub read_noise_dn: f64,
}

/// Global multipliers applied to every preset (the calibration handles).
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct WaterKnobs {
    /// Multiplies `backscatter_inf` (and `lamp_backscatter`).
    pub backscatter_scale: f64,
    /// Multiplies `forward_scatter` (clamped below 1).
    pub forward_scatter_scale: f64,
    /// Multiplies `psf_angle_rad`.
    pub psf_width_scale: f64,
    /// Multiplies the noise standard deviations (shot and read).
    pub noise_scale: f64,
    /// Multiplies `exposure`.
    pub exposure_scale: f64,
}

impl Default for WaterKnobs {
    fn default() -> Self {
        Self {
            backscatter_scale: 1.0,
            forward_scatter_scale: 1.0,
            psf_width_scale: 1.0,
            noise_scale: 1.0,
            exposure_scale: 1.0,
        }
    }
}

/// Optional overrides, as written in `[defaults]` and each `[[preset]]`.
#[derive(Debug, Clone, Copy, PartialEq, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct ParamsSpec {
    c_per_m: Option<f64>,
    forward_scatter: Option<f64>,
    psf_shape_p: Option<f64>,
    psf_angle_rad: Option<f64>,
    backscatter_inf: Option<f64>,
    backscatter_up_gain: Option<f64>,
    ambient_spatial: Option<f64>,
    ambient_temporal: Option<f64>,
    ambient_period_s: Option<f64>,
    ambient_seed: Option<u64>,
    illumination: Option<f64>,
    lamp_power: Option<f64>,
    lamp_backscatter: Option<f64>,
    exposure: Option<f64>,
    vignetting: Option<f64>,
    gain_e_per_dn: Option<f64>,
    read_noise_dn: Option<f64>,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
struct PresetsFile {
    #[serde(default)]
    knobs: WaterKnobs,
    #[serde(default)]
    defaults: ParamsSpec,
    preset: Vec<ParamsSpec>,
}

impl ParamsSpec {
    fn apply(&self, p: &mut WaterParams) {
        macro_rules! set {
            ($($f:ident),*) => { $( if let Some(v) = self.$f { p.$f = v; } )* };
        }
        set!(
            c_per_m,
            forward_scatter,
            psf_shape_p,
            psf_angle_rad,
            backscatter_inf,
            backscatter_up_gain,
            ambient_spatial,
            ambient_temporal,
            ambient_period_s,
            ambient_seed,
            illumination,
            lamp_power,
            lamp_backscatter,
            exposure,
            vignetting,
            gain_e_per_dn,
            read_noise_dn
        );
    }
}

impl WaterParams {
    /// Physically plausible defaults for attenuation `c_per_m`, before any
    /// preset file: moderate forward scatter, a mid-grey veil, a machine-vision
    /// sensor (20 e⁻/DN, 1 DN read noise).
    pub fn baseline(c_per_m: f64) -> WaterParams {
        WaterParams {
            c_per_m,
            forward_scatter: 0.4,
            psf_shape_p: 1.5,
            psf_angle_rad: 0.004,
            backscatter_inf: 0.5,
            backscatter_up_gain: 0.3,
            ambient_spatial: 0.05,
            ambient_temporal: 0.03,
            ambient_period_s: 20.0,
            ambient_seed: 1,
            illumination: 1.0,
            lamp_power: 0.0,
            lamp_backscatter: 0.0,
            exposure: 1.0,
            vignetting: 0.3,
            gain_e_per_dn: 20.0,
            read_noise_dn: 1.0,
        }
    }

    /// The built-in preset for `c_per_m` (interpolated between the shipped
    /// presets, clamped to their range; see [`WaterPresets::get`]).
    pub fn preset(c_per_m: f64) -> WaterParams {
        let presets = WaterPresets::builtin();
        let c = if c_per_m.is_finite() { c_per_m } else { 0.0 };
        let c = c.clamp(presets.min_c(), presets.max_c());
        presets.get(c).unwrap_or_else(|_| WaterParams::baseline(c))
    }

    /// No water at all: nothing attenuates or scatters, no veil, no noise.
    pub fn clear() -> WaterParams {
        WaterParams {
            c_per_m: 0.0,
            forward_scatter: 0.0,
            backscatter_inf: 0.0,
            ambient_spatial: 0.0,
            ambient_temporal: 0.0,
            vignetting: 0.0,
            gain_e_per_dn: f64::INFINITY,
            read_noise_dn: 0.0,
            ..WaterParams::baseline(0.0)
        }
    }

    /// The same water without sensor noise (for geometry tests).
    pub fn noiseless(mut self) -> WaterParams {
        self.gain_e_per_dn = f64::INFINITY;
        self.read_noise_dn = 0.0;
        self
    }

    /// These parameters with the global knobs applied.
    pub fn with_knobs(mut self, k: &WaterKnobs) -> WaterParams {
        self.backscatter_inf *= k.backscatter_scale;
        self.lamp_backscatter *= k.backscatter_scale;
        self.forward_scatter = (self.forward_scatter * k.forward_scatter_scale).clamp(0.0, 0.999);
        self.psf_angle_rad *= k.psf_width_scale;
        self.exposure *= k.exposure_scale;
        if k.noise_scale > 0.0 {
            // σ_shot² = DN / gain, so scaling σ by k divides the gain by k².
            self.gain_e_per_dn /= k.noise_scale * k.noise_scale;
        } else {
            self.gain_e_per_dn = f64::INFINITY;
        }
        self.read_noise_dn *= k.noise_scale;
        self
    }

    /// Check every field; `Err` names the first bad one.
    pub fn validate(&self) -> Result<(), SimError> {
        let bad = |field, value, reason| {
            Err(SimError::WaterInvalid {
                field,
                value,
                reason,
            })
        };
        let nonneg: [(&'static str, f64); 10] = [
            ("c_per_m", self.c_per_m),
            ("psf_angle_rad", self.psf_angle_rad),
            ("backscatter_inf", self.backscatter_inf),
            ("backscatter_up_gain", self.backscatter_up_gain),
            ("illumination", self.illumination),
            ("lamp_power", self.lamp_power),
            ("lamp_backscatter", self.lamp_backscatter),
            ("exposure", self.exposure),
            ("read_noise_dn", self.read_noise_dn),
            ("ambient_period_s", self.ambient_period_s),
        ];
        for (field, value) in nonneg {
            if !(value.is_finite() && value >= 0.0) {
                return bad(field, value, "must be finite and non-negative");
            }
        }
        let unit: [(&'static str, f64); 4] = [
            ("forward_scatter", self.forward_scatter),
            ("ambient_spatial", self.ambient_spatial),
            ("ambient_temporal", self.ambient_temporal),
            ("vignetting", self.vignetting),
        ];
        for (field, value) in unit {
            if !(0.0..1.0).contains(&value) && value != 0.0 {
                return bad(field, value, "must be in 0..1");
            }
        }
        if !(self.psf_shape_p.is_finite() && self.psf_shape_p >= 0.5 && self.psf_shape_p <= 4.0) {
            return bad("psf_shape_p", self.psf_shape_p, "must be in 0.5..=4");
        }
        if self.gain_e_per_dn.is_nan() || self.gain_e_per_dn <= 0.0 {
            return bad(
                "gain_e_per_dn",
                self.gain_e_per_dn,
                "must be positive (inf = no shot noise)",
            );
        }
        if self.c_per_m > 100.0 {
            return bad(
                "c_per_m",
                self.c_per_m,
                "above 100 /m is not water one can see through",
            );
        }
        Ok(())
    }

    /// True when this water adds no sensor noise.
    pub fn is_noiseless(&self) -> bool {
        self.gain_e_per_dn.is_infinite() && self.read_noise_dn == 0.0
    }

    fn lerp(a: &WaterParams, b: &WaterParams, w: f64) -> WaterParams {
        let l = |x: f64, y: f64| x + (y - x) * w;
        WaterParams {
            c_per_m: l(a.c_per_m, b.c_per_m),
            forward_scatter: l(a.forward_scatter, b.forward_scatter),
            psf_shape_p: l(a.psf_shape_p, b.psf_shape_p),
            psf_angle_rad: l(a.psf_angle_rad, b.psf_angle_rad),
            backscatter_inf: l(a.backscatter_inf, b.backscatter_inf),
            backscatter_up_gain: l(a.backscatter_up_gain, b.backscatter_up_gain),
            ambient_spatial: l(a.ambient_spatial, b.ambient_spatial),
            ambient_temporal: l(a.ambient_temporal, b.ambient_temporal),
            ambient_period_s: l(a.ambient_period_s, b.ambient_period_s),
            ambient_seed: if w < 0.5 {
                a.ambient_seed
            } else {
                b.ambient_seed
            },
            illumination: l(a.illumination, b.illumination),
            lamp_power: l(a.lamp_power, b.lamp_power),
            lamp_backscatter: l(a.lamp_backscatter, b.lamp_backscatter),
            exposure: l(a.exposure, b.exposure),
            vignetting: l(a.vignetting, b.vignetting),
            // Interpolate noise in σ, not in gain.
            gain_e_per_dn: {
                let (sa, sb) = (
                    a.gain_e_per_dn.recip().sqrt(),
                    b.gain_e_per_dn.recip().sqrt(),
                );
                let s = l(sa, sb);
                if s > 0.0 {
                    1.0 / (s * s)
                } else {
                    f64::INFINITY
                }
            },
            read_noise_dn: l(a.read_noise_dn, b.read_noise_dn),
        }
    }
}

/// The water presets of a `water.toml`, sorted by attenuation, with the
/// global knobs the file sets (which [`WaterPresets::get`] applies).
#[derive(Debug, Clone, PartialEq)]
pub struct WaterPresets {
    /// Presets as written (knobs not applied), ascending `c_per_m`.
    pub presets: Vec<WaterParams>,
    pub knobs: WaterKnobs,
}

impl WaterPresets {
    /// The presets shipped in `configs/water.toml` (compiled in).
    pub fn builtin() -> WaterPresets {
        // The shipped file is checked by a unit test, so this cannot fail at run time.
        Self::parse(SHIPPED_PRESETS, Path::new("configs/water.toml")).unwrap_or_else(|_| {
            WaterPresets {
                presets: vec![WaterParams::baseline(0.0), WaterParams::baseline(20.0)],
                knobs: WaterKnobs::default(),
            }
        })
    }

    /// Load a presets file.
    pub fn load(path: &Path) -> Result<WaterPresets, SimError> {
        let text = std::fs::read_to_string(path).map_err(|source| SimError::WaterRead {
            path: path.to_path_buf(),
            source,
        })?;
        Self::parse(&text, path)
    }

    /// Parse presets TOML; `path` only names the source in messages.
    pub fn parse(text: &str, path: &Path) -> Result<WaterPresets, SimError> {
        let perr = |message: String| SimError::WaterParse {
            path: path.to_path_buf(),
            message,
        };
        let file: PresetsFile =
            toml::from_str(text).map_err(|e| perr(e.to_string().trim_end().to_string()))?;
        if file.preset.is_empty() {
            return Err(perr("no [[preset]] tables".into()));
        }
        let mut presets = Vec::new();
        for (i, spec) in file.preset.iter().enumerate() {
            if spec.c_per_m.is_none() {
                return Err(perr(format!("preset[{i}] has no c_per_m")));
            }
            let mut p = WaterParams::baseline(0.0);
            file.defaults.apply(&mut p);
            spec.apply(&mut p);
            p.validate()
                .map_err(|e| perr(format!("preset[{i}]: {e}")))?;
            presets.push(p);
        }
        presets.sort_by(|a, b| a.c_per_m.total_cmp(&b.c_per_m));
        if presets
            .windows(2)
            .any(|w| w[1].c_per_m - w[0].c_per_m < 1e-9)
        {
            return Err(perr("two presets have the same c_per_m".into()));
        }
        let k = file.knobs;
        for (name, v) in [
            ("knobs.backscatter_scale", k.backscatter_scale),
            ("knobs.forward_scatter_scale", k.forward_scatter_scale),
            ("knobs.psf_width_scale", k.psf_width_scale),
            ("knobs.noise_scale", k.noise_scale),
            ("knobs.exposure_scale", k.exposure_scale),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(perr(format!(
                    "{name} = {v} must be finite and non-negative"
                )));
            }
        }
        // Knobs that are fine alone can still break a preset (a huge
        // noise_scale zeroes the gain): check every preset with them applied.
        for p in &presets {
            (*p).with_knobs(&k).validate().map_err(|e| {
                perr(format!(
                    "preset c_per_m = {} with [knobs] applied (backscatter_scale = {}, \
                     forward_scatter_scale = {}, psf_width_scale = {}, noise_scale = {}, \
                     exposure_scale = {}): {e}",
                    p.c_per_m,
                    k.backscatter_scale,
                    k.forward_scatter_scale,
                    k.psf_width_scale,
                    k.noise_scale,
                    k.exposure_scale
                ))
            })?;
        }
        Ok(WaterPresets { presets, knobs: k })
    }

    pub fn min_c(&self) -> f64 {
        self.presets.first().map_or(0.0, |p| p.c_per_m)
    }

    pub fn max_c(&self) -> f64 {
        self.presets.last().map_or(0.0, |p| p.c_per_m)
    }

    /// The attenuation coefficients of the presets, ascending.
    pub fn coefficients(&self) -> Vec<f64> {
        self.presets.iter().map(|p| p.c_per_m).collect()
    }

    /// The preset for `c_per_m`, knobs applied: the preset itself when `c`
    /// is within 0.5 % of one, otherwise interpolated linearly between the
    /// two neighbouring presets. Outside the presets' range it is an error.
    pub fn get(&self, c_per_m: f64) -> Result<WaterParams, SimError> {
        self.get_with(c_per_m, &self.knobs)
    }

    /// As [`WaterPresets::get`] but with the given knobs instead of the file's.
    pub fn get_with(&self, c_per_m: f64, knobs: &WaterKnobs) -> Result<WaterParams, SimError> {
        let (min, max) = (self.min_c(), self.max_c());
        let out = || SimError::WaterOutOfRange { c_per_m, min, max };
        if !c_per_m.is_finite() {
            return Err(out());
        }
        if let Some(p) = self
            .presets
            .iter()
            .find(|p| (p.c_per_m - c_per_m).abs() <= 0.005 * p.c_per_m.max(1e-3))
        {
            return Ok(p.with_knobs(knobs));
        }
        if c_per_m < min || c_per_m > max {
            return Err(out());
        }
        let hi = self
            .presets
            .iter()
            .position(|p| p.c_per_m >= c_per_m)
            .ok_or_else(out)?;
        let (a, b) = (&self.presets[hi - 1], &self.presets[hi]);
        let w = (c_per_m - a.c_per_m) / (b.c_per_m - a.c_per_m);
        let mut p = WaterParams::lerp(a, b, w);
        p.c_per_m = c_per_m;
        Ok(p.with_knobs(knobs))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const PAPER_C: [f64; 10] = [
        0.126, 0.5, 1.38, 3.92, 5.16, 6.12, 8.22, 10.13, 12.20, 14.20,
    ];

    #[test]
    fn shipped_file_parses_and_has_the_papers_coefficients() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/water.toml");
        let loaded = WaterPresets::load(&path).unwrap();
        assert_eq!(loaded, WaterPresets::builtin());
        for c in PAPER_C {
            let p = loaded.get(c).unwrap();
            assert_eq!(p.c_per_m, c);
            p.validate().unwrap();
        }
    }

    #[test]
    fn knobs_scale_every_preset() {
        let pr = WaterPresets::builtin();
        let knobs = WaterKnobs {
            backscatter_scale: 2.0,
            noise_scale: 0.5,
            ..WaterKnobs::default()
        };
        let a = pr.get_with(8.22, &WaterKnobs::default()).unwrap();
        let b = pr.get_with(8.22, &knobs).unwrap();
        assert!((b.backscatter_inf - 2.0 * a.backscatter_inf).abs() < 1e-12);
        assert!((b.read_noise_dn - 0.5 * a.read_noise_dn).abs() < 1e-12);
        assert!((b.gain_e_per_dn - 4.0 * a.gain_e_per_dn).abs() < 1e-9);
    }

    #[test]
    fn between_presets_interpolates_and_outside_is_an_error() {
        let pr = WaterPresets::builtin();
        let p = pr.get(7.0).unwrap();
        let (a, b) = (pr.get(6.12).unwrap(), pr.get(8.22).unwrap());
        assert_eq!(p.c_per_m, 7.0);
        let lo = a.backscatter_inf.min(b.backscatter_inf);
        let hi = a.backscatter_inf.max(b.backscatter_inf);
        assert!(p.backscatter_inf >= lo && p.backscatter_inf <= hi);
        assert!(matches!(
            pr.get(50.0),
            Err(SimError::WaterOutOfRange { .. })
        ));
        assert!(matches!(
            pr.get(f64::NAN),
            Err(SimError::WaterOutOfRange { .. })
        ));
        // The infallible form clamps.
        assert_eq!(WaterParams::preset(50.0).c_per_m, 14.2);
    }

    #[test]
    fn unknown_field_and_bad_value_are_reported() {
        let e = WaterPresets::parse(
            "[[preset]]\nc_per_m = 1.0\nturbidity = 3\n",
            Path::new("w.toml"),
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("w.toml") && e.contains("turbidity"), "{e}");
        let e = WaterPresets::parse(
            "[[preset]]\nc_per_m = 1.0\nforward_scatter = 2\n",
            Path::new("w.toml"),
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("forward_scatter"), "{e}");
        assert!(WaterPresets::parse("[[preset]]\nexposure = 1.0\n", Path::new("w.toml")).is_err());
    }
}
