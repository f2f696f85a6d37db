"""Sample match views for a benchmark report: a few pairs per suite and case.

The evaluation layer cannot draw (viz sits above it), so ``graffmatch report`` adds the views
after :func:`graffmatch.evaluation.report.make_report`: for each suite built by the benchmark
and each case (1-3), it re-runs GraffMatch on evenly spaced sample pairs. For each sample it
writes the interactive 3D view (sharing one ``plotly.min.js``, offline) and a static bird's-eye
PNG. It then appends a section with links and images to the report's ``summary.md``.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from graffmatch.errors import MalformedFileError

VIEWS_DIR = "views"
SECTION_TITLE = "## Sample matches (interactive 3D views)"


def _sample(items: list, k: int) -> list:
    """``k`` evenly spaced items (deterministic; the first and last when k >= 2)."""
    if k <= 0 or not items:
        return []
    if len(items) <= k:
        return list(items)
    idx = np.unique(np.round(np.linspace(0, len(items) - 1, k)).astype(int))
    return [items[i] for i in idx]


def _scan_points(path: Path, scan_format: str) -> np.ndarray | None:
    """The scan's points for display, or None when it cannot be read as a point cloud."""
    if not path.is_file() or (path.suffix == ".bin" and scan_format != "kitti-bin"):
        return None
    from graffmatch.lidar.io import read_points

    try:
        return read_points(path)
    except (OSError, ValueError):
        return None


def benchmark_folder_of(results: Path) -> Path | None:
    """The benchmark folder (with ``benchmark.json``) of a results or benchmark folder."""
    for cand in (results, results.parent):
        if (cand / "benchmark.json").is_file():
            return cand
    return None


def write_report_views(
    bench_dir: Path,
    report_dir: Path,
    per_case: int = 1,
    matcher_config: Any = None,
    max_points: int = 20_000,
    on_pair: Callable[[str], None] | None = None,
) -> list[dict[str, Any]]:
    """Write views of ``per_case`` sample pairs per suite and case; return one entry per view."""
    from graffmatch.evaluation.loop_closures import LoopClosureDataset
    from graffmatch.evaluation.metrics import association_inlier_mask
    from graffmatch.geometry.transforms import transform_errors
    from graffmatch.matcher import GraffMatcher
    from graffmatch.viz.match_view import write_match_view
    from graffmatch.viz.plots import plot_match_topdown

    try:
        bench = json.loads((bench_dir / "benchmark.json").read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise MalformedFileError(f"{bench_dir / 'benchmark.json'}: cannot read ({exc})") from exc
    views = report_dir / VIEWS_DIR
    matcher = GraffMatcher(matcher_config)
    entries: list[dict[str, Any]] = []
    for suite, build in sorted((bench.get("build") or {}).items()):
        folder = Path(build.get("folder", ""))
        if not (folder / "pairs.json").is_file():
            continue
        ds = LoopClosureDataset.load(folder)
        for case in (1, 2, 3):
            for pair in _sample(ds.of_case(case), per_case):
                name = f"{suite}_case{case}_{pair.pair_id}"
                if on_pair is not None:
                    on_pair(name)
                src, tgt = pair.source, pair.target
                res = matcher.match(src, tgt)
                assoc = np.asarray(res.associations, np.int64).reshape(-1, 2)
                mask = association_inlier_mask(src, tgt, assoc, pair.T_target_source)
                T = np.eye(4) if res.T_target_source is None else np.asarray(res.T_target_source)
                if res.T_target_source is None:
                    rot, trans = float("inf"), float("inf")
                else:
                    rot, trans = transform_errors(T, pair.T_target_source)
                ps = _scan_points(pair.source_scan_path, ds.scan_format)
                pt = _scan_points(pair.target_scan_path, ds.scan_format)
                info = {
                    "case": case,
                    "IIR": f"{pair.iir:.3f}",
                    "distance": f"{pair.distance:.1f} m",
                    "inliers": f"{int(mask.sum())}/{len(assoc)}",
                    "error": f"{rot:.2f}° / {trans:.2f} m",
                    "valid": "yes" if res.valid else "no",
                }
                html = write_match_view(
                    views / f"{name}.html", src, tgt, T, assoc, ps, pt, mask,
                    title=f"GraffMatch on {suite}: {pair.pair_id}", info=info,
                    max_points=max_points, plotlyjs="directory",
                )  # fmt: skip
                png = plot_match_topdown(
                    src, tgt, T, assoc, ps, pt, mask, path=views / f"{name}.png",
                    max_points=max_points, title=f"{suite} case {case}: {pair.pair_id}", dpi=100,
                )  # fmt: skip
                del png
                entries.append(
                    {
                        "suite": suite,
                        "case": case,
                        "pair_id": pair.pair_id,
                        "iir": pair.iir,
                        "distance_m": pair.distance,
                        "n_associations": len(assoc),
                        "n_inliers": int(mask.sum()),
                        "rotation_error_deg": rot,
                        "translation_error_m": trans,
                        "valid": bool(res.valid),
                        "html": f"{VIEWS_DIR}/{html.name}",
                        "png": f"{VIEWS_DIR}/{name}.png",
                    }
                )
    if entries:
        (views / "index.json").write_text(
            json.dumps([{k: _finite(v) for k, v in e.items()} for e in entries], indent=2)
        )
        _append_summary(report_dir / "summary.md", entries)
    return entries


def _finite(v: Any) -> Any:
    return None if isinstance(v, float) and not np.isfinite(v) else v


def _append_summary(summary: Path, entries: list[dict[str, Any]]) -> None:
    """Replace (or add) the views section of the report's markdown summary."""
    text = summary.read_text() if summary.is_file() else ""
    if SECTION_TITLE in text:
        text = text[: text.index(SECTION_TITLE)].rstrip() + "\n"
    lines = [
        "",
        SECTION_TITLE,
        "",
        "GraffMatch re-run on sample pairs of each case: open the HTML for the 3D view "
        "(before/after toggles; green = inlier, red = outlier after ground-truth alignment).",
        "",
        "| suite | case | pair | inliers / selected | error | view |",
        "|---|---|---|---|---|---|",
    ]
    for e in entries:
        lines.append(
            f"| {e['suite']} | {e['case']} | {e['pair_id']} | {e['n_inliers']}/"
            f"{e['n_associations']} | {e['rotation_error_deg']:.2f}° / "
            f"{e['translation_error_m']:.2f} m | [3D view]({e['html']}) |"
        )
    lines.append("")
    for e in entries:
        lines.append(f"![{e['suite']} case {e['case']} {e['pair_id']}]({e['png']})")
    summary.write_text(text + "\n".join(lines) + "\n")
