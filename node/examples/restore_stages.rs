//! HOIRM stage by stage on a synthetic degraded marker: prints the marker's
//! CNR and edge steepness after every stage and writes the stages as PNGs.
//!
//! `cargo run -p shoal-node --example restore_stages [c_per_m] [out_dir]`

use opencv::core::{Mat, Vector};
use shoal_node::metrics::{cnr_mat, gray_from_mat};
use shoal_node::restore::synthetic::{marker_frame, Degradation};
use shoal_node::restore::{Hoirm, RestoreParams, StageOrder};

fn main() {
    let c: f64 = std::env::args()
        .nth(1)
        .and_then(|a| a.parse().ok())
        .unwrap_or(10.13);
    let dir = std::env::args()
        .nth(2)
        .unwrap_or_else(|| "/tmp/shoal-stages".into());
    std::fs::create_dir_all(&dir).unwrap();
    let f = marker_frame(640, 480, 300, 250, 16, &Degradation::for_c(c), 1).unwrap();
    let edge = |m: &Mat| {
        // Mean |horizontal difference| over the marker / cell contrast.
        let g = gray_from_mat(m).unwrap();
        let r = f.marker;
        let mut s = 0.0;
        for y in r.y..r.y + r.height {
            for x in r.x..r.x + r.width - 1 {
                s +=
                    (g.get(x as u32, y as u32) as f64 - g.get(x as u32 + 1, y as u32) as f64).abs();
            }
        }
        s / (r.width * r.height) as f64
    };
    for order in [StageOrder::Paper, StageOrder::Physical] {
        let params = RestoreParams {
            keep_stages: true,
            order,
            ..RestoreParams::default()
        };
        let mut h = Hoirm::new(params);
        let (out, p) = h.restore_with_params(&f.degraded, 0).unwrap();
        println!(
            "order {order:?}: {p:?}\n  rois {:?} level {}",
            out.rois, out.pyramid_level
        );
        for (i, (name, m)) in out.stages.unwrap().iter().enumerate() {
            let cnr = cnr_mat(m, &f.white, &f.black).unwrap_or(f64::NAN);
            println!("  {i} {name:<28} CNR {cnr:7.2}  edge {:6.2}", edge(m));
            let path = format!("{dir}/{order:?}_{i}.png");
            opencv::imgcodecs::imwrite(&path, m, &Vector::new()).unwrap();
        }
    }
    println!(
        "clean CNR n/a (noiseless), clean edge {:.2}",
        edge(&f.clean)
    );
    opencv::imgcodecs::imwrite(&format!("{dir}/clean.png"), &f.clean, &Vector::new()).unwrap();
}
