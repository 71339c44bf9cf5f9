//! A solve's pose graph, for independent solvers: the constraints the
//! Levenberg–Marquardt step ([`crate::solver`]) minimised after the chi-square
//! gate, with the spanning-tree initial poses, written as a **g2o** file.
//!
//! Format (g2o's 3-D pose graph, read by g2o, gtsam's `readG2o`, Ceres'
//! pose-graph example), one record per line:
//!
//! ```text
//! VERTEX_SE3:QUAT <vehicle> x y z qx qy qz qw           reference_from_vehicle, initial guess
//! FIX <reference>                                        the gauge: the reference vehicle is fixed
//! EDGE_SE3:QUAT <a> <b> x y z qx qy qz qw I11 I12 … I66  measured a_from_b, 21 upper-triangular
//!                                                        information entries, row by row
//! ```
//!
//! The information is over `(δt, δθ)` of the **right** (local) perturbation
//! of the measurement, `measured · Exp(ξ)` with ξ = (ω, v) written translation
//! first — the convention gtsam's `readG2o` and g2o's `EdgeSE3` read.
//! shoal's own covariances are over the left perturbation in frame `a`
//! (`docs/wire.md`); the two agree to first order through
//! `Λ_local = Bᵀ Λ B`, `B = diag(R_measured, R_measured)`.
//!
//! The file is the least-squares problem. shoal solves it with a Huber kernel
//! (`RobustKernel`, k = 4.1), quadratic for every edge within 4.1σ; g2o has no
//! place for a kernel, so a reader adds its own or none.

use crate::solver::{edge_chi2, Constraint, RobustKernel};
use nalgebra::Matrix6;
use proto::geometry::Pose;
use proto::VehicleId;
use std::collections::BTreeMap;
use std::io::Write;

/// The graph of one solve (after its last gate round).
#[derive(Debug, Clone, PartialEq)]
pub struct PoseGraph {
    /// The vehicle fixing the gauge (identity pose).
    pub reference: VehicleId,
    /// `reference_from_vehicle` from the spanning tree: the solver's start.
    pub initial: BTreeMap<VehicleId, Pose>,
    /// One fused constraint per accepted vehicle pair.
    pub constraints: Vec<Constraint>,
}

impl PoseGraph {
    /// Write the graph as g2o (see the module docs). A constraint whose
    /// covariance cannot be inverted is an error naming its pair.
    pub fn write_g2o(&self, out: &mut impl Write) -> std::io::Result<()> {
        for (v, p) in &self.initial {
            let (t, q) = (p.translation.vector, p.rotation.coords);
            writeln!(
                out,
                "VERTEX_SE3:QUAT {v} {:.17e} {:.17e} {:.17e} {:.17e} {:.17e} {:.17e} {:.17e}",
                t.x, t.y, t.z, q.x, q.y, q.z, q.w
            )?;
        }
        writeln!(out, "FIX {}", self.reference)?;
        for c in &self.constraints {
            let info = c.covariance.try_inverse().ok_or_else(|| {
                std::io::Error::new(
                    std::io::ErrorKind::InvalidData,
                    format!("constraint {}->{}: covariance not invertible", c.a, c.b),
                )
            })?;
            let r = c.a_from_b.rotation.to_rotation_matrix().into_inner();
            let mut b = Matrix6::zeros();
            b.fixed_view_mut::<3, 3>(0, 0).copy_from(&r);
            b.fixed_view_mut::<3, 3>(3, 3).copy_from(&r);
            let local = b.transpose() * ((info + info.transpose()) * 0.5) * b;
            let (t, q) = (c.a_from_b.translation.vector, c.a_from_b.rotation.coords);
            write!(
                out,
                "EDGE_SE3:QUAT {} {} {:.17e} {:.17e} {:.17e} {:.17e} {:.17e} {:.17e} {:.17e}",
                c.a, c.b, t.x, t.y, t.z, q.x, q.y, q.z, q.w
            )?;
            for i in 0..6 {
                for j in i..6 {
                    write!(out, " {:.17e}", local[(i, j)])?;
                }
            }
            writeln!(out)?;
        }
        Ok(())
    }

    /// shoal's objective at `poses`: `Σ ρ(rᵀ Λ r)` over the constraints
    /// (`None` when a constraint's vehicle has no pose or its covariance
    /// cannot be inverted).
    pub fn cost(&self, poses: &BTreeMap<VehicleId, Pose>, kernel: RobustKernel) -> Option<f64> {
        self.constraints.iter().try_fold(0.0, |sum, c| {
            let info = c.covariance.try_inverse()?;
            let s = edge_chi2(poses.get(&c.a)?, poses.get(&c.b)?, &c.a_from_b, &info);
            Some(sum + kernel.cost(s))
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proto::geometry::{pose_from_xyz_rpy, Cov6};

    #[test]
    fn the_g2o_text_holds_every_vertex_the_gauge_and_each_edge_with_21_entries() {
        let p = pose_from_xyz_rpy([2.0, 0.5, 0.1], [0.1, -0.2, 0.3]);
        let g = PoseGraph {
            reference: 10,
            initial: BTreeMap::from([(10, Pose::identity()), (15, p)]),
            constraints: vec![Constraint {
                a: 10,
                b: 15,
                a_from_b: p,
                covariance: Cov6::identity() * 1e-4,
            }],
        };
        let mut text = Vec::new();
        g.write_g2o(&mut text).expect("written");
        let text = String::from_utf8(text).expect("utf-8");
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines.len(), 4, "{text}");
        assert!(lines[0].starts_with("VERTEX_SE3:QUAT 10 "));
        assert_eq!(lines[2], "FIX 10");
        let edge: Vec<f64> = lines[3]
            .split_whitespace()
            .skip(3)
            .map(|v| v.parse().expect("number"))
            .collect();
        assert_eq!(edge.len(), 7 + 21);
        // An isotropic information stays isotropic in the local frame: 1e4 on the diagonal.
        assert!((edge[7] - 1e4).abs() < 1e-6 && edge[8].abs() < 1e-9);
        assert!((edge[7 + 20] - 1e4).abs() < 1e-6);
        let at_start = g.cost(&g.initial, RobustKernel::None).expect("cost");
        assert!(at_start < 1e-20, "the start is the measurement: {at_start}");
        let moved = BTreeMap::from([(10, Pose::identity())]);
        assert_eq!(g.cost(&moved, RobustKernel::None), None, "15 has no pose");
    }
}
