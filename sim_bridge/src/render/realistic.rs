//! A frame through a [`CameraProfile`]: the renderer's light integrated
//! over the exposure and the rolling shutter's rows, then what a real
//! camera adds on its way to the node (issue #16; `docs/water-model.md`,
//! "Camera effects"). The ideal profile is [`Renderer::render_with_port`]
//! exactly.
//!
//! Order (the light's): sub-frames through the port → per colour channel:
//! spot-lamp pattern, marine snow, heavy-tailed PSF, vignetting → auto
//! gain → Bayer mosaic → Poisson–Gaussian noise → demosaicing and luma →
//! gamma → 8 bits → JPEG / H.264-like. The node's calibration is drawn
//! once per profile seed (calibration error), not per frame.

use super::codec::{blur, h264_like, jpeg_roundtrip, PsfShape};
use super::effects::{
    add_snow, auto_gain, demosaic, draw_snow, encode, lamp_field, luma, mosaic, noisy_linear,
    smooth_field, vignetting,
};
use super::motion::{image_speed_px_per_s, ExposureSchedule, Timeline};
use super::{RenderOutput, Renderer};
use crate::error::SimError;
use crate::profile::{CalibrationError, CameraProfile, Effect};
use crate::water::WaterParams;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use shoal_proto::camera::Distortion;
use shoal_proto::{CameraModel, FlatPort, GrayImage};

/// What the profile did to one frame (for logs and the contact sheet).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct FrameReport {
    /// Sub-frames rendered per colour channel.
    pub sub_frames: usize,
    /// Seconds after the frame's start the ground truth refers to.
    pub reference_s: f64,
    /// Fastest image motion of a marker corner (px/s).
    pub image_speed_px_per_s: f64,
    /// Auto-exposure gain (1 without the effect).
    pub gain: f64,
    /// The PSF drawn for this frame.
    pub psf: Option<String>,
    pub snow_particles: usize,
}

/// One frame through a profile.
#[derive(Debug, Clone, PartialEq)]
pub struct ProfiledFrame {
    /// `image` as the node receives it; `clean` and `visible` from the
    /// sub-frame nearest the reference time.
    pub output: RenderOutput,
    /// The calibration the node should use: the in-water camera, off by the
    /// calibration error when that effect is on.
    pub node_camera: CameraModel,
    /// The port the frame was rendered through (the node does not model it).
    pub port: Option<FlatPort>,
    pub report: FrameReport,
}

/// The node's calibration: `cam` with fx, fy, cx, cy and k1 each moved
/// uniformly within ± the bounds of `e`, drawn from `seed` (same seed, same camera).
pub fn calibration_error(cam: &CameraModel, e: &CalibrationError, seed: u64) -> CameraModel {
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0xCA1B_0000_0000_0016);
    let mut u = |b: f64| if b > 0.0 { rng.gen_range(-b..=b) } else { 0.0 };
    let mut out = *cam;
    out.fx *= 1.0 + u(e.focal_rel);
    out.fy *= 1.0 + u(e.focal_rel);
    out.cx += u(e.principal_px);
    out.cy += u(e.principal_px);
    let dk = u(e.k1);
    match &mut out.distortion {
        Distortion::PlumbBob(k) => k[0] += dk,
        Distortion::Rational(k) => k[0] += dk,
        Distortion::Equidistant(k) => k[0] += dk,
    }
    out
}

/// The lens in air that, behind `port`, sees what the in-water pinhole
/// `cam` describes near the axis: focal lengths divided by the water's index.
pub fn lens_in_air(cam: &CameraModel, port: &FlatPort) -> CameraModel {
    CameraModel {
        fx: cam.fx / port.n_water,
        fy: cam.fy / port.n_water,
        ..*cam
    }
}

/// Render one frame of `timeline` through `profile`. `cam` is the camera as
/// calibrated in water; `port` a window the camera already has (then `cam`
/// is the lens in air, as in a fleet file, and the port effect adds none).
/// `time_s` is the simulation time of the frame's start (ambient light),
/// `seed` the frame's noise seed.
#[allow(clippy::too_many_arguments)]
pub fn render_profiled(
    renderer: &mut Renderer,
    profile: &CameraProfile,
    cam: &CameraModel,
    port: Option<&FlatPort>,
    timeline: &dyn Timeline,
    water: &WaterParams,
    time_s: f64,
    seed: u64,
) -> Result<ProfiledFrame, SimError> {
    profile.validate()?;
    if profile.is_ideal() {
        return ideal_frame(renderer, (cam, port), timeline, water, time_s, seed);
    }
    let p = &profile.params;
    let (lens, port) = match (port, profile.is_on(Effect::Port)) {
        (Some(given), _) => (*cam, Some(*given)),
        (None, true) => {
            let port = profile.port()?;
            (lens_in_air(cam, &port), Some(port))
        }
        (None, false) => (*cam, None),
    };
    let (w, h) = (cam.width as usize, cam.height as usize);
    let (schedule, speed) = schedule_of(profile, timeline, (&lens, port.as_ref()))?;
    let reference_s = schedule.reference_s(h);
    let nearest = (0..schedule.times_s.len())
        .min_by(|a, b| {
            let d = |j: usize| (schedule.times_s[j] - reference_s).abs();
            d(*a).total_cmp(&d(*b))
        })
        .unwrap_or(0);

    // Per-frame draws: the PSF family and the marine snow.
    let mut rng =
        ChaCha8Rng::seed_from_u64(profile.seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ seed);
    let psf = profile
        .is_on(Effect::Psf)
        .then(|| PsfShape::draw(&p.psf, &mut rng));
    let particles = if profile.is_on(Effect::Snow) {
        draw_snow(cam, &p.snow, &mut rng)
    } else {
        Vec::new()
    };

    let colour = profile.is_on(Effect::Colour);
    let channel_c: Vec<f64> = if colour {
        vec![
            water.c_per_m + p.colour.extra_c_red_per_m,
            water.c_per_m,
            water.c_per_m + p.colour.extra_c_blue_per_m,
        ]
    } else {
        vec![water.c_per_m]
    };
    let vig = profile
        .is_on(Effect::Vignetting)
        .then(|| smooth_field(cam, |x, y| vignetting(x, y, p.vignetting.strength)));
    let mut reference: Option<RenderOutput> = None;
    let mut channels = Vec::with_capacity(channel_c.len());
    for (ci, &c) in channel_c.iter().enumerate() {
        let water_c = WaterParams {
            c_per_m: c,
            ..*water
        };
        let keep = (ci == channel_c.len() / 2).then_some(nearest);
        let (mut acc, kept) = integrate(
            renderer,
            (&lens, port.as_ref()),
            timeline,
            &schedule,
            &water_c,
            time_s,
            seed,
            keep,
        )?;
        if kept.is_some() {
            reference = kept;
        }
        if profile.is_on(Effect::Lamps) {
            for (a, g) in acc.iter_mut().zip(lamp_field(cam, &p.lamps, c)) {
                *a *= g;
            }
        }
        if !particles.is_empty() {
            add_snow(&mut acc, cam, water, c, &p.snow, &p.lamps, &particles);
        }
        if let Some(psf) = &psf {
            acc = blur(&acc, w, h, psf)?;
        }
        if let Some(v) = &vig {
            for (a, g) in acc.iter_mut().zip(v) {
                *a *= g;
            }
        }
        channels.push(acc);
    }
    let Some(mut output) = reference else {
        return Err(SimError::Effect {
            stage: "exposure",
            message: "no sub-frame was rendered".into(),
        });
    };

    let (data, gain) = sensor(profile, channels, water, (w, h), seed)?;
    output.image = GrayImage {
        width: cam.width,
        height: cam.height,
        data,
    };
    let node_camera = if profile.is_on(Effect::Calibration) {
        calibration_error(cam, &p.calibration, profile.seed)
    } else {
        *cam
    };
    Ok(ProfiledFrame {
        output,
        node_camera,
        port,
        report: FrameReport {
            sub_frames: schedule.times_s.len(),
            reference_s,
            image_speed_px_per_s: speed,
            gain,
            psf: psf.map(|p| p.describe()),
            snow_particles: particles.len(),
        },
    })
}

/// The light of one colour channel integrated over the schedule's
/// sub-frames, row by row; with `keep`, also that sub-frame's render.
#[allow(clippy::too_many_arguments)]
fn integrate(
    renderer: &mut Renderer,
    (lens, port): (&CameraModel, Option<&FlatPort>),
    timeline: &dyn Timeline,
    schedule: &ExposureSchedule,
    water: &WaterParams,
    time_s: f64,
    seed: u64,
    keep: Option<usize>,
) -> Result<(Vec<f32>, Option<RenderOutput>), SimError> {
    let (w, h) = (lens.width as usize, lens.height as usize);
    let mut acc = vec![0.0f32; w * h];
    let mut kept = None;
    for (j, &t) in schedule.times_s.iter().enumerate() {
        let (world_from_camera, scene) = timeline.at(t)?;
        let out = renderer.render_with_port(
            lens,
            port,
            &world_from_camera,
            &scene,
            water,
            time_s + t,
            seed,
        )?;
        let dn = renderer.last_frame_dn();
        for y in 0..h {
            let wgt = schedule.weight(j, y) as f32;
            if wgt > 0.0 {
                let row = y * w..(y + 1) * w;
                for (a, d) in acc[row.clone()].iter_mut().zip(&dn[row]) {
                    *a += wgt * d;
                }
            }
        }
        if keep == Some(j) {
            kept = Some(out);
        }
    }
    Ok((acc, kept))
}

/// The sensor and the camera's processing: metering and gain, the Bayer
/// mosaic, noise, demosaicing and luma, gamma, 8 bits, the codec. Returns
/// the frame and the gain.
fn sensor(
    profile: &CameraProfile,
    channels: Vec<Vec<f32>>,
    water: &WaterParams,
    (w, h): (usize, usize),
    seed: u64,
) -> Result<(Vec<u8>, f64), SimError> {
    let p = &profile.params;
    let colour = channels.len() == 3;
    let (gain, gamma) = if profile.is_on(Effect::Exposure) {
        let e = &p.exposure;
        let meter = if colour {
            luma(&[
                channels[0].clone(),
                channels[1].clone(),
                channels[2].clone(),
            ])
        } else {
            channels[0].clone()
        };
        let mean = meter.iter().map(|v| f64::from(*v)).sum::<f64>() / meter.len().max(1) as f64;
        (
            auto_gain(mean, e.target_mean, e.min_gain, e.max_gain),
            e.gamma,
        )
    } else {
        (1.0, 1.0)
    };
    let linear = if colour {
        let mut it = channels.into_iter();
        let (Some(r), Some(g), Some(b)) = (it.next(), it.next(), it.next()) else {
            return Err(SimError::Effect {
                stage: "colour",
                message: "three channels expected".into(),
            });
        };
        let raw = noisy_linear(&mosaic(&[r, g, b], w), w, water, gain, seed);
        luma(&demosaic(&raw, w, h))
    } else {
        noisy_linear(&channels[0], w, water, gain, seed)
    };
    let mut data = encode(&linear, gamma);
    if profile.is_on(Effect::Jpeg) {
        data = jpeg_roundtrip(&data, w, h, p.jpeg.quality)?;
    } else if profile.is_on(Effect::H264) {
        data = h264_like(&data, w, h, p.h264.qp);
    }
    Ok((data, gain))
}

/// The sub-frames of a frame: the exposure (motion blur) and line time
/// (rolling shutter) of the effects that are on, as many as the image
/// motion needs; and that motion (px/s).
fn schedule_of(
    profile: &CameraProfile,
    timeline: &dyn Timeline,
    (lens, port): (&CameraModel, Option<&FlatPort>),
) -> Result<(ExposureSchedule, f64), SimError> {
    let p = &profile.params;
    let h = lens.height as usize;
    let exposure_s = if profile.is_on(Effect::MotionBlur) {
        p.motion_blur.exposure_s
    } else {
        0.0
    };
    let line_time_s = if profile.is_on(Effect::RollingShutter) {
        p.rolling_shutter.line_time_s
    } else {
        0.0
    };
    let span = exposure_s + line_time_s * h.saturating_sub(1) as f64;
    let speed = image_speed_px_per_s(timeline, lens, port, span)?;
    let schedule = ExposureSchedule::new(
        exposure_s,
        line_time_s,
        h,
        speed,
        p.motion_blur.max_step_px,
        p.motion_blur.max_samples,
    );
    Ok((schedule, speed))
}

/// The ideal profile: the renderer at the frame's start, the node knowing the camera.
fn ideal_frame(
    renderer: &mut Renderer,
    (cam, port): (&CameraModel, Option<&FlatPort>),
    timeline: &dyn Timeline,
    water: &WaterParams,
    time_s: f64,
    seed: u64,
) -> Result<ProfiledFrame, SimError> {
    let (world_from_camera, scene) = timeline.at(0.0)?;
    let output =
        renderer.render_with_port(cam, port, &world_from_camera, &scene, water, time_s, seed)?;
    Ok(ProfiledFrame {
        output,
        node_camera: *cam,
        port: port.copied(),
        report: FrameReport {
            sub_frames: 1,
            gain: 1.0,
            ..FrameReport::default()
        },
    })
}
