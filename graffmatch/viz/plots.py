"""Static (matplotlib) pictures of a match, for reports and papers: a bird's-eye view.

The interactive view (:mod:`graffmatch.viz.match_view`) is for exploring; a report wants a
small PNG that needs no browser. :func:`plot_match_topdown` draws the same content from above:
both scans (downsampled), poles as dots, planes as their rectangles' footprints, and the
correspondences coloured by inlier status, either after alignment or side by side.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from graffmatch.geometry.landmarks import LandmarkSet
from graffmatch.geometry.transforms import transform_points
from graffmatch.viz import scene

if TYPE_CHECKING:  # pragma: no cover
    from matplotlib.axes import Axes


def _draw_landmarks(ax: Axes, ls: LandmarkSet, color: str, label: str) -> None:
    from matplotlib.collections import PolyCollection

    _, s, e = scene.pole_segments(ls)
    if len(s):
        mid = (s + e) / 2
        ax.scatter(
            mid[:, 0],
            mid[:, 1],
            s=28,
            marker="o",
            facecolor="none",
            edgecolor=color,
            linewidth=1.5,
            label=f"{label} poles",
            zorder=4,
        )
    _, corners = scene.plane_quads(ls)
    if len(corners):
        polys = PolyCollection(
            corners[:, :, :2],
            facecolor=color,
            edgecolor=color,
            alpha=0.18,
            linewidth=1.0,
            label=f"{label} planes",
            zorder=3,
        )
        ax.add_collection(polys)


def plot_match_topdown(
    source_landmarks: LandmarkSet,
    target_landmarks: LandmarkSet,
    T_target_source: ArrayLike,
    associations: ArrayLike,
    source_points: ArrayLike | None = None,
    target_points: ArrayLike | None = None,
    inlier_mask: ArrayLike | None = None,
    side_by_side: bool = False,
    title: str | None = None,
    ax: Axes | None = None,
    path: str | Path | None = None,
    max_points: int = 20_000,
    dpi: int = 150,
) -> Axes:
    """Bird's-eye view of a match in the target frame (x right, y up, metres).

    ``side_by_side`` draws the raw source shifted beside the target (before alignment, the
    correspondences readable); otherwise the source is moved by ``T_target_source``. With
    ``path`` the figure is saved as PNG (and closed when this function created it).
    """
    import matplotlib

    if ax is None:
        matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    T, assoc, mask = scene.check_match(
        source_landmarks, target_landmarks, T_target_source, associations, inlier_mask
    )
    src_pts = scene.downsample(source_points, max_points, seed=1)
    tgt_pts = scene.downsample(target_points, max_points, seed=2)
    if side_by_side:
        ext_t = np.concatenate([tgt_pts, target_landmarks.anchors, np.zeros((1, 3))])
        ext_s = np.concatenate([src_pts, source_landmarks.anchors, np.zeros((1, 3))])
        margin = 0.1 * max(float(np.ptp(ext_t[:, 1])), 10.0)
        T = np.eye(4)
        T[1, 3] = ext_t[:, 1].max() - ext_s[:, 1].min() + margin
    placed = source_landmarks.transform(T)

    own = ax is None
    if own:
        _, ax = plt.subplots(figsize=(7, 7), dpi=dpi)
    src_placed = transform_points(T, src_pts) if len(src_pts) else src_pts
    for pts, color, label in (
        (tgt_pts, scene.TARGET_COLOR, "target scan"),
        (src_placed, scene.SOURCE_COLOR, "source scan"),
    ):
        if len(pts):
            ax.scatter(pts[:, 0], pts[:, 1], s=0.3, c=color, alpha=0.5, lw=0, rasterized=True)
            ax.scatter([], [], s=12, c=color, label=label)  # legend proxy
    _draw_landmarks(ax, target_landmarks, scene.TARGET_LANDMARK_COLOR, "target")
    _draw_landmarks(ax, placed, scene.SOURCE_LANDMARK_COLOR, "source")
    if len(assoc):
        a = placed.anchors[assoc[:, 0], :2]
        b = target_landmarks.anchors[assoc[:, 1], :2]
        if mask is None:
            groups = [("correspondences", np.ones(len(assoc), bool), scene.UNKNOWN_COLOR)]
        else:
            groups = [
                ("inliers", mask, scene.INLIER_COLOR),
                ("outliers", ~mask, scene.OUTLIER_COLOR),
            ]
        for name, sel, color in groups:
            if np.any(sel):
                xs = np.stack([a[sel, 0], b[sel, 0]])
                ys = np.stack([a[sel, 1], b[sel, 1]])
                ax.plot(xs, ys, color=color, lw=1.0, alpha=0.9, zorder=5)
                ax.plot([], [], color=color, lw=1.5, label=f"{name} ({int(sel.sum())})")
    for Tp, name in ((np.eye(4), "target"), (T, "source")):
        o = Tp[:3, 3]
        ax.plot(*o[:2], marker="^", color="black", ms=7, zorder=6)
        ax.annotate(name, o[:2], textcoords="offset points", xytext=(4, 4), fontsize=7)
    ax.set_aspect("equal", adjustable="datalim")
    ax.autoscale_view()
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.legend(loc="upper right", fontsize=7, framealpha=0.8)
    ax.set_title(
        title or ("side by side (before)" if side_by_side else "after alignment"), fontsize=10
    )
    if path is not None:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        ax.figure.savefig(path, bbox_inches="tight", dpi=dpi)
        if own:
            plt.close(ax.figure)
    return ax
