"""Summary rows and the paper's tables, from per-pair records alone.

``summarize`` turns records into one row per (suite, case, method); ``table1``/``table2`` lay
those rows out as the paper's Tables I and II; ``rho_table`` summarises the rho study. The
markdown and CSV writers live here too, so that one module owns the tables' columns.
"""

from __future__ import annotations

import csv
import json
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from graffmatch.errors import InvalidInputError
from graffmatch.evaluation import metrics as M
from graffmatch.evaluation.records import GT_METHOD, RHO_METHOD
from graffmatch.evaluation.registry import (
    GLOBAL_BASELINES,
    LOCAL_METHODS,
    TABLE_I_METHODS,
    TABLE_II_METHODS,
)
from graffmatch.evaluation.validity import is_negative, validity_stats

#: Column order of the paper's Table I, then our extra variants.
TABLE_I_ORDER = (*TABLE_I_METHODS, "GraffMatch-Naive", "GraffMatch-lines", "GraffMatch-planes")
TABLE_II_ORDER = (*TABLE_II_METHODS, "KISS-Matcher")
CLIPPER_METHODS = ("CLIPPER-Rn", "CLIPPER-CP")
BASELINES = LOCAL_METHODS + GLOBAL_BASELINES
ALL_CASES = "all"


# ----------------------------------------------------------------------------------------------
# numbers
# ----------------------------------------------------------------------------------------------
def num(x: Any) -> float:
    """Record value -> float ('inf'/'nan' strings and None included)."""
    if x is None:
        return float("nan")
    return float(x)


def is_rho_spec(method: str) -> bool:
    return method.startswith(f"{RHO_METHOD}[") and "rho=" in method


def is_ablation(method: str) -> bool:
    return method.startswith(f"{RHO_METHOD}-")


def summary_row(records: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Metrics of one group of records (one method on a set of pairs)."""
    recs = [M.PairRecord.from_dict(r) for r in records]
    if not recs:
        raise InvalidInputError("summary_row needs at least one record")
    tau_d = num(records[0].get("tau_d_deg", M.DEFAULT_TAU_D_DEG))
    kind = str(records[0].get("kind", "landmark"))
    rot = np.array([num(r["rotation_error_deg"]) for r in records])
    trans = np.array([num(r["translation_error_m"]) for r in records])
    ok = np.array([bool(r["success"]) for r in records])
    total = np.array([num(r.get("timings", {}).get("total")) for r in records])
    row: dict[str, Any] = {
        "kind": kind,
        "n": len(recs),
        "n_errors": int(sum(r.get("status") != "ok" for r in records)),
        "n_success": int(ok.sum()),
        "recall": float(ok.mean()),
        "estimate_rate": float(np.mean([r.T_target_source_est is not None for r in recs])),
        "rotation_error_deg": float(rot[ok].mean()) if ok.any() else float("nan"),
        "translation_error_m": float(trans[ok].mean()) if ok.any() else float("nan"),
        "median_ms": 1e3 * M.runtime_stats(total).get("median", float("nan")),
        "p95_ms": 1e3 * M.runtime_stats(total).get("p95", float("nan")),
        "mean_associations": float(np.mean([r.n_associations for r in recs])),
    }
    if kind == "landmark":
        oirs = np.array([r.oir(tau_d) for r in recs])
        row.update(
            auc=M.lmr_auc(oirs),
            lmr_at_0_8=M.lmr(oirs, M.DEFAULT_TAU_OIR),
            mean_oir=float(oirs.mean()),
        )
    else:
        row.update(auc=float("nan"), lmr_at_0_8=float("nan"), mean_oir=float("nan"))
    return row


def group_by(records: Iterable[Mapping[str, Any]], *keys: str) -> dict[tuple, list]:
    out: dict[tuple, list] = {}
    for r in records:
        out.setdefault(tuple(r[k] for k in keys), []).append(r)
    return out


def summarize(records: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """One row per (suite, case, method), plus case ``"all"`` per (suite, method).

    Recall, AUC and errors are over the positive pairs (loop closures). Each row also has the
    validity numbers of :mod:`~graffmatch.evaluation.validity`: per case over its positives,
    and in the ``"all"`` row over the positives *and* the suite's negative pairs (precision,
    false-positive rate on negatives, recall at 100 % precision).
    """
    positives = [r for r in records if not is_negative(r)]
    negatives = group_by([r for r in records if is_negative(r)], "suite", "method")
    rows = []
    for (suite, case, method), group in sorted(
        group_by(positives, "suite", "case", "method").items(), key=lambda kv: sort_key(kv[0])
    ):
        rows.append(
            {
                "suite": suite,
                "case": case,
                "method": method,
                **summary_row(group),
                **_validity(group),
            }
        )
    for (suite, method), group in sorted(group_by(positives, "suite", "method").items()):
        both = [*group, *negatives.get((suite, method), [])]
        rows.append(
            {
                "suite": suite,
                "case": ALL_CASES,
                "method": method,
                **summary_row(group),
                **_validity(both),
            }
        )
    return rows


def _validity(records: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    v = validity_stats(records)
    keys = ("precision", "fpr_negatives", "n_negatives", "recall_at_full_precision", "signal")
    return {k: v[k] for k in keys}


def sort_key(k: tuple) -> tuple:
    return tuple(str(x) for x in k)


def ordered(methods: Iterable[str], order: Sequence[str]) -> list[str]:
    ms = set(methods)
    head = [m for m in dict.fromkeys(order) if m in ms]
    return head + sorted(ms - set(head))


# ----------------------------------------------------------------------------------------------
# tables
# ----------------------------------------------------------------------------------------------
def fmt(x: Any, spec: str) -> str:
    x = num(x)
    return "–" if not np.isfinite(x) else format(x, spec)


def _cases(rows: Sequence[Mapping[str, Any]], suite: str) -> list[Any]:
    cs = {r["case"] for r in rows if r["suite"] == suite and r["case"] != ALL_CASES}
    return sorted(cs, key=str)


def _cell(row: Mapping[str, Any], **extra: Any) -> dict[str, Any]:
    """One method's numbers in a table row: recall and precision [%], errors (deg, cm), counts."""
    return {
        "recall_pct": 100.0 * row["recall"],
        "precision_pct": 100.0 * row.get("precision", float("nan")),
        **extra,
        "rotation_error_deg": row["rotation_error_deg"],
        "translation_error_cm": 100.0 * row["translation_error_m"],
        "n": row["n"],
        "n_errors": row["n_errors"],
    }


def table1(rows: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Table I analogue: per suite x case, recall [%], LMR AUC, R_e [deg], t_e [cm]."""
    methods = ordered(
        {r["method"] for r in rows if r["kind"] == "landmark" and not is_rho_spec(r["method"])}
        - {GT_METHOD, "GraffMatch+ICP"},
        TABLE_I_ORDER,
    )
    by = {(r["suite"], r["case"], r["method"]): r for r in rows}
    out_rows = []
    for suite in sorted({r["suite"] for r in rows}):
        for case in [*_cases(rows, suite), ALL_CASES]:
            entry: dict[str, Any] = {"suite": suite, "case": case, "methods": {}}
            ref = by.get((suite, case, GT_METHOD))
            entry["n"] = (
                ref["n"]
                if ref
                else max(
                    (by[(suite, case, m)]["n"] for m in methods if (suite, case, m) in by),
                    default=0,
                )
            )
            entry["gt_recall"] = ref["recall"] if ref else None
            for m in methods:
                r = by.get((suite, case, m))
                if r is None:
                    continue
                entry["methods"][m] = _cell(
                    r, auc=r["auc"], mean_associations=r["mean_associations"]
                ) | {"estimate_pct": 100.0 * r["estimate_rate"]}
            vals = entry["methods"]
            # Bold as in the paper: the best of the compared methods; GraffMatch's ablations
            # (Naive, lines, planes) are shown but do not compete.
            contenders = {m: v for m, v in vals.items() if not is_ablation(m)}
            for metric in ("recall_pct", "auc"):
                finite = [v[metric] for v in contenders.values() if np.isfinite(v[metric])]
                best = max(finite) if finite else None
                entry[f"best_{metric}"] = [
                    m for m, v in contenders.items() if best is not None and v[metric] == best
                ]
            out_rows.append(entry)
    return {
        "methods": methods,
        "rows": out_rows,
        "units": {"recall_pct": "%", "rotation_error_deg": "deg", "translation_error_cm": "cm"},
        "notes": "R_e and t_e are means over the successful pairs (<= 5 deg, <= 1 m).",
    }


def table2(rows: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Table II analogue: point-based methods and GraffMatch(+ICP): recall, errors, runtime."""
    present = {r["method"] for r in rows}
    methods = [m for m in TABLE_II_ORDER if m in present]
    methods += sorted(
        {r["method"] for r in rows if r["kind"] == "point"} - set(methods) - {GT_METHOD}
    )
    if "GraffMatch" in present:
        methods.append("GraffMatch")  # reference: landmarks only, no ICP
    by = {(r["suite"], r["case"], r["method"]): r for r in rows}
    out_rows = []
    for suite in sorted({r["suite"] for r in rows}):
        for case in [*_cases(rows, suite), ALL_CASES]:
            entry: dict[str, Any] = {"suite": suite, "case": case, "methods": {}}
            for m in methods:
                r = by.get((suite, case, m))
                if r is None:
                    continue
                entry["methods"][m] = _cell(r, median_ms=r["median_ms"])
            finite = [v["recall_pct"] for v in entry["methods"].values()]
            best = max(finite) if finite else None
            entry["best_recall_pct"] = [
                m for m, v in entry["methods"].items() if v["recall_pct"] == best
            ]
            entry["n"] = max((v["n"] for v in entry["methods"].values()), default=0)
            out_rows.append(entry)
    return {"methods": methods, "rows": out_rows, "units": {"median_ms": "ms"}}


def table_md(table: Mapping[str, Any], cols: Sequence[tuple[str, str, str]]) -> str:
    """Markdown: one line per (suite, case), one group of columns per method."""
    methods = table["methods"]
    head = ["suite", "case", "N"]
    for m in methods:
        head += [f"{m} {label}" for _, label, _ in cols]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for row in table["rows"]:
        vals = [str(row["suite"]), str(row["case"]), str(row["n"])]
        for m in methods:
            v = row["methods"].get(m)
            for key, _, spec in cols:
                if v is None:
                    vals.append("")
                    continue
                s = fmt(v[key], spec)
                if m in row.get(f"best_{key}", []):
                    s = f"**{s}**"
                vals.append(s)
        lines.append("| " + " | ".join(vals) + " |")
    return "\n".join(lines)


def table_long_md(table: Mapping[str, Any], cols: Sequence[tuple[str, str, str]]) -> str:
    """The same table, one line per (suite, case, method): readable at any method count."""
    head = ["suite", "case", "N", "method", *[label for _, label, _ in cols]]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for row in table["rows"]:
        for m in table["methods"]:
            v = row["methods"].get(m)
            if v is None:
                continue
            vals = [str(row["suite"]), str(row["case"]), str(row["n"]), m]
            for key, _, spec in cols:
                s = fmt(v[key], spec)
                vals.append(f"**{s}**" if m in row.get(f"best_{key}", []) else s)
            lines.append("| " + " | ".join(vals) + " |")
    return "\n".join(lines)


TABLE1_COLS = (
    ("recall_pct", "recall [%]", ".0f"),
    ("precision_pct", "precision [%]", ".0f"),
    ("auc", "AUC", ".2f"),
    ("rotation_error_deg", "R_e [deg]", ".2f"),
    ("translation_error_cm", "t_e [cm]", ".0f"),
)
#: The summary's long Table I also shows why a method fails: few associations, no estimate.
TABLE1_LONG_COLS = (
    *TABLE1_COLS,
    ("mean_associations", "#assoc", ".1f"),
    ("estimate_pct", "estimate [%]", ".0f"),
)
TABLE2_COLS = (
    ("recall_pct", "recall [%]", ".0f"),
    ("precision_pct", "precision [%]", ".0f"),
    ("rotation_error_deg", "R_e [deg]", ".2f"),
    ("translation_error_cm", "t_e [cm]", ".0f"),
    ("median_ms", "time [ms]", ".0f"),
)


def table_csv(path: Path, table: Mapping[str, Any], cols: Sequence[tuple[str, str, str]]) -> None:
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["suite", "case", "n", "method", *[k for k, _, _ in cols], "best"])
        for row in table["rows"]:
            for m, v in row["methods"].items():
                best = [k for k, _, _ in cols if m in row.get(f"best_{k}", [])]
                w.writerow(
                    [
                        row["suite"],
                        row["case"],
                        row["n"],
                        m,
                        *[repr(num(v[k])) for k, _, _ in cols],
                        ";".join(best),
                    ]
                )


def rows_csv(path: Path, rows: Sequence[Mapping[str, Any]]) -> None:
    keys: list[str] = []
    for r in rows:
        keys += [k for k in r if k not in keys]
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        for r in rows:
            w.writerow({k: (repr(v) if isinstance(v, float) else v) for k, v in r.items()})


def dump_json(path: Path, doc: Any) -> None:
    path.write_text(json.dumps(M._jsonable(doc), indent=1))


# ----------------------------------------------------------------------------------------------
# rho study
# ----------------------------------------------------------------------------------------------
def rho_table(records: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """AUC and recall of GraffMatch per rho (and suite), from the ``GraffMatch[rho=...]`` runs."""
    out = []
    rho_recs = [r for r in records if is_rho_spec(r["method"])]
    for (suite, method), group in sorted(group_by(rho_recs, "suite", "method").items()):
        rho = float(method.split("rho=")[1].rstrip("]").split(",")[0])
        s = summary_row(group)
        out.append(
            {
                "suite": suite,
                "rho": rho,
                "n": s["n"],
                "auc": s["auc"],
                "recall": s["recall"],
                "median_ms": s["median_ms"],
            }
        )
    out.sort(key=lambda r: (r["suite"], r["rho"]))
    return out
