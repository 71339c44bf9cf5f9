//! Camera profiles: how far a rendered frame is from the renderer's clean
//! camera (issue #16). [`CameraProfile::ideal`] is the renderer exactly;
//! [`CameraProfile::realistic`] turns on every effect of
//! `docs/water-model.md` ("Camera effects") with physically typical
//! parameters. A profile is the set of effects that are on, the parameters
//! of every effect (used when it is on), and a seed for its own random
//! draws (PSF family, marine snow, calibration error), so a profile and a
//! frame seed give the same bytes every time.
//!
//! A profile file (TOML) starts from a base and switches effects on or off;
//! a section sets an effect's parameters (it does not switch it on):
//!
//! ```toml
//! base = "ideal"              # or "realistic"
//! enable = ["snow", "jpeg"]   # effect names: CameraProfile::names()
//! disable = []
//! seed = 3
//! [snow]
//! density_per_m3 = 500.0
//! [jpeg]
//! quality = 60
//! ```

use crate::error::SimError;
use serde::Deserialize;
use shoal_proto::config::PortSpec;
use shoal_proto::FlatPort;
use std::collections::BTreeSet;
use std::path::Path;

/// One effect of the realistic camera, by the name the CLI and files use.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Effect {
    /// Observer and target motion during the exposure.
    MotionBlur,
    /// Rows exposed one line time after another.
    RollingShutter,
    /// A flat window in front of the lens; the node keeps its in-water pinhole.
    Port,
    /// Spot beams of the vehicle's lamps: uneven artificial light.
    Lamps,
    /// Marine snow lit by the lamps.
    Snow,
    /// A heavy-tailed PSF (Moffat or generalized Gaussian) drawn per frame.
    Psf,
    /// The rest of the lens's cos⁴ fall-off.
    Vignetting,
    /// A colour sensor: per-channel attenuation, Bayer mosaic, demosaicing, luma.
    Colour,
    /// Auto-exposure (gain) and gamma.
    Exposure,
    /// JPEG at a typical quality.
    Jpeg,
    /// H.264-like intra coding (documented approximation, see `docs/water-model.md`).
    H264,
    /// The node's intrinsics and distortion off from the renderer's.
    Calibration,
}

impl Effect {
    pub const ALL: [Effect; 12] = [
        Effect::MotionBlur,
        Effect::RollingShutter,
        Effect::Port,
        Effect::Lamps,
        Effect::Snow,
        Effect::Psf,
        Effect::Vignetting,
        Effect::Colour,
        Effect::Exposure,
        Effect::Jpeg,
        Effect::H264,
        Effect::Calibration,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Effect::MotionBlur => "motion-blur",
            Effect::RollingShutter => "rolling-shutter",
            Effect::Port => "port",
            Effect::Lamps => "lamps",
            Effect::Snow => "snow",
            Effect::Psf => "psf",
            Effect::Vignetting => "vignetting",
            Effect::Colour => "colour",
            Effect::Exposure => "exposure",
            Effect::Jpeg => "jpeg",
            Effect::H264 => "h264",
            Effect::Calibration => "calibration",
        }
    }
}

impl std::fmt::Display for Effect {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for Effect {
    type Err = SimError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let key = s.trim().replace('_', "-").to_ascii_lowercase();
        Effect::ALL
            .into_iter()
            .find(|e| e.name() == key || (key == "color" && *e == Effect::Colour))
            .ok_or_else(|| SimError::UnknownEffect {
                name: s.to_string(),
                known: CameraProfile::names(),
            })
    }
}

/// Motion blur: the exposure integrates the scene over `exposure_s`.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MotionBlur {
    /// Exposure time (s). 8 ms: a machine-vision camera's auto-exposure in
    /// dim water, typical of AUV footage (5–20 ms).
    pub exposure_s: f64,
    /// Largest image motion (px) between two sub-frames; sets how many are rendered.
    pub max_step_px: f64,
    /// Cap on the sub-frames of one frame (cost).
    pub max_samples: usize,
}

impl Default for MotionBlur {
    fn default() -> Self {
        MotionBlur {
            exposure_s: 0.008,
            max_step_px: 0.5,
            max_samples: 48,
        }
    }
}

/// Rolling shutter: row `y` starts its exposure `y · line_time_s` after row 0.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RollingShutter {
    /// Line time (s). 15 µs: 1080 rows read in 16 ms, a 1080p30 CMOS sensor.
    pub line_time_s: f64,
}

impl Default for RollingShutter {
    fn default() -> Self {
        RollingShutter { line_time_s: 15e-6 }
    }
}

/// The spot beams of two lamps beside the camera.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SpotLamps {
    /// Distance between the two lamps, placed symmetrically left and right of the lens (m).
    pub separation_m: f64,
    /// Beam half-angle at 1/e² of the axial intensity (degrees).
    pub beam_half_angle_deg: f64,
    /// Outward tilt of each lamp's axis from the optical axis (degrees).
    pub toe_out_deg: f64,
    /// Range at which the beam pattern is evaluated (m).
    pub range_m: f64,
    /// Share of the light that is ambient (uniform), the rest is the lamps' pattern.
    pub ambient_share: f64,
}

impl Default for SpotLamps {
    fn default() -> Self {
        SpotLamps {
            separation_m: 0.30,
            beam_half_angle_deg: 25.0,
            toe_out_deg: 10.0,
            range_m: 1.0,
            ambient_share: 0.4,
        }
    }
}

/// Marine snow: particles in the water column, lit by the lamps, out of focus.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MarineSnow {
    /// Particles per cubic metre between `near_m` and `far_m`.
    pub density_per_m3: f64,
    /// Particle diameters (mm), drawn from a power law `N(d) ∝ d^-3`.
    pub min_diameter_mm: f64,
    pub max_diameter_mm: f64,
    /// Depth range of the particles in front of the lens (m).
    pub near_m: f64,
    pub far_m: f64,
    /// Focus distance (m) and aperture diameter (mm): the blur circle of a particle.
    pub focus_m: f64,
    pub aperture_mm: f64,
    /// Reflectance of a particle.
    pub albedo: f64,
    /// Lamp radiance on a white surface at 1 m in clear water, relative to the ambient light.
    pub lamp_power: f64,
}

impl Default for MarineSnow {
    fn default() -> Self {
        MarineSnow {
            density_per_m3: 300.0,
            min_diameter_mm: 0.5,
            max_diameter_mm: 3.0,
            near_m: 0.15,
            far_m: 2.5,
            focus_m: 1.0,
            aperture_mm: 1.5,
            albedo: 0.5,
            lamp_power: 1.0,
        }
    }
}

/// A heavy-tailed PSF drawn per frame: Moffat or a generalized Gaussian.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PsfMix {
    /// Full width at half maximum (px), drawn uniformly in this range.
    pub fwhm_px: [f64; 2],
    /// Probability of a Moffat PSF (else a generalized Gaussian).
    pub moffat_share: f64,
    /// Moffat exponent β range (smaller = heavier tails; 2.5–4.8 in astronomy, 1.5 in turbid water).
    pub moffat_beta: [f64; 2],
    /// Generalized-Gaussian shape range (the detector's models have 1.5–2).
    pub gg_shape: [f64; 2],
}

impl Default for PsfMix {
    fn default() -> Self {
        PsfMix {
            fwhm_px: [1.0, 2.5],
            moffat_share: 0.5,
            moffat_beta: [1.5, 3.0],
            gg_shape: [0.6, 1.0],
        }
    }
}

/// The rest of the lens's natural `cos⁴θ` fall-off.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Vignetting {
    /// `V = 1 − strength · (1 − cos⁴θ)` on top of the water preset's own vignetting.
    pub strength: f64,
}

impl Default for Vignetting {
    fn default() -> Self {
        Vignetting { strength: 0.7 }
    }
}

/// A colour camera: the preset's attenuation is the green channel's.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ColourCamera {
    /// Extra attenuation of the red and the blue channel over the green (1/m).
    pub extra_c_red_per_m: f64,
    pub extra_c_blue_per_m: f64,
}

impl Default for ColourCamera {
    fn default() -> Self {
        ColourCamera {
            extra_c_red_per_m: 0.30,
            extra_c_blue_per_m: 0.10,
        }
    }
}

/// Auto-exposure by gain, then gamma encoding.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct AutoExposure {
    /// Mean linear level the metering aims at (fraction of full scale; 0.18 = mid-grey).
    pub target_mean: f64,
    /// Gain range (below 1: a shorter exposure, above 1: analog gain amplifying the read noise).
    pub min_gain: f64,
    pub max_gain: f64,
    /// Display gamma of the encoding: `out = in^(1/gamma)`.
    pub gamma: f64,
}

impl Default for AutoExposure {
    fn default() -> Self {
        AutoExposure {
            target_mean: 0.18,
            min_gain: 0.25,
            max_gain: 8.0,
            gamma: 2.2,
        }
    }
}

/// JPEG quality (1–100).
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Jpeg {
    pub quality: u8,
}

impl Default for Jpeg {
    fn default() -> Self {
        Jpeg { quality: 75 }
    }
}

/// H.264-like intra coding at quantization parameter `qp` (0–51).
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct H264 {
    pub qp: u8,
}

impl Default for H264 {
    fn default() -> Self {
        H264 { qp: 30 }
    }
}

/// How far the node's calibration is from the renderer's camera: each
/// quantity is drawn uniformly within ± its bound.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CalibrationError {
    /// Relative focal-length error (0.003 = ±0.3 %), fx and fy drawn independently.
    pub focal_rel: f64,
    /// Principal-point error (px), cx and cy drawn independently.
    pub principal_px: f64,
    /// Error of the first radial coefficient k1 (absolute).
    pub k1: f64,
}

impl Default for CalibrationError {
    fn default() -> Self {
        CalibrationError {
            focal_rel: 0.003,
            principal_px: 2.0,
            k1: 0.005,
        }
    }
}

fn default_port() -> PortSpec {
    // The refraction experiment's housing: 10 mm of air, 8 mm of acrylic.
    PortSpec {
        distance_mm: 10.0,
        glass_mm: 8.0,
        n_glass: FlatPort::N_ACRYLIC,
        n_water: FlatPort::N_SEA_WATER,
    }
}

/// The parameters of every effect (used when it is on).
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EffectParams {
    #[serde(default)]
    pub motion_blur: MotionBlur,
    #[serde(default)]
    pub rolling_shutter: RollingShutter,
    #[serde(default = "default_port")]
    pub port: PortSpec,
    #[serde(default)]
    pub lamps: SpotLamps,
    #[serde(default)]
    pub snow: MarineSnow,
    #[serde(default)]
    pub psf: PsfMix,
    #[serde(default)]
    pub vignetting: Vignetting,
    #[serde(default)]
    pub colour: ColourCamera,
    #[serde(default)]
    pub exposure: AutoExposure,
    #[serde(default)]
    pub jpeg: Jpeg,
    #[serde(default)]
    pub h264: H264,
    #[serde(default)]
    pub calibration: CalibrationError,
}

impl Default for EffectParams {
    fn default() -> Self {
        EffectParams {
            motion_blur: MotionBlur::default(),
            rolling_shutter: RollingShutter::default(),
            port: default_port(),
            lamps: SpotLamps::default(),
            snow: MarineSnow::default(),
            psf: PsfMix::default(),
            vignetting: Vignetting::default(),
            colour: ColourCamera::default(),
            exposure: AutoExposure::default(),
            jpeg: Jpeg::default(),
            h264: H264::default(),
            calibration: CalibrationError::default(),
        }
    }
}

/// A camera profile: which effects are on, their parameters, and the seed
/// of the profile's own random draws.
#[derive(Debug, Clone, PartialEq)]
pub struct CameraProfile {
    pub name: String,
    pub enabled: BTreeSet<Effect>,
    pub params: EffectParams,
    pub seed: u64,
}

/// The keys a profile file may have at its top level.
const FILE_KEYS: [&str; 16] = [
    "base",
    "enable",
    "disable",
    "seed",
    "motion_blur",
    "rolling_shutter",
    "port",
    "lamps",
    "snow",
    "psf",
    "vignetting",
    "colour",
    "exposure",
    "jpeg",
    "h264",
    "calibration",
];

/// A profile file (see the module doc).
#[derive(Debug, Clone, Deserialize)]
// No `deny_unknown_fields` here (serde does not combine it with `flatten`):
// keys this struct does not take go to `EffectParams`, which denies them.
struct ProfileFile {
    base: String,
    #[serde(default)]
    enable: Vec<String>,
    #[serde(default)]
    disable: Vec<String>,
    #[serde(default)]
    seed: Option<u64>,
    #[serde(flatten)]
    params: EffectParams,
}

impl CameraProfile {
    /// Today's renderer exactly: no effect, bit-identical frames.
    pub fn ideal() -> CameraProfile {
        CameraProfile {
            name: "ideal".into(),
            enabled: BTreeSet::new(),
            params: EffectParams::default(),
            seed: 1,
        }
    }

    /// Every effect on with typical parameters; JPEG rather than H.264 (one codec at a time).
    pub fn realistic() -> CameraProfile {
        CameraProfile {
            name: "realistic".into(),
            enabled: Effect::ALL
                .into_iter()
                .filter(|e| *e != Effect::H264)
                .collect(),
            params: EffectParams::default(),
            seed: 1,
        }
    }

    /// `ideal` or `realistic`.
    pub fn named(name: &str) -> Result<CameraProfile, SimError> {
        match name.trim() {
            "ideal" => Ok(CameraProfile::ideal()),
            "realistic" => Ok(CameraProfile::realistic()),
            other => Err(SimError::UnknownProfile {
                name: other.to_string(),
            }),
        }
    }

    /// Only the given effects, with typical parameters (`--effect`).
    pub fn only(effects: &[Effect]) -> CameraProfile {
        let enabled: BTreeSet<Effect> = effects.iter().copied().collect();
        let name = enabled
            .iter()
            .map(|e| e.name())
            .collect::<Vec<_>>()
            .join("+");
        CameraProfile {
            name: if name.is_empty() {
                "ideal".into()
            } else {
                name
            },
            enabled,
            params: EffectParams::default(),
            seed: 1,
        }
    }

    /// The profile a command line names: a profile file, else the listed
    /// effects alone (each entry may hold several, comma-separated), else
    /// the named profile; validated.
    pub fn selected(
        name: &str,
        effects: &[String],
        file: Option<&Path>,
    ) -> Result<CameraProfile, SimError> {
        let p = if let Some(f) = file {
            CameraProfile::load(f)?
        } else if !effects.is_empty() {
            let list = effects
                .iter()
                .flat_map(|e| e.split(','))
                .map(str::parse::<Effect>)
                .collect::<Result<Vec<_>, _>>()?;
            CameraProfile::only(&list)
        } else {
            CameraProfile::named(name)?
        };
        p.validate()?;
        Ok(p)
    }

    /// The effect names, comma-separated (for messages and `--help`).
    pub fn names() -> String {
        Effect::ALL.map(|e| e.name()).join(", ")
    }

    pub fn is_on(&self, e: Effect) -> bool {
        self.enabled.contains(&e)
    }

    /// No effect on: frames are the renderer's.
    pub fn is_ideal(&self) -> bool {
        self.enabled.is_empty()
    }

    pub fn with_seed(mut self, seed: u64) -> CameraProfile {
        self.seed = seed;
        self
    }

    /// Parse a profile file's text (`source` names it in errors) and validate it.
    pub fn from_toml(text: &str, source: &Path) -> Result<CameraProfile, SimError> {
        let parse_err = |message: String| SimError::ProfileParse {
            path: source.to_path_buf(),
            message,
        };
        // `flatten` lets unknown top-level keys through: refuse them here.
        let table: toml::Table = toml::from_str(text).map_err(|e| parse_err(e.to_string()))?;
        if let Some(key) = table.keys().find(|k| !FILE_KEYS.contains(&k.as_str())) {
            return Err(parse_err(format!(
                "unknown key `{key}`; expected one of {}",
                FILE_KEYS.join(", ")
            )));
        }
        let file: ProfileFile = toml::from_str(text).map_err(|e| parse_err(e.to_string()))?;
        let mut p = CameraProfile::named(&file.base)?;
        p.name = source
            .file_stem()
            .map_or("file".into(), |s| s.to_string_lossy().into_owned());
        p.params = file.params;
        for name in &file.enable {
            p.enabled.insert(name.parse()?);
        }
        for name in &file.disable {
            p.enabled.remove(&name.parse::<Effect>()?);
        }
        if let Some(seed) = file.seed {
            p.seed = seed;
        }
        p.validate()?;
        Ok(p)
    }

    /// Read and validate a profile file.
    pub fn load(path: &Path) -> Result<CameraProfile, SimError> {
        let text = std::fs::read_to_string(path).map_err(|source| SimError::ProfileRead {
            path: path.to_path_buf(),
            source,
        })?;
        CameraProfile::from_toml(&text, path)
    }

    /// The flat port of the `port` effect, validated.
    pub fn port(&self) -> Result<FlatPort, SimError> {
        self.params
            .port
            .port()
            .map_err(|reason| SimError::ProfileInvalid {
                effect: "port",
                field: "port",
                value: f64::NAN,
                reason,
            })
    }

    /// Check every parameter (of every effect, on or off); the error names
    /// the effect, the field, the value and the reason.
    pub fn validate(&self) -> Result<(), SimError> {
        let p = &self.params;
        let m = p.motion_blur;
        check("motion_blur", "exposure_s", m.exposure_s, 0.0, 1.0)?;
        check("motion_blur", "max_step_px", m.max_step_px, 0.01, 100.0)?;
        check(
            "motion_blur",
            "max_samples",
            m.max_samples as f64,
            1.0,
            1000.0,
        )?;
        check(
            "rolling_shutter",
            "line_time_s",
            p.rolling_shutter.line_time_s,
            0.0,
            1e-3,
        )?;
        self.port()?;
        let l = p.lamps;
        check("lamps", "separation_m", l.separation_m, 0.0, 10.0)?;
        check(
            "lamps",
            "beam_half_angle_deg",
            l.beam_half_angle_deg,
            1.0,
            90.0,
        )?;
        check("lamps", "toe_out_deg", l.toe_out_deg, -45.0, 45.0)?;
        check("lamps", "range_m", l.range_m, 0.05, 100.0)?;
        check("lamps", "ambient_share", l.ambient_share, 0.0, 1.0)?;
        let s = p.snow;
        check("snow", "density_per_m3", s.density_per_m3, 0.0, 1e5)?;
        check("snow", "min_diameter_mm", s.min_diameter_mm, 0.01, 100.0)?;
        check(
            "snow",
            "max_diameter_mm",
            s.max_diameter_mm,
            s.min_diameter_mm,
            100.0,
        )?;
        check("snow", "near_m", s.near_m, 0.01, 100.0)?;
        check("snow", "far_m", s.far_m, s.near_m, 100.0)?;
        check("snow", "focus_m", s.focus_m, 0.01, 1e3)?;
        check("snow", "aperture_mm", s.aperture_mm, 0.0, 100.0)?;
        check("snow", "albedo", s.albedo, 0.0, 1.0)?;
        check("snow", "lamp_power", s.lamp_power, 0.0, 1e3)?;
        let f = p.psf;
        check_range("psf", "fwhm_px", f.fwhm_px, 0.1, 20.0)?;
        check("psf", "moffat_share", f.moffat_share, 0.0, 1.0)?;
        check_range("psf", "moffat_beta", f.moffat_beta, 1.05, 20.0)?;
        check_range("psf", "gg_shape", f.gg_shape, 0.3, 4.0)?;
        check("vignetting", "strength", p.vignetting.strength, 0.0, 1.0)?;
        check(
            "colour",
            "extra_c_red_per_m",
            p.colour.extra_c_red_per_m,
            0.0,
            10.0,
        )?;
        check(
            "colour",
            "extra_c_blue_per_m",
            p.colour.extra_c_blue_per_m,
            0.0,
            10.0,
        )?;
        let e = p.exposure;
        check("exposure", "target_mean", e.target_mean, 0.01, 0.9)?;
        check("exposure", "min_gain", e.min_gain, 0.01, 1.0)?;
        check("exposure", "max_gain", e.max_gain, 1.0, 1000.0)?;
        check("exposure", "gamma", e.gamma, 0.5, 4.0)?;
        check("jpeg", "quality", f64::from(p.jpeg.quality), 1.0, 100.0)?;
        check("h264", "qp", f64::from(p.h264.qp), 0.0, 51.0)?;
        let c = p.calibration;
        check("calibration", "focal_rel", c.focal_rel, 0.0, 0.2)?;
        check("calibration", "principal_px", c.principal_px, 0.0, 100.0)?;
        check("calibration", "k1", c.k1, 0.0, 0.5)?;
        if self.is_on(Effect::Jpeg) && self.is_on(Effect::H264) {
            return Err(SimError::ProfileInvalid {
                effect: "jpeg",
                field: "enable",
                value: f64::NAN,
                reason: "jpeg and h264 are both on; a camera streams one codec".into(),
            });
        }
        Ok(())
    }
}

/// `value` finite and within `lo..=hi`.
fn check(
    effect: &'static str,
    field: &'static str,
    value: f64,
    lo: f64,
    hi: f64,
) -> Result<(), SimError> {
    if value.is_finite() && value >= lo && value <= hi {
        Ok(())
    } else {
        Err(SimError::ProfileInvalid {
            effect,
            field,
            value,
            reason: format!("must be finite and within {lo}..={hi}"),
        })
    }
}

/// A `[lo, hi]` range within `min..=max`, lo ≤ hi.
fn check_range(
    effect: &'static str,
    field: &'static str,
    r: [f64; 2],
    min: f64,
    max: f64,
) -> Result<(), SimError> {
    check(effect, field, r[0], min, max)?;
    check(effect, field, r[1], r[0], max)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn realistic_turns_every_effect_on_but_the_second_codec() {
        let p = CameraProfile::realistic();
        assert_eq!(p.enabled.len(), Effect::ALL.len() - 1);
        assert!(!p.is_on(Effect::H264) && p.is_on(Effect::Jpeg));
        p.validate().unwrap();
        assert!(CameraProfile::ideal().is_ideal());
    }

    #[test]
    fn effect_names_round_trip() {
        for e in Effect::ALL {
            assert_eq!(e.name().parse::<Effect>().unwrap(), e);
        }
        assert_eq!("motion_blur".parse::<Effect>().unwrap(), Effect::MotionBlur);
        let err = "bloom".parse::<Effect>().unwrap_err().to_string();
        assert!(
            err.contains("bloom") && err.contains("motion-blur"),
            "{err}"
        );
    }

    #[test]
    fn a_file_starts_from_its_base_and_switches_effects() {
        let text = "base = \"ideal\"\nenable = [\"snow\", \"jpeg\"]\nseed = 9\n[snow]\ndensity_per_m3 = 50.0\n[jpeg]\nquality = 40\n";
        let p = CameraProfile::from_toml(text, Path::new("murky.toml")).unwrap();
        assert_eq!(p.name, "murky");
        assert_eq!(
            p.enabled,
            [Effect::Snow, Effect::Jpeg].into_iter().collect()
        );
        assert_eq!(p.params.snow.density_per_m3, 50.0);
        assert_eq!(p.params.snow.far_m, MarineSnow::default().far_m);
        assert_eq!((p.params.jpeg.quality, p.seed), (40, 9));
        let r = CameraProfile::from_toml(
            "base = \"realistic\"\ndisable = [\"port\"]\n",
            Path::new("x.toml"),
        )
        .unwrap();
        assert!(!r.is_on(Effect::Port) && r.is_on(Effect::Snow));
    }

    #[test]
    fn bad_parameters_are_named() {
        let cases = [
            (
                "base = \"ideal\"\n[motion_blur]\nexposure_s = -0.001\n",
                "exposure_s",
            ),
            ("base = \"ideal\"\n[psf]\nfwhm_px = [3.0, 1.0]\n", "fwhm_px"),
            ("base = \"ideal\"\n[jpeg]\nquality = 0\n", "quality"),
            (
                "base = \"ideal\"\n[port]\ndistance_mm = -1\nglass_mm = 8\n",
                "port",
            ),
            ("base = \"ideal\"\n[snow]\nnear_m = 3.0\n", "far_m"),
            ("base = \"ideal\"\n[exposure]\ngamma = nan\n", "gamma"),
            (
                "base = \"ideal\"\nenable = [\"jpeg\", \"h264\"]\n",
                "one codec",
            ),
            ("base = \"ideal\"\nenable = [\"bloom\"]\n", "bloom"),
            ("base = \"pretty\"\n", "pretty"),
            ("base = \"ideal\"\n[snow]\ndensity = 3\n", "density"),
            ("base = \"ideal\"\nsead = 3\n", "sead"),
        ];
        for (text, needle) in cases {
            let err = CameraProfile::from_toml(text, Path::new("bad.toml"))
                .unwrap_err()
                .to_string();
            assert!(err.contains(needle), "{text:?}: {err}");
        }
    }
}
