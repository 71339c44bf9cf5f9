"""Solve a shoal pose graph (g2o, `shoal_fusion::export`) with gtsam.

Usage: python3 solve_g2o.py GRAPH.g2o REFERENCE_ID
Prints every optimized vertex as `VERTEX_SE3:QUAT id x y z qx qy qz qw`,
then `ERROR <gtsam's final error>` and `ITERATIONS <n>`. The reference vehicle
is held at its initial pose (the file's FIX line) by a tight prior; plain
least squares, no robust kernel. Only gtsam reads the file: an independent
check of shoal's own Levenberg-Marquardt.
"""
import sys

import gtsam


def main() -> None:
    path, reference = sys.argv[1], int(sys.argv[2])
    graph, initial = gtsam.readG2o(path, True)
    prior = gtsam.noiseModel.Isotropic.Sigma(6, 1e-9)
    graph.add(gtsam.PriorFactorPose3(reference, initial.atPose3(reference), prior))
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-14)
    params.setAbsoluteErrorTol(1e-14)
    params.setMaxIterations(200)
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, initial, params)
    result = optimizer.optimize()
    for key in sorted(result.keys()):
        p = result.atPose3(key)
        t, q = p.translation(), p.rotation().toQuaternion()
        values = [float(x) for x in (t[0], t[1], t[2], q.x(), q.y(), q.z(), q.w())]
        print(f"VERTEX_SE3:QUAT {key} " + " ".join(repr(x) for x in values))
    print(f"ERROR {float(graph.error(result))!r}")
    print(f"ITERATIONS {optimizer.iterations()}")


if __name__ == "__main__":
    main()
