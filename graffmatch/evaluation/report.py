"""Turn a results folder into the paper's tables and figures, and check its claims.

``make_report(results_dir, out_dir)`` writes::

    summary.md                 every number below, the expectation checks, links to figures
    table1.{md,csv,json}       landmark methods per suite x case: recall, LMR AUC, R_e, t_e
    table2.{md,csv,json}       point-based methods (and GraffMatch+ICP) with runtime
    metrics.{csv,json}         every (suite, case, method) summary row
    rho.{md,csv,json}          AUC and recall of GraffMatch over rho
    expectations.{md,json}     the paper's orderings, computed from our numbers
    config.json                copy of the study config the results came from
    figures/*.png              LMR curves, error heatmaps, runtimes, rho sensitivity

Everything is computed from the per-pair records alone (no landmarks or scans needed), with the
metric definitions of :mod:`graffmatch.evaluation.metrics`.
"""

from __future__ import annotations

import csv
import json
import shutil
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from graffmatch.errors import InvalidInputError
from graffmatch.evaluation import metrics as M
from graffmatch.evaluation.runner import GT_METHOD, RHO_METHOD, load_config, load_records

#: Column order of the paper's Table I, then our extra variants.
TABLE_I_ORDER = (
    "CPMatch",
    "BruteForceRMSE",
    "ClusterMatch",
    "LiPMatch",
    "CLIPPER-Rn",
    "CLIPPER-CP",
    "GraffMatch",
    "GraffMatch-Naive",
    "GraffMatch-lines",
    "GraffMatch-planes",
)
TABLE_II_ORDER = ("GraffMatch+ICP", "FPFH+RANSAC", "ScanContext", "ScanContext+ICP", "KISS-Matcher")
LOCAL_METHODS = ("CPMatch", "BruteForceRMSE")
GLOBAL_BASELINES = ("ClusterMatch", "LiPMatch", "CLIPPER-Rn", "CLIPPER-CP")
CLIPPER_METHODS = ("CLIPPER-Rn", "CLIPPER-CP")
BASELINES = LOCAL_METHODS + GLOBAL_BASELINES
ALL_CASES = "all"


# ----------------------------------------------------------------------------------------------
# numbers
# ----------------------------------------------------------------------------------------------
def _f(x: Any) -> float:
    """Record value -> float ('inf'/'nan' strings and None included)."""
    if x is None:
        return float("nan")
    return float(x)


def _is_rho_spec(method: str) -> bool:
    return method.startswith(f"{RHO_METHOD}[") and "rho=" in method


def _is_ablation(method: str) -> bool:
    return method.startswith(f"{RHO_METHOD}-")


def summary_row(records: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Metrics of one group of records (one method on a set of pairs)."""
    recs = [M.PairRecord.from_dict(r) for r in records]
    if not recs:
        raise InvalidInputError("summary_row needs at least one record")
    tau_d = _f(records[0].get("tau_d_deg", M.DEFAULT_TAU_D_DEG))
    kind = str(records[0].get("kind", "landmark"))
    rot = np.array([_f(r["rotation_error_deg"]) for r in records])
    trans = np.array([_f(r["translation_error_m"]) for r in records])
    ok = np.array([bool(r["success"]) for r in records])
    total = np.array([_f(r.get("timings", {}).get("total")) for r in records])
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


def _group(records: Iterable[Mapping[str, Any]], *keys: str) -> dict[tuple, list]:
    out: dict[tuple, list] = {}
    for r in records:
        out.setdefault(tuple(r[k] for k in keys), []).append(r)
    return out


def summarize(records: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """One row per (suite, case, method), plus case ``"all"`` per (suite, method)."""
    rows = []
    for (suite, case, method), group in sorted(
        _group(records, "suite", "case", "method").items(), key=lambda kv: _sort_key(kv[0])
    ):
        rows.append({"suite": suite, "case": case, "method": method, **summary_row(group)})
    for (suite, method), group in sorted(_group(records, "suite", "method").items()):
        rows.append({"suite": suite, "case": ALL_CASES, "method": method, **summary_row(group)})
    return rows


def _sort_key(k: tuple) -> tuple:
    return tuple(str(x) for x in k)


def _ordered(methods: Iterable[str], order: Sequence[str]) -> list[str]:
    ms = set(methods)
    head = [m for m in dict.fromkeys(order) if m in ms]
    return head + sorted(ms - set(head))


# ----------------------------------------------------------------------------------------------
# tables
# ----------------------------------------------------------------------------------------------
def _fmt(x: Any, spec: str) -> str:
    x = _f(x)
    return "–" if not np.isfinite(x) else format(x, spec)


def _cases(rows: Sequence[Mapping[str, Any]], suite: str) -> list[Any]:
    cs = {r["case"] for r in rows if r["suite"] == suite and r["case"] != ALL_CASES}
    return sorted(cs, key=str)


def table1(rows: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Table I analogue: per suite x case, recall [%], LMR AUC, R_e [deg], t_e [cm]."""
    methods = _ordered(
        {r["method"] for r in rows if r["kind"] == "landmark" and not _is_rho_spec(r["method"])}
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
                entry["methods"][m] = {
                    "recall_pct": 100.0 * r["recall"],
                    "auc": r["auc"],
                    "rotation_error_deg": r["rotation_error_deg"],
                    "translation_error_cm": 100.0 * r["translation_error_m"],
                    "mean_associations": r["mean_associations"],
                    "estimate_pct": 100.0 * r["estimate_rate"],
                    "n": r["n"],
                    "n_errors": r["n_errors"],
                }
            vals = entry["methods"]
            # Bold as in the paper: the best of the compared methods; GraffMatch's ablations
            # (Naive, lines, planes) are shown but do not compete.
            contenders = {m: v for m, v in vals.items() if not _is_ablation(m)}
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
                entry["methods"][m] = {
                    "recall_pct": 100.0 * r["recall"],
                    "rotation_error_deg": r["rotation_error_deg"],
                    "translation_error_cm": 100.0 * r["translation_error_m"],
                    "median_ms": r["median_ms"],
                    "n": r["n"],
                    "n_errors": r["n_errors"],
                }
            finite = [v["recall_pct"] for v in entry["methods"].values()]
            best = max(finite) if finite else None
            entry["best_recall_pct"] = [
                m for m, v in entry["methods"].items() if v["recall_pct"] == best
            ]
            entry["n"] = max((v["n"] for v in entry["methods"].values()), default=0)
            out_rows.append(entry)
    return {"methods": methods, "rows": out_rows, "units": {"median_ms": "ms"}}


def _table_md(table: Mapping[str, Any], cols: Sequence[tuple[str, str, str]]) -> str:
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
                s = _fmt(v[key], spec)
                if m in row.get(f"best_{key}", []):
                    s = f"**{s}**"
                vals.append(s)
        lines.append("| " + " | ".join(vals) + " |")
    return "\n".join(lines)


def _table_long_md(table: Mapping[str, Any], cols: Sequence[tuple[str, str, str]]) -> str:
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
                s = _fmt(v[key], spec)
                vals.append(f"**{s}**" if m in row.get(f"best_{key}", []) else s)
            lines.append("| " + " | ".join(vals) + " |")
    return "\n".join(lines)


TABLE1_COLS = (
    ("recall_pct", "recall [%]", ".0f"),
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
    ("rotation_error_deg", "R_e [deg]", ".2f"),
    ("translation_error_cm", "t_e [cm]", ".0f"),
    ("median_ms", "time [ms]", ".0f"),
)


def _table_csv(path: Path, table: Mapping[str, Any], cols: Sequence[tuple[str, str, str]]) -> None:
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
                        *[repr(_f(v[k])) for k, _, _ in cols],
                        ";".join(best),
                    ]
                )


def _rows_csv(path: Path, rows: Sequence[Mapping[str, Any]]) -> None:
    keys: list[str] = []
    for r in rows:
        keys += [k for k in r if k not in keys]
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        for r in rows:
            w.writerow({k: (repr(v) if isinstance(v, float) else v) for k, v in r.items()})


def _dump(path: Path, doc: Any) -> None:
    path.write_text(json.dumps(M._jsonable(doc), indent=1))


# ----------------------------------------------------------------------------------------------
# rho study
# ----------------------------------------------------------------------------------------------
def rho_table(records: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """AUC and recall of GraffMatch per rho (and suite), from the ``GraffMatch[rho=...]`` runs."""
    out = []
    rho_recs = [r for r in records if _is_rho_spec(r["method"])]
    for (suite, method), group in sorted(_group(rho_recs, "suite", "method").items()):
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


# ----------------------------------------------------------------------------------------------
# expectations of the paper, computed
# ----------------------------------------------------------------------------------------------
def check_expectations(rows: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """Evaluate the paper's orderings on our numbers, per suite x case (never assumed).

    Each result: {id, claim, definition, per_case: [{suite, case, holds, detail}], verdict}.
    ``holds`` is None when a needed method did not run.
    """
    by = {(r["suite"], r["case"], r["method"]): r for r in rows}
    keys = sorted({(r["suite"], r["case"]) for r in rows if r["case"] != ALL_CASES}, key=_sort_key)

    def get(sc: tuple, m: str, metric: str) -> float | None:
        r = by.get((*sc, m))
        return None if r is None else _f(r[metric])

    def check(claim_id: str, claim: str, definition: str, fn) -> dict[str, Any]:
        per = []
        for sc in keys:
            holds, detail = fn(sc)
            per.append({"suite": sc[0], "case": sc[1], "holds": holds, "detail": detail})
        evaluated = [p for p in per if p["holds"] is not None]
        n_ok = sum(bool(p["holds"]) for p in evaluated)
        if not evaluated:
            verdict = "not evaluated (methods missing)"
        elif n_ok == len(evaluated):
            verdict = f"reproduced in all {len(evaluated)} suite x case cells"
        elif n_ok == 0:
            verdict = f"not reproduced in any of {len(evaluated)} suite x case cells"
        else:
            verdict = f"partly reproduced: {n_ok} of {len(evaluated)} suite x case cells"
        return {
            "id": claim_id,
            "claim": claim,
            "definition": definition,
            "per_case": per,
            "n_holds": n_ok,
            "n_evaluated": len(evaluated),
            "verdict": verdict,
        }

    def best_graffmatch(sc):
        present = [m for m in BASELINES if (*sc, m) in by]
        if (*sc, "GraffMatch") not in by or not present:
            return None, "missing"
        g_rec, g_auc = get(sc, "GraffMatch", "recall"), get(sc, "GraffMatch", "auc")
        best_rec = max(present, key=lambda m: get(sc, m, "recall"))
        best_auc = max(present, key=lambda m: get(sc, m, "auc"))
        holds = g_rec >= get(sc, best_rec, "recall") and g_auc >= get(sc, best_auc, "auc")
        # the mean number of selected associations explains most AUC gaps: a method that
        # selects 1-2 correct matches has OIR 1 but cannot register the pair
        return bool(holds), (
            f"GraffMatch recall {100 * g_rec:.0f}% / AUC {g_auc:.2f} "
            f"({get(sc, 'GraffMatch', 'mean_associations'):.1f} assoc.); best baseline recall "
            f"{best_rec} {100 * get(sc, best_rec, 'recall'):.0f}%, AUC {best_auc} "
            f"{get(sc, best_auc, 'auc'):.2f} ({get(sc, best_auc, 'mean_associations'):.1f} assoc.)"
        )

    def best_in(sc, metric: str):
        present = [m for m in BASELINES if (*sc, m) in by]
        if (*sc, "GraffMatch") not in by or not present:
            return None, "missing"
        g = get(sc, "GraffMatch", metric)
        best = max(present, key=lambda m: get(sc, m, metric))
        return bool(g >= get(sc, best, metric)), (
            f"GraffMatch {g:.2f} vs best baseline {best} {get(sc, best, metric):.2f}"
        )

    def clipper_next(sc):
        present = [m for m in BASELINES if (*sc, m) in by]
        if not all(m in present for m in CLIPPER_METHODS) or len(present) < 3:
            return None, "missing"
        ranked = sorted(present, key=lambda m: -get(sc, m, "auc"))
        top2 = set(ranked[:2])
        holds = top2 == set(CLIPPER_METHODS)
        return holds, "AUC ranking of baselines: " + " > ".join(
            f"{m} {get(sc, m, 'auc'):.2f}" for m in ranked
        )

    def local_worst(sc):
        loc = [m for m in LOCAL_METHODS if (*sc, m) in by]
        glo = [m for m in (*GLOBAL_BASELINES, "GraffMatch") if (*sc, m) in by]
        if not loc or not glo:
            return None, "missing"
        lr = float(np.mean([get(sc, m, "recall") for m in loc]))
        gr = float(np.mean([get(sc, m, "recall") for m in glo]))
        return bool(lr < gr), f"mean recall local {100 * lr:.0f}% vs global {100 * gr:.0f}%"

    def naive_below(sc):
        if (*sc, "GraffMatch") not in by or (*sc, "GraffMatch-Naive") not in by:
            return None, "missing"
        a, b = get(sc, "GraffMatch", "auc"), get(sc, "GraffMatch-Naive", "auc")
        ra, rb = get(sc, "GraffMatch", "recall"), get(sc, "GraffMatch-Naive", "recall")
        holds = (a - b) >= 0.05 and rb <= ra
        return bool(holds), (
            f"AUC GraffMatch {a:.2f} vs Naive {b:.2f} (Δ {a - b:+.2f}); recall "
            f"{100 * ra:.0f}% vs {100 * rb:.0f}%"
        )

    def fpfh_slow_weak(sc):
        if (*sc, "FPFH+RANSAC") not in by:
            return None, "missing"
        others = [m for m in (*TABLE_II_ORDER, "GraffMatch") if m != "FPFH+RANSAC"]
        others = [m for m in others if (*sc, m) in by]
        ref = [m for m in ("GraffMatch+ICP", "GraffMatch") if (*sc, m) in by]
        if not others or not ref:
            return None, "missing"
        t = get(sc, "FPFH+RANSAC", "median_ms")
        rec = get(sc, "FPFH+RANSAC", "recall")
        slower = all(t > get(sc, m, "median_ms") for m in ref)
        weaker = all(rec < get(sc, m, "recall") for m in ref)
        return bool(slower and weaker), (
            f"FPFH+RANSAC {t:.0f} ms, recall {100 * rec:.0f}%; "
            + ", ".join(
                f"{m} {get(sc, m, 'median_ms'):.0f} ms, {100 * get(sc, m, 'recall'):.0f}%"
                for m in ref
            )
        )

    return [
        check(
            "graffmatch_best",
            "GraffMatch has the highest recall and LMR AUC in every case",
            "GraffMatch recall >= and AUC >= every landmark baseline (ties count as holding)",
            best_graffmatch,
        ),
        check(
            "graffmatch_best_recall",
            "... the recall part: GraffMatch has the highest registration recall",
            "GraffMatch recall >= every landmark baseline's recall",
            lambda sc: best_in(sc, "recall"),
        ),
        check(
            "graffmatch_best_auc",
            "... the AUC part: GraffMatch has the highest LMR AUC",
            "GraffMatch AUC >= every landmark baseline's AUC",
            lambda sc: best_in(sc, "auc"),
        ),
        check(
            "clipper_next",
            "CLIPPER-Rn and CLIPPER-CP are next after GraffMatch",
            "the two CLIPPER variants have the two highest AUCs among the six baselines",
            clipper_next,
        ),
        check(
            "local_worst",
            "the local methods (CPMatch, BruteForceRMSE) are worst",
            "mean recall of the local methods < mean recall of the global methods "
            "(ClusterMatch, LiPMatch, CLIPPER-Rn, CLIPPER-CP, GraffMatch)",
            local_worst,
        ),
        check(
            "naive_below",
            "GraffMatch-Naive is clearly below GraffMatch",
            "AUC(GraffMatch) - AUC(Naive) >= 0.05 and recall(Naive) <= recall(GraffMatch)",
            naive_below,
        ),
        check(
            "fpfh_slow_weak",
            "FPFH+RANSAC is slow and weak",
            "median runtime and recall of FPFH+RANSAC: slower than and below GraffMatch+ICP "
            "and GraffMatch",
            fpfh_slow_weak,
        ),
    ]


def _expectations_md(exps: Sequence[Mapping[str, Any]]) -> str:
    lines = []
    for e in exps:
        lines.append(f"### {e['claim']}\n")
        lines.append(f"*Test:* {e['definition']}.  \n**Verdict: {e['verdict']}.**\n")
        lines.append("| suite | case | holds | numbers |\n|---|---|---|---|")
        for p in e["per_case"]:
            h = {True: "yes", False: "**no**", None: "n/a"}[p["holds"]]
            lines.append(f"| {p['suite']} | {p['case']} | {h} | {p['detail']} |")
        lines.append("")
    return "\n".join(lines)


# ----------------------------------------------------------------------------------------------
# figures
# ----------------------------------------------------------------------------------------------
def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _oirs(group: Sequence[Mapping[str, Any]]) -> np.ndarray:
    tau = _f(group[0].get("tau_d_deg", M.DEFAULT_TAU_D_DEG))
    return np.array([M.PairRecord.from_dict(r).oir(tau) for r in group])


def fig_lmr(records: Sequence[Mapping[str, Any]], methods: Sequence[str], path: Path, title: str):
    """LMR vs tau_OIR (left) and LMR at tau_OIR = 0.8 vs tau_d (right)."""
    plt = _plt()
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(12, 4.5))
    groups = _group(records, "method")
    for m in methods:
        g = groups.get((m,))
        if not g:
            continue
        style = {"color": "k", "ls": "--"} if m == GT_METHOD else {}
        t, v = M.lmr_curve(_oirs(g))
        a1.plot(t, v, label=f"{m} (AUC {np.mean(_oirs(g)):.2f})", **style)
        dists = [M.PairRecord.from_dict(r).association_distances_deg for r in g]
        td, vd = M.lmr_vs_tau_d(dists)
        a2.plot(td, vd, label=m, **style)
    a1.set(xlabel=r"$\tau_{OIR}$", ylabel="LMR", title=f"{title}: LMR vs $\\tau_{{OIR}}$")
    a2.set(
        xlabel=r"$\tau_d$ [deg]",
        ylabel=r"LMR at $\tau_{OIR}=0.8$",
        title=f"{title}: LMR vs $\\tau_d$",
    )
    a2.axvline(M.DEFAULT_TAU_D_DEG, color="gray", lw=0.8)
    for a in (a1, a2):
        a.set_ylim(-0.02, 1.02)
        a.grid(alpha=0.3)
    a1.legend(fontsize=7, loc="lower left")
    fig.subplots_adjust(left=0.06, right=0.99, bottom=0.12, top=0.92, wspace=0.18)
    fig.savefig(path, dpi=110)
    plt.close(fig)


ROT_RANGE = (-2.0, 2.5)  # log10 deg
TRANS_RANGE = (-2.5, 2.0)  # log10 m


def fig_error_heatmaps(
    records: Sequence[Mapping[str, Any]], methods: Sequence[str], path: Path, title: str
) -> None:
    """Alignment-error densities: rows = cases, columns = methods (GT-matches first).

    Each panel is a 2D histogram of log10 translation error (x, -2.5..2) vs log10 rotation
    error (y, -2..2.5), divided by its maximum ("likelihood-normalised"); cyan lines mark
    5 deg and 1 m; pairs without an estimate are counted under the panel. The panels are tiled
    into one image on one axes: dozens of matplotlib axes would dominate the report's runtime.
    """
    plt = _plt()
    cases = sorted({r["case"] for r in records}, key=str)
    groups = _group(records, "case", "method")
    nr, nc, nb, gap = len(cases), len(methods), 30, 6
    bins = (np.linspace(*TRANS_RANGE, nb + 1), np.linspace(*ROT_RANGE, nb + 1))
    img = np.full((nr * (nb + gap), nc * (nb + gap)), np.nan)
    labels = []
    for i, case in enumerate(cases):
        for j, m in enumerate(methods):
            g = groups.get((case, m), [])
            rot = np.array([_f(r["rotation_error_deg"]) for r in g])
            tr = np.array([_f(r["translation_error_m"]) for r in g])
            fin = np.isfinite(rot) & np.isfinite(tr)
            x = np.clip(np.log10(np.maximum(tr[fin], 1e-9)), *TRANS_RANGE)
            y = np.clip(np.log10(np.maximum(rot[fin], 1e-9)), *ROT_RANGE)
            H, _, _ = np.histogram2d(x, y, bins=bins)
            if H.max() > 0:
                H = H / H.max()  # likelihood-normalised: the densest cell is 1
            r0, c0 = i * (nb + gap), j * (nb + gap)
            img[r0 : r0 + nb, c0 : c0 + nb] = H.T[::-1]  # rows: high rotation error on top
            ok = sum(bool(r["success"]) for r in g)
            labels.append(
                (r0 + nb + 0.5, c0 + nb / 2, f"{ok}/{len(g)} ok, {int((~fin).sum())} none")
            )
    fig, ax = plt.subplots(figsize=(1.45 * nc + 1.0, 1.55 * nr + 1.0))
    fig.subplots_adjust(left=0.8 / (1.45 * nc + 1.0), right=0.99, bottom=0.02, top=0.86)
    cmap = plt.get_cmap("magma").with_extremes(bad="white")
    ax.imshow(img, cmap=cmap, vmin=0, vmax=1, interpolation="nearest", aspect="equal")
    # threshold lines: x = log10(1 m), y = log10(5 deg), in bin units of each panel
    xt = (0.0 - TRANS_RANGE[0]) / (TRANS_RANGE[1] - TRANS_RANGE[0]) * nb - 0.5
    yt = nb - (np.log10(5.0) - ROT_RANGE[0]) / (ROT_RANGE[1] - ROT_RANGE[0]) * nb - 0.5
    for i in range(nr):
        for j in range(nc):
            r0, c0 = i * (nb + gap), j * (nb + gap)
            ax.plot([c0 + xt] * 2, [r0 - 0.5, r0 + nb - 0.5], color="c", lw=0.6)
            ax.plot([c0 - 0.5, c0 + nb - 0.5], [r0 + yt] * 2, color="c", lw=0.6)
    for r, c, text in labels:
        ax.text(c, r, text, ha="center", va="top", fontsize=5.5)
    for j, m in enumerate(methods):
        ax.text(j * (nb + gap) + nb / 2, -1.5, m, ha="center", va="bottom", fontsize=6.5)
    for i, case in enumerate(cases):
        ax.text(
            -2,
            i * (nb + gap) + nb / 2,
            f"case {case}",
            ha="right",
            va="center",
            fontsize=7,
            rotation=90,
        )
    ax.set_axis_off()
    ax.set_xlim(-4, img.shape[1])
    ax.set_ylim(img.shape[0], -4)
    fig.suptitle(
        f"{title}: alignment-error density per method (columns) and case (rows)\n"
        "x: log10 t_e [m] from -2.5 to 2, y: log10 R_e [deg] from -2 to 2.5; cyan: 1 m, 5 deg",
        fontsize=7,
    )
    fig.savefig(path, dpi=110)
    plt.close(fig)


def fig_runtimes(records: Sequence[Mapping[str, Any]], methods: Sequence[str], out: Path) -> None:
    """Box plots of total runtime per method, and of each stage of each method (one axes)."""
    plt = _plt()
    groups = _group(records, "method")

    def box(path: Path, series: list[tuple[str, list[float]]], ylabel: str, title: str) -> None:
        fig, ax = plt.subplots(figsize=(max(6.0, 0.32 * len(series) + 2), 4.8))
        fig.subplots_adjust(left=0.12, right=0.99, bottom=0.3, top=0.92)
        if series:
            ax.boxplot([v for _, v in series], showfliers=False)
            ax.set_xticks(
                range(1, len(series) + 1),
                [k for k, _ in series],
                rotation=60,
                ha="right",
                fontsize=6.5,
            )
            ax.set_yscale("log")
        ax.axhline(100.0, color="gray", ls=":", lw=0.8)  # 10 Hz LiDAR budget
        ax.set_ylabel(ylabel)
        ax.set_title(title, fontsize=9)
        fig.savefig(path, dpi=110)
        plt.close(fig)

    def ms(g: Sequence[Mapping[str, Any]], stage: str) -> list[float]:
        v = [1e3 * _f(r["timings"].get(stage)) for r in g if stage in r["timings"]]
        return [max(x, 1e-3) for x in v if np.isfinite(x)]

    totals = [(m, ms(groups.get((m,), []), "total")) for m in methods]
    box(
        out / "runtime_total.png",
        [(m, v) for m, v in totals if v],
        "total runtime per pair [ms] (log)",
        "Runtime per method (dotted: 100 ms = 10 Hz)",
    )
    stages: list[tuple[str, list[float]]] = []
    for m in methods:
        g = groups.get((m,), [])
        names = sorted({k for r in g for k in r["timings"] if k != "total"})
        stages += [(f"{m}: {s}", v) for s in names if (v := ms(g, s))]
    if stages:
        box(
            out / "runtime_stages.png",
            stages,
            "stage runtime [ms] (log)",
            "Runtime per method and stage",
        )


def fig_rho(rho_rows: Sequence[Mapping[str, Any]], stats: Mapping[str, Any], path: Path) -> None:
    """Histogram of pairwise landmark-centroid distances (left) and AUC over rho (right)."""
    plt = _plt()
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4))
    for suite, st in stats.items():
        counts = np.asarray(st.get("counts", []), dtype=float)
        if counts.sum() <= 0:
            continue
        w = float(st["bin_width_m"])
        edges = np.arange(len(counts) + 1) * w
        a1.stairs(
            counts / counts.sum() / w,
            edges,
            label=f"{suite}: {st['mean_m']:.0f} ± {st['std_m']:.0f} m",
        )
    a1.set(xlabel="pairwise landmark-centroid distance [m]", ylabel="density")
    a1.legend(fontsize=8)
    for k, suite in enumerate(sorted({r["suite"] for r in rho_rows})):
        rr = [r for r in rho_rows if r["suite"] == suite]
        rho, c = [r["rho"] for r in rr], f"C{k % 10}"
        a2.plot(rho, [r["auc"] for r in rr], "o-", color=c, label=f"{suite} AUC")
        a2.plot(rho, [r["recall"] for r in rr], "x--", color=c, label=f"{suite} recall")
    a2.set_xscale("log")
    a2.set(xlabel=r"$\rho$", ylabel="AUC / recall", ylim=(-0.02, 1.02))
    a2.set_title(r"GraffMatch sensitivity to $\rho$")
    a2.grid(alpha=0.3)
    if rho_rows:
        a2.legend(fontsize=8)
    fig.subplots_adjust(left=0.07, right=0.99, bottom=0.13, top=0.92, wspace=0.2)
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ----------------------------------------------------------------------------------------------
# the report
# ----------------------------------------------------------------------------------------------
def _read_json_dir(d: Path) -> dict[str, Any]:
    return (
        {p.stem: json.loads(p.read_text()) for p in sorted(d.glob("*.json"))} if d.is_dir() else {}
    )


def make_report(
    results_dir: str | Path, out_dir: str | Path | None = None, figures: bool = True
) -> Path:
    """Write the report folder for a results folder and return it.

    ``results_dir`` is the folder of ``run_study`` (with ``records/``) or the folder of
    ``run_benchmark`` (with ``results/``). Default ``out_dir``: ``report/`` next to the records
    (for a benchmark folder: ``<benchmark>/report``). ``figures=False``: tables and numbers
    only (seconds instead of tens of seconds for large studies).
    """
    results_dir = Path(results_dir)
    default_out = results_dir / "report"
    if not (results_dir / "records").is_dir() and (results_dir / "results" / "records").is_dir():
        results_dir = results_dir / "results"
    out = Path(out_dir) if out_dir is not None else default_out
    records = load_records(results_dir)
    if not records:
        raise InvalidInputError(f"{results_dir} holds no records yet")
    fig_dir = out / "figures"
    fig_dir.mkdir(parents=True, exist_ok=True)
    config = load_config(results_dir)
    if (results_dir / "config.json").is_file():
        shutil.copyfile(results_dir / "config.json", out / "config.json")
    pairs = _read_json_dir(results_dir / "pairs")
    stats = _read_json_dir(results_dir / "stats")

    main = [r for r in records if not _is_rho_spec(r["method"])]
    rows = summarize(main)
    _dump(out / "metrics.json", rows)
    _rows_csv(out / "metrics.csv", rows)

    t1, t2 = table1(rows), table2(rows)
    t1_md, t2_md = _table_md(t1, TABLE1_COLS), _table_md(t2, TABLE2_COLS)
    for name, t, md, cols in (
        ("table1", t1, t1_md, TABLE1_COLS),
        ("table2", t2, t2_md, TABLE2_COLS),
    ):
        _dump(out / f"{name}.json", t)
        (out / f"{name}.md").write_text(md + "\n")
        _table_csv(out / f"{name}.csv", t, cols)

    rr = rho_table(records)
    _dump(out / "rho.json", {"rows": rr, "centroid_distances": stats})
    _rows_csv(out / "rho.csv", rr)
    rho_md = (
        "| suite | rho | N | AUC | recall [%] | median [ms] |\n|---|---|---|---|---|---|\n"
        + "\n".join(
            f"| {r['suite']} | {r['rho']:g} | {r['n']} | {_fmt(r['auc'], '.3f')} | "
            f"{100 * r['recall']:.0f} | {_fmt(r['median_ms'], '.0f')} |"
            for r in rr
        )
    )
    (out / "rho.md").write_text(rho_md + "\n")

    exps = check_expectations(rows)
    _dump(out / "expectations.json", exps)
    exp_md = _expectations_md(exps)
    (out / "expectations.md").write_text(exp_md)

    # figures
    order = [m for m in config.get("study", {}).get("methods", []) if not _is_rho_spec(m)]
    all_methods = _ordered({r["method"] for r in main}, [*order, GT_METHOD, *TABLE_I_ORDER])
    landmark_methods = [GT_METHOD] + [
        m
        for m in _ordered({r["method"] for r in main if r["kind"] == "landmark"}, TABLE_I_ORDER)
        if m != GT_METHOD
    ]
    fig_links: list[tuple[str, str]] = []
    suites = sorted({r["suite"] for r in main})
    if figures:
        for suite in suites:
            recs = [r for r in main if r["suite"] == suite]
            p = fig_dir / f"lmr_{suite}.png"
            fig_lmr(recs, landmark_methods, p, suite)
            fig_links.append((f"LMR curves, {suite}", p.relative_to(out).as_posix()))
            p = fig_dir / f"errors_{suite}.png"
            fig_error_heatmaps(recs, landmark_methods, p, suite)
            fig_links.append((f"alignment-error heatmaps, {suite}", p.relative_to(out).as_posix()))
        if len(suites) > 1:
            p = fig_dir / "lmr_all.png"
            fig_lmr(main, landmark_methods, p, "all suites")
            fig_links.append(("LMR curves, all suites", p.relative_to(out).as_posix()))
        fig_runtimes(main, [m for m in all_methods if m != GT_METHOD], fig_dir)
        fig_links.append(("runtime per method", "figures/runtime_total.png"))
        if (fig_dir / "runtime_stages.png").is_file():
            fig_links.append(("runtime per stage", "figures/runtime_stages.png"))
        fig_rho(rr, stats, fig_dir / "rho_sensitivity.png")
        fig_links.append(("rho sensitivity and centroid distances", "figures/rho_sensitivity.png"))

    # summary
    errors = [r for r in main if r.get("status") != "ok"]
    err_by = _group(errors, "method")
    dataset_lines = []
    for suite in suites:
        meta = pairs.get(suite, [])
        per_case = _group(meta, "case") if meta else {}
        cs = ", ".join(f"case {c[0]}: {len(v)}" for c, v in sorted(per_case.items(), key=str))
        st = stats.get(suite, {})
        dataset_lines.append(
            f"- **{suite}**: {len(meta)} pairs ({cs}); landmark-centroid distances "
            f"{_fmt(st.get('mean_m'), '.1f')} ± {_fmt(st.get('std_m'), '.1f')} m"
        )
    runtime_lines = ["| method | N | median [ms] | p95 [ms] |", "|---|---|---|---|"]
    for m in all_methods:
        g = _group(main, "method").get((m,), [])
        if g:
            s = summary_row(g)
            runtime_lines.append(
                f"| {m} | {s['n']} | {_fmt(s['median_ms'], '.1f')} | {_fmt(s['p95_ms'], '.1f')} |"
            )
    study = config.get("study", {})
    parts = [
        "# GraffMatch evaluation report\n",
        f"Results: `{results_dir}`; {len(main)} records ({len(records) - len(main)} more in the "
        f"rho study); quick mode: {config.get('quick')}; executor: {config.get('executor')}; "
        f"commit {config.get('graffmatch_commit')}.\n",
        f"Metrics: inlier if GT-aligned d_Graff < {study.get('tau_d_deg', M.DEFAULT_TAU_D_DEG)}°; "
        f"success within {study.get('max_rotation_deg', 5.0)}° and "
        f"{study.get('max_translation_m', 1.0)} m; R_e and t_e are means over successes; "
        "AUC is the exact area under LMR(τ_OIR) on [0, 1]. The config used is in `config.json`.\n",
        "## Data\n",
        "\n".join(dataset_lines) + "\n",
        "## Table I analogue: landmark methods (best recall and AUC in bold)\n",
        "`GT-matches` (registration with the true matches) recall per row: "
        + ", ".join(
            f"{r['suite']}/{r['case']}: {_fmt(100 * _f(r['gt_recall']), '.0f')}%"
            for r in t1["rows"]
        )
        + "\n",
        _table_long_md(t1, TABLE1_LONG_COLS) + "\n",
        "The paper's wide layout: [table1.md](table1.md); CSV/JSON: [table1.csv](table1.csv), "
        "[table1.json](table1.json).\n",
        "## Table II analogue: point-based methods (GraffMatch without ICP for reference)\n",
        _table_long_md(t2, TABLE2_COLS) + "\n",
        "The paper's wide layout: [table2.md](table2.md); CSV/JSON: [table2.csv](table2.csv), "
        "[table2.json](table2.json).\n",
        "## The paper's expectations, checked on our numbers\n",
        exp_md,
        "## ρ sensitivity (GraffMatch)\n",
        rho_md + "\n",
        "## Runtime (total per pair, this machine)\n",
        "\n".join(runtime_lines) + "\n",
        "## Errors raised by methods\n",
        (
            "\n".join(
                f"- {m[0]}: {len(v)} pairs, e.g. `{str(v[0].get('error', '')).splitlines()[0]}`"
                for m, v in sorted(err_by.items())
            )
            if errors
            else "None: every method returned on every pair."
        )
        + "\n",
        "## Figures\n",
        (
            "\n".join(f"- [{t}]({p})\n\n  ![{t}]({p})" for t, p in fig_links)
            if fig_links
            else "Not drawn (make_report(..., figures=False))."
        )
        + "\n",
        "All numbers per (suite, case, method): [metrics.csv](metrics.csv), "
        "[metrics.json](metrics.json).\n",
    ]
    (out / "summary.md").write_text("\n".join(parts))
    return out
