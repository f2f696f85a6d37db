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
from graffmatch.geometry.transforms import transform_points
from graffmatch.viz.scene import (  # noqa: F401  (re-exported: these lived here)
    AXIS_COLORS,
    DEFAULT_PLANE_SIDE,
    DEFAULT_POLE_LENGTH,
    INLIER_COLOR,
    OUTLIER_COLOR,
    SOURCE_COLOR,
    SOURCE_LANDMARK_COLOR,
    TARGET_COLOR,
    TARGET_LANDMARK_COLOR,
    UNKNOWN_COLOR,
    check_match,
    downsample,
    plane_quads,
    pole_segments,
)

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


@dataclass(frozen=True)
class Placement:
    """One way of drawing the source scan: a name for the button and a 4x4 T_display_source."""

    label: str
    T_display_source: NDArray[np.float64]


def _segments_xyz(starts: np.ndarray, ends: np.ndarray) -> tuple[np.ndarray, ...]:
    """Interleave start/end/NaN so that many segments live in one Scatter3d trace."""
    n = len(starts)
    out = np.full((3 * n, 3), np.nan)
    out[0::3] = starts
    out[1::3] = ends
    return out[:, 0], out[:, 1], out[:, 2]


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
