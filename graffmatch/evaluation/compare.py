"""Comparing two studies: metric differences on the pairs both runs finished."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from graffmatch.evaluation.records import load_records
from graffmatch.evaluation.tables import summarize

COMPARE_METRICS = ("recall", "auc", "rotation_error_deg", "translation_error_m", "median_ms")


def compare_runs(dir_a: str | Path, dir_b: str | Path) -> list[dict[str, Any]]:
    """Metric differences (b - a) per (suite, case, method), on the pairs both runs finished.

    Returns rows ``{suite, case, method, n, <metric>_a, <metric>_b, <metric>_delta}``; render
    them with :func:`format_comparison`.
    """
    ra, rb = load_records(dir_a), load_records(dir_b)
    key = lambda r: (r["suite"], r["method"], r["pair_id"])  # noqa: E731
    common = {key(r) for r in ra} & {key(r) for r in rb}
    sa = {
        (s["suite"], s["case"], s["method"]): s
        for s in summarize([r for r in ra if key(r) in common])
    }
    sb = {
        (s["suite"], s["case"], s["method"]): s
        for s in summarize([r for r in rb if key(r) in common])
    }
    rows = []
    for k in sorted(set(sa) & set(sb), key=lambda k: (k[0], str(k[1]), k[2])):
        row: dict[str, Any] = {"suite": k[0], "case": k[1], "method": k[2], "n": sa[k]["n"]}
        for m in COMPARE_METRICS:
            a, b = sa[k].get(m), sb[k].get(m)
            row[f"{m}_a"], row[f"{m}_b"] = a, b
            ok = a is not None and b is not None and np.isfinite(a) and np.isfinite(b)
            row[f"{m}_delta"] = (b - a) if ok else None
        rows.append(row)
    return rows


def format_comparison(rows: Sequence[Mapping[str, Any]]) -> str:
    """Markdown table of :func:`compare_runs` rows."""
    head = ["suite", "case", "method", "n"] + [f"Δ{m}" for m in COMPARE_METRICS]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        vals = [str(r["suite"]), str(r["case"]), str(r["method"]), str(r["n"])]
        for m in COMPARE_METRICS:
            d = r[f"{m}_delta"]
            vals.append("–" if d is None else f"{d:+.3g}")
        lines.append("| " + " | ".join(vals) + " |")
    return "\n".join(lines)
