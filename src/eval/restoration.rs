//! `restoration` (paper §6.1, Tables 1–4): SSIM, PSNR and CNR of none,
//! CLAHE, DCP, UDCP and HOIRM at 6.12, 8.22, 10.13 and 12.20 /m, against
//! the simulator's clean image of the same view.
//!
//! Through a camera profile (`--profile realistic`, issue #16) the frames
//! carry the camera's effects (port, lamps, snow, PSF, vignetting, noise,
//! compression…) and the clean image stays the scene's: the same geometry
//! through the same port, without water or camera effects. SSIM and PSNR
//! then score how close each method brings the camera's frame to the scene,
//! including what no restoration undoes (noise, compression); CNR needs no
//! reference. The regions and masks come from the pinhole projection of the
//! true pose, within 0.25 px of the port's rendering at this 0.6 m.
//!
//! The metrics are taken over the marker's region (its quiet zone plus a
//! margin of one module), not the whole frame: the clean twin has a black
//! background where the underwater frame has the water's veil, so whole-frame
//! figures would mostly measure the background. CNR is between the pixels of
//! the marker's white and black modules (central 60 % of each module, from
//! the known pose: [`super::scene::module_masks`]).

use super::features::plot_or_warn;
use super::plot::{self, Grouped};
use super::scene::{
    crop, frame_rng, jittered_pose, make_restorer, marker_roi, module_masks, render_marker_through,
    restore, FRAME_INTERVAL_S, MARKER_ID, MARKER_SIDE_M,
};
use super::table::{cell, Csv};
use super::{water_key, EvalError, EvalOptions};
use rand::Rng;
use serde_json::{json, Map, Value};
use shoal_node::metrics::{cnr, gray_from_mat, psnr, ssim};
use shoal_node::restore::Method;
use shoal_proto::{CameraModel, CodeSet, GrayImage};
use shoal_sim_bridge::render::Renderer;

/// Tables 1–4's waters (1/m).
pub const WATERS: [f64; 4] = [6.12, 8.22, 10.13, 12.20];
/// The paper's (SSIM, PSNR dB, CNR) at each of [`WATERS`] for CLAHE, DCP ("DCPA") and HOIRM ("Ours").
pub const PAPER: [(&str, [[f64; 3]; 4]); 3] = [
    (
        "clahe",
        [
            [0.18878, 14.6112, 3.318],
            [0.35333, 12.6422, 2.6573],
            [0.31598, 6.1466, 1.4678],
            [0.30476, 12.9064, 2.6078],
        ],
    ),
    (
        "dcp",
        [
            [0.6372, 15.6326, -1.0],
            [0.70481, 13.3453, -1.0],
            [0.51625, 6.3799, -1.0],
            [0.74566, 14.4325, -1.0],
        ],
    ),
    (
        "hoirm",
        [
            [0.81372, 14.80951, 13.1265],
            [0.74497, 14.2165, 15.6027],
            [0.67948, 7.9747, 12.2967],
            [0.7467, 14.9633, 16.901],
        ],
    ),
];
/// Fraction of each module's side kept for the CNR masks.
const MASK_INNER: f64 = 0.6;

pub fn run(opts: &EvalOptions) -> Result<Value, EvalError> {
    let frames = opts.count(2, 10);
    let cam = CameraModel::vehicle_1440();
    let presets = opts.presets()?;
    let methods = Method::ALL;
    let mut renderer = Renderer::new();
    let (profile, _) = opts.seeded_profile_and_lens(&cam)?;
    let width = cam.width as usize;
    let mut csv = Csv::new(&["c_per_m", "frame", "restoration", "ssim", "psnr_db", "cnr"]);
    // sums[method][water] = (ssim, psnr, cnr, n)
    let mut sums = vec![vec![[0.0f64; 4]; WATERS.len()]; methods.len()];
    let bar = opts.bar(WATERS.len() * frames, "restoration: frames");
    for (wi, &c) in WATERS.iter().enumerate() {
        let water = presets.get(c)?;
        let mut restorers: Vec<_> = methods
            .iter()
            .map(|&m| make_restorer(m, &opts.restore_params))
            .collect();
        for k in 0..frames {
            let mut rng = frame_rng(opts.seed, 2000 + wi as u64, k as u64);
            let truth = jittered_pose(0.600, [0.0; 3], 0.002, 0.5f64.to_radians(), &mut rng);
            let noise_seed: u64 = rng.gen();
            let time_s = k as f64 * FRAME_INTERVAL_S;
            let frame = render_marker_through(
                &mut renderer,
                profile.as_ref(),
                &cam,
                CodeSet::Shoal,
                &truth,
                &water,
                time_s,
                noise_seed,
            )?;
            let pad = MARKER_SIDE_M / CodeSet::Shoal.modules() as f64;
            let pad_px = cam.fx * pad / 0.6;
            let (Some(roi), Some((white, black))) = (
                marker_roi(&cam, &truth, CodeSet::Shoal, MARKER_SIDE_M, pad_px),
                module_masks(
                    &cam,
                    &truth,
                    CodeSet::Shoal,
                    MARKER_ID,
                    MARKER_SIDE_M,
                    MASK_INNER,
                ),
            ) else {
                bar.inc(1);
                continue;
            };
            let cut = |img: &GrayImage| GrayImage {
                width: roi.2 as u32,
                height: roi.3 as u32,
                data: crop(&img.data, width, roi),
            };
            let clean = cut(&frame.clean);
            let (white, black) = (crop(&white, width, roi), crop(&black, width, roi));
            for (mi, r) in restorers.iter_mut().enumerate() {
                let restored = restore(r.as_mut(), &frame.image, (time_s * 1e9) as u64)?;
                let img = cut(&gray_from_mat(&restored.image)?);
                let s = ssim(&img, &clean)?;
                let p = psnr(&img, &clean)?;
                let n = cnr(&img, &white, &black).ok();
                csv.row(vec![
                    c.to_string(),
                    k.to_string(),
                    methods[mi].name().into(),
                    cell(Some(s)),
                    cell(Some(p)),
                    cell(n),
                ]);
                let acc = &mut sums[mi][wi];
                acc[0] += s;
                acc[1] += p.min(99.0);
                acc[2] += n.unwrap_or(0.0);
                acc[3] += 1.0;
            }
            bar.inc(1);
        }
    }
    bar.finish_and_clear();
    csv.write(&opts.out.join("restoration.csv"))?;

    summarize(opts, frames, &methods, &sums)
}

/// Mean SSIM, PSNR and CNR per method and water from `sums[method][water] =
/// (ssim, psnr, cnr, n)`, beside the paper's, with their bar plots.
fn summarize(
    opts: &EvalOptions,
    frames: usize,
    methods: &[Method],
    sums: &[Vec<[f64; 4]>],
) -> Result<Value, EvalError> {
    let mean = |mi: usize, wi: usize, q: usize| {
        let a = sums[mi][wi];
        (a[3] > 0.0).then(|| a[q] / a[3])
    };
    let mut results = Map::new();
    for (mi, m) in methods.iter().enumerate() {
        let per: Map<String, Value> = WATERS
            .iter()
            .enumerate()
            .map(|(wi, c)| {
                (
                    water_key(*c),
                    json!({ "ssim": mean(mi, wi, 0), "psnr_db": mean(mi, wi, 1), "cnr": mean(mi, wi, 2) }),
                )
            })
            .collect();
        results.insert(m.name().into(), Value::Object(per));
    }
    let mut paper = Map::new();
    for (name, rows) in PAPER {
        let per: Map<String, Value> = WATERS
            .iter()
            .zip(rows)
            .map(|(c, r)| {
                (
                    water_key(*c),
                    json!({ "ssim": r[0], "psnr_db": r[1], "cnr": r[2] }),
                )
            })
            .collect();
        paper.insert(name.into(), Value::Object(per));
    }
    let categories: Vec<String> = WATERS.iter().map(|c| water_key(*c)).collect();
    let series: Vec<String> = methods.iter().map(|m| m.name().to_string()).collect();
    let mut plots = Vec::new();
    for (q, key, label) in [
        (0, "ssim", "SSIM"),
        (1, "psnr", "PSNR (dB)"),
        (2, "cnr", "CNR"),
    ] {
        let values: Vec<Vec<Option<f64>>> = (0..methods.len())
            .map(|mi| (0..WATERS.len()).map(|wi| mean(mi, wi, q)).collect())
            .collect();
        plots.push(plot_or_warn(plot::bars(
            &opts.out.join(format!("eval-restoration-{key}")),
            &Grouped {
                title: format!(
                    "{label} against the clean image, marker region (paper Tables 1–4; {} camera)",
                    opts.profile_name()
                ),
                x_label: "attenuation coefficient c (1/m)".into(),
                y_label: label.into(),
                categories: categories.clone(),
                series: series.clone(),
            },
            &values,
        )));
    }
    Ok(json!({
        "frames": frames,
        "camera_profile": opts.profile_name(),
        "reference": "the renderer's clean image of the same view (same geometry and port; no water, no camera effects)",
        "region": "marker quiet zone + 1 module margin",
        "cnr_masks": format!("central {:.0} % of each module, from the true pose", MASK_INNER * 100.0),
        "results": results,
        "paper": paper,
        "plots": plots,
    }))
}
