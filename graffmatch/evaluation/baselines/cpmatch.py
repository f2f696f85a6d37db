"""CPMatch: nearest-neighbour association of closest-point (CP) vectors (Zhou et al., pi-LSAM, 2021).

pi-LSAM parameterises a plane by its closest point to the origin, ``cp = n * d`` (the CP vector),
and associates a scan plane to a map plane by a nearest-neighbour search on CP vectors after
moving the scan plane with the current pose estimate. PLC-LiSLAM extends the CP vector to lines
(the point of the line closest to the origin). As in the GraffMatch paper's comparison there is no
odometry prior between the two places, so the pose estimate is the identity: CPMatch is a
*local* method that only succeeds for small baselines.

Algorithm (per landmark type, vectorised with a k-d tree):

1. CP vectors of both sets in their own frames (the source moved by ``T_init``, identity by
   default).
2. Mutual nearest neighbours in CP space (a source landmark and its nearest target are each
   other's nearest neighbour).
3. Gates: CP distance < ``max_cp_distance`` (1.0 m) and angle between line directions / plane
   normals < ``max_angle_deg`` (15 deg; sign-free). pi-LSAM does not publish its thresholds;
   these are generous values for LiDAR landmarks at the scale of KITTI.
4. Closed-form registration of the associations (``register_landmarks``).

Points (type 0) are associated the same way (their CP vector is the point itself).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from graffmatch.evaluation.methods import (
    LocalMethod,
    MethodKind,
    Timer,
)
from graffmatch.geometry.landmarks import LandmarkSet


def direction_angles_deg(d1: NDArray[np.float64], d2: NDArray[np.float64]) -> NDArray[np.float64]:
    """Row-wise unsigned angle [deg] between unit directions/normals (sign ambiguity ignored)."""
    c = np.abs(np.einsum("ij,ij->i", d1, d2))
    return np.degrees(np.arccos(np.clip(c, 0.0, 1.0)))


def cp_associations(
    source: LandmarkSet,
    target: LandmarkSet,
    max_cp_distance: float = 1.0,
    max_angle_deg: float = 15.0,
) -> NDArray[np.intp]:
    """(k, 2) mutual-nearest-neighbour CP associations that pass the gates, per type."""
    out = []
    cps, cpt = source.cp_vectors(), target.cp_vectors()
    ds, dt = source.directions, target.directions
    for kind in (0, 1, 2):
        si, ti = source.indices_of_type(kind), target.indices_of_type(kind)
        if len(si) == 0 or len(ti) == 0:
            continue
        dist_st, nn_st = cKDTree(cpt[ti]).query(cps[si])
        _, nn_ts = cKDTree(cps[si]).query(cpt[ti])
        mutual = nn_ts[nn_st] == np.arange(len(si))
        keep = mutual & (dist_st < max_cp_distance)
        a_s, a_t = si[keep], ti[nn_st[keep]]
        if kind > 0 and len(a_s):
            ok = direction_angles_deg(ds[a_s], dt[a_t]) < max_angle_deg
            a_s, a_t = a_s[ok], a_t[ok]
        out.append(np.stack([a_s, a_t], axis=1))
    return np.concatenate(out).astype(np.intp) if out else np.zeros((0, 2), np.intp)


@dataclass
class CPMatch(LocalMethod):
    max_cp_distance: float = 1.0
    max_angle_deg: float = 15.0
    kappa_max: float = 1e3
    T_init: NDArray[np.float64] = field(default_factory=lambda: np.eye(4))
    name: str = "CPMatch"
    kind: MethodKind = "landmark"

    def associate(
        self, moved_source: LandmarkSet, target: LandmarkSet, timer: Timer
    ) -> tuple[NDArray[np.intp], dict[str, Any]]:
        with timer.stage("association"):
            a = cp_associations(moved_source, target, self.max_cp_distance, self.max_angle_deg)
        return a, {}
