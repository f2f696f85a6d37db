"""Interactive 3D view of a landmark match: the paper's Fig. 1, as one self-contained HTML file.

The page shows, in the *target* frame:

- both scans, downsampled, in two colours, with the sensor origins and their axes;
- poles as thick segments along their axis and planes as translucent patches;
- the selected correspondences as lines between the landmark anchors, green for inliers and
  red for outliers when the ground truth is known (purple otherwise);
- buttons that toggle between the source placed by the estimate (after alignment), the source
  in its own frame (before alignment), and the source beside the target (readable "before").

plotly.js is embedded (``include_plotlyjs=True``) so the file opens offline, with no CDN.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from graffmatch.errors import InvalidInputError
from graffmatch.geometry.landmarks import LandmarkSet, LandmarkType
from graffmatch.geometry.transforms import check_transform, transform_points

#: Runs after plotly has drawn: marks <body> so that a headless browser test can tell a rendered
#: scene (a WebGL canvas inside the plot) from a page that failed, and records page errors.
RENDERED_MARKER_JS = """
(function () {
  var gd = document.getElementById('{plot_id}');
  var canvas = gd ? gd.querySelector('canvas') : null;
  var ok = !!(gd && gd._fullLayout && gd.data && gd.data.length && canvas);
  document.body.setAttribute('data-graffmatch-rendered', ok ? '1' : '0');
  document.body.setAttribute('data-graffmatch-traces', gd && gd.data ? gd.data.length : 0);
  document.body.setAttribute('data-graffmatch-viewport', window.innerWidth + 'x' + window.innerHeight);
  window.addEventListener('error', function (e) {
    document.body.setAttribute('data-graffmatch-error', String(e.message));
  });
})();
"""

PAGE_STYLE = (
    '<meta charset="utf-8"><title>GraffMatch match view</title>'
    "<style>html, body { margin: 0; height: 100%; overflow: hidden; }"
    " body > div { height: 100%; }</style>"
)

SOURCE_COLOR = "#1f77b4"
TARGET_COLOR = "#ff7f0e"
SOURCE_LANDMARK_COLOR = "#0b3d91"
TARGET_LANDMARK_COLOR = "#b34700"
INLIER_COLOR = "#2ca02c"
OUTLIER_COLOR = "#d62728"
UNKNOWN_COLOR = "#9467bd"
AXIS_COLORS = ("#e41a1c", "#4daf4a", "#377eb8")

#: Fallback sizes [m] when a landmark carries neither an extent attribute nor support points.
DEFAULT_POLE_LENGTH = 3.0
DEFAULT_PLANE_SIDE = 4.0


@dataclass(frozen=True)
class Placement:
    """One way of drawing the source scan: a name for the button and a 4x4 T_display_source."""

    label: str
    T_display_source: NDArray[np.float64]


def downsample(points: ArrayLike | None, max_points: int, seed: int = 0) -> NDArray[np.float32]:
    """Deterministic uniform subset of at most ``max_points`` rows (x, y, z only).

    A uniform subset keeps the look of the scan (dense near the sensor) which is what people
    expect from a LiDAR viewer, and is reproducible for the same seed.
    """
    if points is None:
        return np.zeros((0, 3), np.float32)
    P = np.asarray(points)
    if P.ndim != 2 or P.shape[1] < 3:
        raise InvalidInputError(f"points must be (N, 3+) arrays, got shape {P.shape}")
    P = P[:, :3]
    P = P[np.all(np.isfinite(P), axis=1)]
    if len(P) > max_points > 0:
        idx = np.sort(np.random.default_rng(seed).choice(len(P), max_points, replace=False))
        P = P[idx]
    return np.ascontiguousarray(P, dtype=np.float32)


def _segments_xyz(starts: np.ndarray, ends: np.ndarray) -> tuple[np.ndarray, ...]:
    """Interleave start/end/NaN so that many segments live in one Scatter3d trace."""
    n = len(starts)
    out = np.full((3 * n, 3), np.nan)
    out[0::3] = starts
    out[1::3] = ends
    return out[:, 0], out[:, 1], out[:, 2]


def _support_uv(
    ls: LandmarkSet, idx: np.ndarray, k: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Support points of landmarks ``idx`` in basis coordinates relative to the anchor.

    Returns (has_points (len(idx),) bool, owner (M,) position in ``idx[has]``, uv (M, k),
    first (len(idx[has]),) start of each group), gathered without Python loops.
    """
    has = np.zeros(len(idx), bool)
    empty = (has, np.zeros(0, np.int64), np.zeros((0, k)), np.zeros(0, np.int64))
    if ls.points is None or ls.point_offsets is None or len(idx) == 0:
        return empty
    counts = ls.point_offsets[idx + 1] - ls.point_offsets[idx]
    has = counts > 0
    if not np.any(has):
        return (has, *empty[1:])
    sel = idx[has]
    c = counts[has]
    first = np.concatenate([[0], np.cumsum(c)[:-1]])
    owner = np.repeat(np.arange(len(sel)), c)
    gather = np.repeat(ls.point_offsets[sel], c) + (np.arange(c.sum()) - np.repeat(first, c))
    P = ls.points[gather].astype(np.float64) - ls.anchors[sel][owner]
    uv = np.einsum("ni,nik->nk", P, ls.bases[sel][owner][:, :, :k])
    return has, owner, uv, first


def pole_segments(ls: LandmarkSet) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(indices, start, end) of every line landmark, in the set's frame.

    The segment spans the support points along the axis when they are present, else
    ``extent`` centred on the anchor, else ``DEFAULT_POLE_LENGTH``.
    """
    idx = ls.indices_of_type(LandmarkType.LINE)
    d = ls.bases[idx, :, 0]
    a = ls.anchors[idx]
    half = np.full(len(idx), DEFAULT_POLE_LENGTH / 2)
    if "extent" in ls.attributes:
        ext = np.asarray(ls.attributes["extent"], float).reshape(len(ls), -1)[idx, 0]
        ok = np.isfinite(ext) & (ext > 0)
        half[ok] = ext[ok] / 2
    lo = -half
    hi = half.copy()
    has, _, uv, first = _support_uv(ls, idx, 1)
    if np.any(has):
        slo = np.minimum.reduceat(uv[:, 0], first)
        shi = np.maximum.reduceat(uv[:, 0], first)
        ok = shi > slo
        pos = np.flatnonzero(has)[ok]
        lo[pos], hi[pos] = slo[ok], shi[ok]
    return idx, a + lo[:, None] * d, a + hi[:, None] * d


def plane_quads(ls: LandmarkSet) -> tuple[np.ndarray, np.ndarray]:
    """(indices, corners (n, 4, 3)) of a rectangle per plane landmark, in the set's frame.

    The rectangle is the minimum-area rectangle of the support points when they are present,
    else the ``box`` sides (or a square of the ``extent`` area) centred on the anchor, the
    larger side horizontal for non-horizontal planes.
    """
    idx = ls.indices_of_type(LandmarkType.PLANE)
    n = len(idx)
    half = np.full((n, 2), DEFAULT_PLANE_SIDE / 2)
    if "extent" in ls.attributes:
        area = np.asarray(ls.attributes["extent"], float).reshape(len(ls), -1)[idx, 0]
        ok = np.isfinite(area) & (area > 0)
        half[ok] = np.sqrt(area[ok])[:, None] / 2
    if "box" in ls.attributes:
        box = np.asarray(ls.attributes["box"], float).reshape(len(ls), -1)
        if box.shape[1] >= 2:
            box = box[idx, :2]
            ok = np.all(np.isfinite(box) & (box > 0), axis=1)
            half[ok] = -np.sort(-box[ok], axis=1) / 2  # larger side first
    lo, hi = -half, half.copy()
    # Without support points the box orientation is unknown: lay the larger side horizontally
    # (facades, walls, boards are drawn upright); horizontal planes keep their basis.
    normal = ls.directions[idx]
    horiz = np.cross([0.0, 0.0, 1.0], normal)
    hn = np.linalg.norm(horiz, axis=1)
    upright = hn > 0.1
    u = ls.bases[idx, :, 0].copy()
    v = ls.bases[idx, :, 1].copy()
    u[upright] = horiz[upright] / hn[upright, None]
    v[upright] = np.cross(normal[upright], u[upright])
    a = ls.anchors[idx]
    has, owner, uv, first = _support_uv(ls, idx, 2)
    if np.any(has):
        # Minimum-area rectangle over a 1-degree grid of in-plane angles (vectorised over
        # points x angles): it orients the patch like its support rather than like the
        # arbitrary basis, and unlike PCA it is stable for near-square patches.
        angles = np.deg2rad(np.arange(0.0, 90.0, 1.0))
        ca, sa = np.cos(angles), np.sin(angles)
        pu = uv[:, :1] * ca + uv[:, 1:] * sa  # (M, n_angles)
        pv = -uv[:, :1] * sa + uv[:, 1:] * ca
        span_u = np.maximum.reduceat(pu, first, axis=0) - np.minimum.reduceat(pu, first, axis=0)
        span_v = np.maximum.reduceat(pv, first, axis=0) - np.minimum.reduceat(pv, first, axis=0)
        best = np.argmin(span_u * span_v, axis=1)
        c, s_ = ca[best], sa[best]
        rot_uv = np.c_[
            uv[:, 0] * c[owner] + uv[:, 1] * s_[owner], -uv[:, 0] * s_[owner] + uv[:, 1] * c[owner]
        ]
        slo = np.minimum.reduceat(rot_uv, first, axis=0)
        shi = np.maximum.reduceat(rot_uv, first, axis=0)
        ok = np.all(shi > slo, axis=1)
        pos = np.flatnonzero(has)[ok]
        cu, su = c[ok, None], s_[ok, None]
        u0, v0 = ls.bases[idx[pos], :, 0], ls.bases[idx[pos], :, 1]  # the basis of uv
        u[pos] = cu * u0 + su * v0
        v[pos] = -su * u0 + cu * v0
        lo[pos], hi[pos] = slo[ok], shi[ok]
    corners = np.stack(
        [
            a + lo[:, :1] * u + lo[:, 1:] * v,
            a + hi[:, :1] * u + lo[:, 1:] * v,
            a + hi[:, :1] * u + hi[:, 1:] * v,
            a + lo[:, :1] * u + hi[:, 1:] * v,
        ],
        axis=1,
    )
    return idx, corners


def _hover(ls: LandmarkSet, idx: np.ndarray, who: str) -> list[str]:
    names = {0: "point", 1: "pole", 2: "plane"}
    out = []
    for i in idx:
        parts = [f"{who} #{int(i)} {names[int(ls.types[i])]}"]
        for key in ("extent", "support", "radius", "rms"):
            if key in ls.attributes:
                val = np.asarray(ls.attributes[key][i], float).reshape(-1)
                if val.size and np.isfinite(val[0]):
                    parts.append(f"{key}={val[0]:.3g}")
        out.append("<br>".join(parts))
    return out


def _landmark_traces(ls: LandmarkSet, who: str, color: str, group: str) -> list:
    import plotly.graph_objects as go

    traces = []
    idx, s, e = pole_segments(ls)
    if len(idx):
        x, y, z = _segments_xyz(s, e)
        text = np.repeat(_hover(ls, idx, who), 3).tolist()
        traces.append(
            go.Scatter3d(
                x=x,
                y=y,
                z=z,
                mode="lines",
                line={"color": color, "width": 9},
                name=f"{who} poles ({len(idx)})",
                legendgroup=group,
                text=text,
                hoverinfo="text",
            )
        )
    idx, corners = plane_quads(ls)
    if len(idx):
        verts = corners.reshape(-1, 3)
        base = 4 * np.arange(len(idx))
        i = np.concatenate([base, base])
        j = np.concatenate([base + 1, base + 2])
        k = np.concatenate([base + 2, base + 3])
        traces.append(
            go.Mesh3d(
                x=verts[:, 0],
                y=verts[:, 1],
                z=verts[:, 2],
                i=i,
                j=j,
                k=k,
                color=color,
                opacity=0.25,
                flatshading=True,
                name=f"{who} planes ({len(idx)})",
                legendgroup=group,
                showlegend=True,
                hoverinfo="text",
                text=np.repeat(_hover(ls, idx, who), 4).tolist(),
            )
        )
        # Outline so that coplanar neighbours stay distinguishable.
        ring = np.concatenate([corners, corners[:, :1], np.full((len(idx), 1, 3), np.nan)], axis=1)
        ring = ring.reshape(-1, 3)
        traces.append(
            go.Scatter3d(
                x=ring[:, 0],
                y=ring[:, 1],
                z=ring[:, 2],
                mode="lines",
                line={"color": color, "width": 3},
                legendgroup=group,
                showlegend=False,
                hoverinfo="skip",
                name=f"{who} plane outlines",
            )
        )
    pts = ls.indices_of_type(LandmarkType.POINT)
    if len(pts):
        traces.append(
            go.Scatter3d(
                x=ls.anchors[pts, 0],
                y=ls.anchors[pts, 1],
                z=ls.anchors[pts, 2],
                mode="markers",
                marker={"color": color, "size": 5, "symbol": "diamond"},
                name=f"{who} points ({len(pts)})",
                legendgroup=group,
                text=_hover(ls, pts, who),
                hoverinfo="text",
            )
        )
    return traces


def _axes_traces(T: np.ndarray, length: float, who: str, group: str) -> list:
    import plotly.graph_objects as go

    o = T[:3, 3]
    traces = [
        go.Scatter3d(
            x=[o[0]],
            y=[o[1]],
            z=[o[2]],
            mode="markers+text",
            text=[f"{who} sensor"],
            textposition="top center",
            marker={"size": 5, "color": "black"},
            name=f"{who} origin",
            legendgroup=group,
            showlegend=False,
        )
    ]
    for axis, color in enumerate(AXIS_COLORS):
        tip = o + length * T[:3, axis]
        traces.append(
            go.Scatter3d(
                x=[o[0], tip[0]],
                y=[o[1], tip[1]],
                z=[o[2], tip[2]],
                mode="lines",
                line={"color": color, "width": 6},
                legendgroup=group,
                showlegend=False,
                hoverinfo="skip",
                name=f"{who} {'xyz'[axis]}-axis",
            )
        )
    return traces


def _correspondence_traces(
    src_anchors: np.ndarray,
    tgt_anchors: np.ndarray,
    inlier_mask: np.ndarray | None,
    assoc: np.ndarray,
) -> list:
    import plotly.graph_objects as go

    labels = np.array(
        [f"association {k}: source #{i} ↔ target #{j}" for k, (i, j) in enumerate(assoc)],
        dtype=object,
    )

    traces = []
    if inlier_mask is None:
        groups = [("correspondences", np.ones(len(src_anchors), bool), UNKNOWN_COLOR)]
    else:
        groups = [
            ("inliers", inlier_mask, INLIER_COLOR),
            ("outliers", ~inlier_mask, OUTLIER_COLOR),
        ]
    for name, sel, color in groups:
        x, y, z = _segments_xyz(src_anchors[sel], tgt_anchors[sel])
        traces.append(
            go.Scatter3d(
                x=x,
                y=y,
                z=z,
                mode="lines",
                line={"color": color, "width": 5},
                name=f"{name} ({int(sel.sum())})",
                legendgroup=name,
                text=np.repeat(labels[sel], 3).tolist(),
                hoverinfo="text",
            )
        )
    return traces


def _points_trace(P: np.ndarray, color: str, name: str, group: str, size: float):
    import plotly.graph_objects as go

    return go.Scatter3d(
        x=P[:, 0],
        y=P[:, 1],
        z=P[:, 2],
        mode="markers",
        marker={"size": size, "color": color, "opacity": 0.55},
        name=name,
        legendgroup=group,
        hoverinfo="skip",
    )


def _side_by_side(
    target_extent: np.ndarray, source_extent: np.ndarray, margin: float
) -> np.ndarray:
    """T_display_source that puts the raw source just beyond the target along +y."""
    T = np.eye(4)
    T[1, 3] = target_extent[1, 1] - source_extent[0, 1] + margin
    return T


def _extent(*arrays: np.ndarray) -> np.ndarray:
    A = np.concatenate([a.reshape(-1, 3) for a in arrays if a.size])
    A = A[np.all(np.isfinite(A), axis=1)]
    if len(A) == 0:
        return np.zeros((2, 3))
    return np.stack([A.min(axis=0), A.max(axis=0)])


def check_match(
    source_landmarks: LandmarkSet,
    target_landmarks: LandmarkSet,
    T_target_source: ArrayLike,
    associations: ArrayLike,
    inlier_mask: ArrayLike | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.int64], NDArray[np.bool_] | None]:
    """(T, associations (k, 2), inlier mask or None) of a match to draw, checked."""
    T = check_transform(T_target_source, "T_target_source")
    assoc = np.asarray(associations, dtype=np.int64).reshape(-1, 2)
    if len(assoc) and (
        assoc.min() < 0
        or assoc[:, 0].max() >= len(source_landmarks)
        or assoc[:, 1].max() >= len(target_landmarks)
    ):
        raise InvalidInputError("associations index beyond the landmark sets")
    mask = None
    if inlier_mask is not None:
        mask = np.asarray(inlier_mask, dtype=bool).reshape(-1)
        if mask.shape != (len(assoc),):
            raise InvalidInputError(
                f"inlier_mask must have one entry per association ({len(assoc)}), got {mask.shape}"
            )
    return T, assoc, mask


def match_figure(
    source_landmarks: LandmarkSet,
    target_landmarks: LandmarkSet,
    T_target_source: ArrayLike,
    associations: ArrayLike,
    source_points: ArrayLike | None = None,
    target_points: ArrayLike | None = None,
    inlier_mask: ArrayLike | None = None,
    title: str = "GraffMatch",
    info: Mapping[str, object] | None = None,
    max_points: int = 25_000,
    point_size: float = 1.5,
    axis_length: float = 2.0,
    initial: str = "after",
):
    """Build the plotly figure (see :func:`write_match_view`); useful to embed in reports."""
    import plotly.graph_objects as go

    T, assoc, mask = check_match(
        source_landmarks, target_landmarks, T_target_source, associations, inlier_mask
    )
    src_pts = downsample(source_points, max_points, seed=1)
    tgt_pts = downsample(target_points, max_points, seed=2)

    src_raw_ext = _extent(src_pts, source_landmarks.anchors, np.zeros(3))
    tgt_ext = _extent(tgt_pts, target_landmarks.anchors, np.zeros(3))
    margin = 0.1 * max(float(np.ptp(tgt_ext[:, 1])), 10.0)
    placements = [
        Placement("After: aligned by T_target_source", T),
        Placement("Before: raw frames", np.eye(4)),
        Placement("Before: side by side", _side_by_side(tgt_ext, src_raw_ext, margin)),
    ]

    fig = go.Figure()
    owner: list[int] = []  # -1: always visible (target), p: visible in placement p

    def add(traces: Sequence, state: int) -> None:
        for tr in traces:
            fig.add_trace(tr)
            owner.append(state)

    if len(tgt_pts):
        add([_points_trace(tgt_pts, TARGET_COLOR, "target scan", "target", point_size)], -1)
    add(_landmark_traces(target_landmarks, "target", TARGET_LANDMARK_COLOR, "target lm"), -1)
    add(_axes_traces(np.eye(4), axis_length, "target", "target"), -1)

    for p, place in enumerate(placements):
        Tp = place.T_display_source
        placed = source_landmarks.transform(Tp)
        traces = []
        if len(src_pts):
            traces.append(
                _points_trace(
                    transform_points(Tp, src_pts).astype(np.float32),
                    SOURCE_COLOR,
                    "source scan",
                    "source",
                    point_size,
                )
            )
        traces += _landmark_traces(placed, "source", SOURCE_LANDMARK_COLOR, "source lm")
        traces += _axes_traces(Tp, axis_length, "source", "source")
        if len(assoc):
            traces += _correspondence_traces(
                placed.anchors[assoc[:, 0]], target_landmarks.anchors[assoc[:, 1]], mask, assoc
            )
        add(traces, p)

    owner_arr = np.asarray(owner)
    states = {"after": 0, "raw": 1, "side": 2}
    if initial not in states:
        raise InvalidInputError(f"initial must be one of {sorted(states)}, got {initial!r}")
    shown = states[initial]
    for trace, o in zip(fig.data, owner_arr, strict=True):
        trace.visible = bool(o in (-1, shown))
    buttons = [
        {
            "label": place.label,
            "method": "restyle",
            "args": [{"visible": [bool(o in (-1, p)) for o in owner_arr]}],
        }
        for p, place in enumerate(placements)
    ]
    subtitle = ""
    if info:
        subtitle = "<br><sup>" + " · ".join(f"{k}: {v}" for k, v in info.items()) + "</sup>"
    fig.update_layout(
        title={"text": f"{title}{subtitle}", "x": 0.01, "xanchor": "left"},
        scene={
            "aspectmode": "data",
            "xaxis_title": "x [m]",
            "yaxis_title": "y [m]",
            "zaxis_title": "z [m]",
            "camera": {"eye": {"x": -0.9, "y": -1.3, "z": 0.9}},
        },
        updatemenus=[
            {
                "type": "buttons",
                "direction": "right",
                "buttons": buttons,
                "active": shown,
                "x": 0.01,
                "xanchor": "left",
                "y": 1.0,
                "yanchor": "top",
                "pad": {"t": 4, "r": 4},
            }
        ],
        legend={"itemsizing": "constant", "x": 1.0, "xanchor": "right", "y": 0.95},
        margin={"l": 0, "r": 0, "t": 70, "b": 0},
        paper_bgcolor="white",
    )
    return fig


def write_match_view(
    path: str | Path,
    source_landmarks: LandmarkSet,
    target_landmarks: LandmarkSet,
    T_target_source: ArrayLike,
    associations: ArrayLike,
    source_points: ArrayLike | None = None,
    target_points: ArrayLike | None = None,
    inlier_mask: ArrayLike | None = None,
    title: str = "GraffMatch",
    info: Mapping[str, object] | None = None,
    max_points: int = 25_000,
    initial: str = "after",
    plotlyjs: str = "embed",
) -> Path:
    """Write the interactive match view as ONE self-contained HTML file and return its path.

    ``T_target_source`` maps source-frame points into the target frame (the display frame).
    ``associations`` is (k, 2) indices (source, target). ``inlier_mask`` (k,) colours the
    correspondences green/red when the ground truth is known. Points are (N, 3+) arrays in each
    scan's own frame [m]; at most ``max_points`` of each are drawn. ``initial`` picks the
    state shown first: "after" (aligned), "raw" (before, own frames) or "side" (side by side).
    ``plotlyjs="directory"`` writes plotly.js once as ``plotly.min.js`` beside the page and
    references it (still offline; for report folders with many views), instead of embedding it.
    """
    if plotlyjs not in ("embed", "directory"):
        raise InvalidInputError(f"plotlyjs must be 'embed' or 'directory', got {plotlyjs!r}")
    fig = match_figure(
        source_landmarks,
        target_landmarks,
        T_target_source,
        associations,
        source_points,
        target_points,
        inlier_mask,
        title=title,
        info=info,
        max_points=max_points,
        initial=initial,
    )
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if plotlyjs == "directory":
        js = path.parent / "plotly.min.js"
        if not js.is_file():
            from plotly.offline import get_plotlyjs

            js.write_text(get_plotlyjs(), encoding="utf-8")
    html = fig.to_html(
        include_plotlyjs=True if plotlyjs == "embed" else "plotly.min.js",
        full_html=True,
        config={"displaylogo": False, "responsive": True},
        default_width="100%",
        default_height="100%",
        post_script=RENDERED_MARKER_JS,
    )
    # Full-window plot: the plot div is 100% of a body that is 100% of the viewport.
    html = html.replace("<head>", f"<head>{PAGE_STYLE}", 1)
    path.write_text(html, encoding="utf-8")
    return path


def result_view_info(data: Mapping[str, Any]) -> dict[str, str]:
    """The info box of a view from a saved registration result (``graffmatch register`` JSON)."""
    d = {
        "associations": str(len(data["associations"])),
        "score": f"{data['score']:.2f}" if data["score"] is not None else "-",
        "κ": f"{data['kappa']:.3g}" if data["kappa"] is not None else "-",
        "valid": "yes" if data["valid"] else "no",
    }
    gt = data.get("ground_truth")
    if gt:
        d["inliers"] = f"{gt['n_inliers']}/{len(data['associations'])}"
        d["error"] = f"{gt['rotation_error_deg']:.2f}° / {gt['translation_error_m']:.2f} m"
    return d
