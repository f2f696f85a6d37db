"""Score extracted landmarks against the simulator's ground truth (front-end accuracy).

A GT landmark is *recovered* when an extracted landmark of the same type matches it one-to-one
(linear-sum assignment) within the gates: direction/normal within ``max_angle_deg``, the
extracted anchor within ``max_offset`` of the GT line/plane, and the anchor inside the GT
object's extent (so that two coplanar facades of neighbouring houses are not confused).
The anchor error is that distance from the extracted anchor to the GT line/plane: the GT
anchor is the centre of the whole object while an extracted anchor is the centroid of the part
the scan saw, so their Euclidean distance says more about visibility than about accuracy.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment

from graffmatch.errors import InvalidInputError
from graffmatch.geometry.landmarks import LandmarkSet, LandmarkType


def _pair_errors(ext: LandmarkSet, gt: LandmarkSet, kind: int):
    """(n_ext, n_gt) angle [deg], offset [m] and in-extent flag for one landmark type."""
    ue, ug = ext.directions, gt.directions
    ang = np.degrees(np.arccos(np.clip(np.abs(ue @ ug.T), 0.0, 1.0)))
    d = ext.anchors[:, None, :] - gt.anchors[None, :, :]  # (ne, ng, 3)
    along = np.einsum("ijk,jk->ij", d, ug)
    if kind == LandmarkType.LINE:
        offset = np.linalg.norm(d - along[..., None] * ug[None], axis=2)
        half = np.nan_to_num(gt.attributes.get("extent", np.full(len(gt), np.inf)), nan=np.inf) / 2
        inside = np.abs(along) <= half[None] + 1.0
    else:
        offset = np.abs(along)
        B = gt.bases  # (ng, 3, 2) in-plane axes
        uv = np.einsum("ijk,jkl->ijl", d, B)
        box = gt.attributes.get("box", np.full((len(gt), 2), np.inf))
        box = np.nan_to_num(np.asarray(box, float).reshape(len(gt), 2), nan=np.inf)
        # the box sides are not tied to the basis axes: use the larger half-side as a radius
        inside = np.linalg.norm(uv, axis=2) <= 0.5 * np.hypot(box[:, 0], box[:, 1])[None] + 1.0
    return ang, offset, inside


def extraction_accuracy(
    extracted: LandmarkSet,
    gt: LandmarkSet,
    max_angle_deg: float = 10.0,
    max_offset: float = 0.5,
) -> dict:
    """Recovered fraction, precision and errors of ``extracted`` vs ``gt`` (same frame).

    ``gt`` should hold only the GT landmarks the scan actually sampled (e.g.
    :func:`gt_landmarks_in_scan` with a support threshold). Returns per type ("lines",
    "planes"): n_gt, n_extracted, n_matched, recovered (n_matched / n_gt), precision
    (n_matched / n_extracted), angle_deg and anchor_m (median and p90 over matches), and the
    matches themselves as (extracted index, gt index) pairs.
    """
    if max_angle_deg <= 0 or max_offset <= 0:
        raise InvalidInputError("gates must be positive")
    out: dict = {}
    for kind, name in ((LandmarkType.LINE, "lines"), (LandmarkType.PLANE, "planes")):
        ie, ig = extracted.indices_of_type(kind), gt.indices_of_type(kind)
        res = {"n_gt": int(len(ig)), "n_extracted": int(len(ie)), "n_matched": 0, "matches": []}
        ang_m = off_m = np.zeros(0)
        if len(ie) and len(ig):
            ang, off, inside = _pair_errors(extracted[ie], gt[ig], int(kind))
            ok = (ang <= max_angle_deg) & (off <= max_offset) & inside
            cost = np.where(ok, ang / max_angle_deg + off / max_offset, 1e6)
            r, c = linear_sum_assignment(cost)
            keep = ok[r, c]
            r, c = r[keep], c[keep]
            ang_m, off_m = ang[r, c], off[r, c]
            res["n_matched"] = int(len(r))
            res["matches"] = np.stack([ie[r], ig[c]], axis=1).tolist()
        res["recovered"] = res["n_matched"] / res["n_gt"] if res["n_gt"] else float("nan")
        res["precision"] = (
            res["n_matched"] / res["n_extracted"] if res["n_extracted"] else float("nan")
        )
        for key, v in (("angle_deg", ang_m), ("anchor_m", off_m)):
            res[key] = {
                "median": float(np.median(v)) if len(v) else float("nan"),
                "p90": float(np.percentile(v, 90)) if len(v) else float("nan"),
            }
        out[name] = res
    return out
