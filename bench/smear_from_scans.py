"""Can motion smear be read off the scans themselves? (session 25: no; docs/loops.md, measured, not used)

On 8 consecutive pairs spread over a drive, ICP of scan i+1 to scan i with the scans as given, then with both
de-skewed by the pair's own motion (twice, as KISS-ICP iterates): a pair votes "smeared" when the de-skewed scans fit
better (truncated point-to-plane cost). Each drive is scored as given and de-skewed with its ground truth.

    PYTHONPATH=$PWD python bench/smear_from_scans.py /tmp/s25/cal/sim-*    # raw simulated calibration drives
"""

import sys
import time

import numpy as np
import open3d as o3d

from graffmatch.datasets.deskewed import Deskewed
from graffmatch.datasets.registry import open_dataset
from graffmatch.lidar.deskew import azimuth_times, sweep_motion, sweep_twist

VOX, RMIN, RMAX, TRUNC = 0.3, 2.0, 60.0, 0.3


def cloud(P):
    P = np.asarray(P, float)[:, :3]
    r = np.linalg.norm(P, axis=1)
    P = P[np.isfinite(r) & (r > RMIN) & (r < RMAX)]
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(P))
    return np.asarray(pc.voxel_down_sample(VOX).points)


def deskew(P, tw, s):
    if s == 0:
        return P
    T = sweep_motion(np.asarray(tw) * s, azimuth_times(P))
    return np.einsum("nij,nj->ni", T[:, :3, :3], P) + T[:, :3, 3]


def pc_n(P):
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(P))
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=1.0, max_nn=20))
    return pc


def icp(src, tgt, T0, dmax):
    est = o3d.pipelines.registration.TransformationEstimationPointToPlane()
    crit = o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=30)
    return o3d.pipelines.registration.registration_icp(src, tgt, dmax, T0, est, crit).transformation


def cost(src_P, tgt_pc, T):
    tree = o3d.geometry.KDTreeFlann(tgt_pc)
    Q = src_P @ T[:3, :3].T + T[:3, 3]
    tp, tn = np.asarray(tgt_pc.points), np.asarray(tgt_pc.normals)
    idx = np.empty(len(Q), int)
    for k, q in enumerate(Q):
        idx[k] = tree.search_knn_vector_3d(q, 1)[1][0]
    d = np.abs(np.einsum("ij,ij->i", Q - tp[idx], tn[idx]))
    return float(np.mean(np.minimum(d, TRUNC) ** 2))


def pair(A, B, n_periods=1.0):
    a, b = cloud(A), cloud(B)
    ta, tb = pc_n(a), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(b))
    T = icp(tb, ta, icp(tb, ta, np.eye(4), 2.0), 0.5)
    c0 = cost(b, ta, T)
    tw = sweep_twist(np.eye(4), T, n_periods)  # B's pose in A's frame over n_periods sweeps
    out = {
        "motion_m": float(np.linalg.norm(tw[3:])),
        "motion_deg": float(np.degrees(np.linalg.norm(tw[:3]))),
        "c0": c0,
    }
    for _ in range(2):
        a1, b1 = deskew(a, tw, 1), deskew(b, tw, 1)
        ta1 = pc_n(a1)
        T1 = icp(o3d.geometry.PointCloud(o3d.utility.Vector3dVector(b1)), ta1, T, 0.5)
        tw = sweep_twist(np.eye(4), T1, n_periods)
    out["c1"] = cost(b1, ta1, T1)
    out["ratio"] = out["c1"] / out["c0"]
    return out


def run(ds, pairs=8, n_periods=1.0):
    n = len(ds)
    idx = np.linspace(0, n - 2, pairs).round().astype(int)
    res = []
    for i in idx:
        r = pair(ds[int(i)].points, ds[int(i) + 1].points, n_periods)
        res.append({**r, "i": int(i)})
    return res


if __name__ == "__main__":
    for path in sys.argv[1:]:
        ds = open_dataset("folder", path)
        for label, d in (("as given", ds), ("deskewed GT", Deskewed(ds))):
            t0 = time.perf_counter()
            rs = run(d)
            rat = [r["ratio"] for r in rs]
            print(
                f"{path.split('/')[-1]:22s} {label:12s} {time.perf_counter() - t0:5.1f}s mot {np.median([r['motion_m'] for r in rs]):.2f}m "
                f"ratios {' '.join(f'{x:.2f}' for x in rat)}  smeared {sum(x < 1 for x in rat)}/{len(rat)}",
                flush=True,
            )
