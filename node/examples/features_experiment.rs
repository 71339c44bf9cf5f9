//! The paper's Figure 3 simulation (§3.1, Eq. (5)): cumulative distance
//! error against the number of corners, at five noise levels.
//! `cargo run -p shoal-node --example features_experiment -- [trials]`

fn main() -> anyhow::Result<()> {
    let trials: usize = std::env::args().nth(1).map_or(Ok(1000), |s| s.parse())?;
    let sigmas = [1.0, 2.0, 4.0, 8.0, 16.0];
    let counts: Vec<usize> = (4..=20).collect();
    let rows = shoal_node::pose::features_experiment(trials, &sigmas, &counts, 2024);
    println!("sigma_px points cumulative_mm relative_mm(Eq.5) failures");
    for r in rows {
        println!(
            "{:8} {:6} {:13.1} {:16.1} {:8}",
            r.sigma_px, r.points, r.cumulative_mm, r.relative_mm, r.failures
        );
    }
    Ok(())
}
