#!/usr/bin/env python3
"""Open3D side of `deocc bench geometry`: times the same operations on the same PLY files and
writes times and result values to JSON. Comparison only; never on deocc's main path.

Usage: bench_open3d.py A.ply B.ply OURS_NORMALS.ply OUT.json
  A: 1M-point target cloud, B: 500k-point source cloud (A's subset moved a little),
  OURS_NORMALS: A with deocc's normals, to compare normal directions.
"""
import json
import sys
import time

try:
    import numpy as np
    import open3d as o3d
except ImportError as e:  # the caller turns exit code 3 into an install hint
    print(f"open3d is not importable: {e}", file=sys.stderr)
    sys.exit(3)


def timed(fn, repeats=1):
    best = []
    out = None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        best.append(time.perf_counter() - t0)
    best.sort()
    return best[len(best) // 2], out


def main():
    a_path, b_path, normals_path, out_path = sys.argv[1:5]
    a = o3d.io.read_point_cloud(a_path)
    b = o3d.io.read_point_cloud(b_path)
    ours = o3d.io.read_point_cloud(normals_path)
    res = {"open3d_version": o3d.__version__, "points_a": len(a.points), "points_b": len(b.points)}

    t, _ = timed(lambda: o3d.geometry.KDTreeFlann(a), 3)
    res["kdtree_build"] = {"seconds": t}

    t, d = timed(lambda: np.asarray(b.compute_point_cloud_distance(a)), 3)
    res["nearest_neighbour"] = {"seconds": t, "value": float(d.mean())}

    def chamfer():
        ab = np.asarray(a.compute_point_cloud_distance(b)).mean()
        ba = np.asarray(b.compute_point_cloud_distance(a)).mean()
        return (ab + ba) / 2
    t, c = timed(chamfer, 3)
    res["chamfer"] = {"seconds": t, "value": float(c)}

    t, down = timed(lambda: a.voxel_down_sample(0.01), 3)
    res["voxel_downsample"] = {"seconds": t, "value": len(down.points)}

    a_n = o3d.geometry.PointCloud(a)
    t, _ = timed(lambda: a_n.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(30)))
    dots = np.abs((np.asarray(a_n.normals) * np.asarray(ours.normals)).sum(axis=1))
    res["normals"] = {"seconds": t, "value": float(dots.mean())}

    crit = o3d.pipelines.registration.ICPConvergenceCriteria(relative_fitness=0.0, relative_rmse=0.0, max_iteration=30)
    for name, est in [("icp_point_to_point", o3d.pipelines.registration.TransformationEstimationPointToPoint()),
                      ("icp_point_to_plane", o3d.pipelines.registration.TransformationEstimationPointToPlane())]:
        t, r = timed(lambda: o3d.pipelines.registration.registration_icp(b, a_n, 0.05, np.eye(4), est, crit))
        res[name] = {"seconds": t, "value": float(r.inlier_rmse), "fitness": float(r.fitness)}

    with open(out_path, "w") as f:
        json.dump(res, f, indent=2)


if __name__ == "__main__":
    main()
