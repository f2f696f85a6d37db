"""Turn a results folder into the paper's tables and figures, and check its claims.

``make_report(results_dir, out_dir)`` writes::

    summary.md                 every number below, the expectation checks, links to figures
    table1.{md,csv,json}       landmark methods per suite x case: recall, LMR AUC, R_e, t_e
    table2.{md,csv,json}       point-based methods (and GraffMatch+ICP) with runtime
    metrics.{csv,json}         every (suite, case, method) summary row
    rho.{md,csv,json}          AUC and recall of GraffMatch over rho
    expectations.{md,json}     the paper's orderings, computed from our numbers
    validity.{md,csv,json}     per suite and method: precision of valid, FPR on negatives, R@P100
    config.json                copy of the study config the results came from
    figures/*.png              LMR curves, error heatmaps, runtimes, rho sensitivity,
                               precision-recall of the validity scores, GraffMatch reliability

Everything is computed from the per-pair records alone (no landmarks or scans needed), with the
metric definitions of :mod:`graffmatch.evaluation.metrics`.

The numbers, tables, expectation checks and figures live in
:mod:`~graffmatch.evaluation.tables`, :mod:`~graffmatch.evaluation.expectations` and
:mod:`~graffmatch.evaluation.figures`; their public names stay importable from here.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from graffmatch.errors import InvalidInputError
from graffmatch.evaluation import metrics as M
from graffmatch.evaluation.expectations import check_expectations, expectations_md
from graffmatch.evaluation.figures import (
    fig_error_heatmaps,
    fig_lmr,
    fig_precision_recall,
    fig_reliability,
    fig_rho,
    fig_runtimes,
)
from graffmatch.evaluation.records import GT_METHOD, RHO_METHOD, load_config, load_records
from graffmatch.evaluation.tables import (
    ALL_CASES,
    BASELINES,
    CLIPPER_METHODS,
    GLOBAL_BASELINES,
    LOCAL_METHODS,
    TABLE1_COLS,
    TABLE1_LONG_COLS,
    TABLE2_COLS,
    TABLE_I_ORDER,
    TABLE_II_ORDER,
    dump_json,
    fmt,
    group_by,
    is_rho_spec,
    num,
    ordered,
    rho_table,
    rows_csv,
    summarize,
    summary_row,
    table1,
    table2,
    table_csv,
    table_long_md,
    table_md,
)
from graffmatch.evaluation.validity import validity_table

__all__ = [
    "ALL_CASES",
    "BASELINES",
    "CLIPPER_METHODS",
    "GLOBAL_BASELINES",
    "LOCAL_METHODS",
    "TABLE_II_ORDER",
    "TABLE_I_ORDER",
    "check_expectations",
    "fig_error_heatmaps",
    "fig_lmr",
    "fig_rho",
    "fig_runtimes",
    "make_report",
    "rho_table",
    "summarize",
    "summary_row",
    "table1",
    "table2",
]


def _rel(path: Path, root: Path) -> str:
    return path.relative_to(root).as_posix()


def _validity_md(rows: Sequence[Mapping[str, Any]]) -> str:
    head = (
        "| suite | method | signal | positives | negatives | valid | precision [%] | "
        "FPR on negatives [%] | R@P100 [%] |\n|---|---|---|---|---|---|---|---|---|"
    )
    body = [
        f"| {r['suite']} | {r['method']} | {r['signal']} | {r['n_positives']} | "
        f"{r['n_negatives']} | {r['n_valid']} | {fmt(100 * num(r['precision']), '.1f')} | "
        f"{fmt(100 * num(r['fpr_negatives']), '.1f')} | "
        f"{fmt(100 * num(r['recall_at_full_precision']), '.0f')} |"
        for r in rows
        if r["method"] != GT_METHOD and not is_rho_spec(r["method"])
    ]
    return "\n".join([head, *body])


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

    main = [r for r in records if not is_rho_spec(r["method"])]
    rows = summarize(main)
    dump_json(out / "metrics.json", rows)
    rows_csv(out / "metrics.csv", rows)

    t1, t2 = table1(rows), table2(rows)
    t1_md, t2_md = table_md(t1, TABLE1_COLS), table_md(t2, TABLE2_COLS)
    for name, t, md, cols in (
        ("table1", t1, t1_md, TABLE1_COLS),
        ("table2", t2, t2_md, TABLE2_COLS),
    ):
        dump_json(out / f"{name}.json", t)
        (out / f"{name}.md").write_text(md + "\n")
        table_csv(out / f"{name}.csv", t, cols)

    rr = rho_table(records)
    dump_json(out / "rho.json", {"rows": rr, "centroid_distances": stats})
    rows_csv(out / "rho.csv", rr)
    rho_md = (
        "| suite | rho | N | AUC | recall [%] | median [ms] |\n|---|---|---|---|---|---|\n"
        + "\n".join(
            f"| {r['suite']} | {r['rho']:g} | {r['n']} | {fmt(r['auc'], '.3f')} | "
            f"{100 * r['recall']:.0f} | {fmt(r['median_ms'], '.0f')} |"
            for r in rr
        )
    )
    (out / "rho.md").write_text(rho_md + "\n")

    vt = validity_table(main)
    dump_json(out / "validity.json", vt)
    rows_csv(out / "validity.csv", vt)
    validity_md = _validity_md(vt)
    (out / "validity.md").write_text(validity_md + "\n")

    exps = check_expectations(rows)
    dump_json(out / "expectations.json", exps)
    exp_md = expectations_md(exps)
    (out / "expectations.md").write_text(exp_md)

    # figures
    order = [m for m in config.get("study", {}).get("methods", []) if not is_rho_spec(m)]
    all_methods = ordered({r["method"] for r in main}, [*order, GT_METHOD, *TABLE_I_ORDER])
    landmark_methods = [GT_METHOD] + [
        m
        for m in ordered({r["method"] for r in main if r["kind"] == "landmark"}, TABLE_I_ORDER)
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
        methods_v = [m for m in all_methods if m != GT_METHOD]
        for suite in suites:
            recs = [r for r in main if r["suite"] == suite]
            p = fig_dir / f"precision_recall_{suite}.png"
            fig_precision_recall(recs, methods_v, p, suite)
            fig_links.append((f"precision-recall of the validity scores, {suite}", _rel(p, out)))
        ours = [r for r in main if r["method"] == RHO_METHOD]
        if ours:
            p = fig_dir / "reliability_graffmatch.png"
            fig_reliability(ours, p, f"{RHO_METHOD} confidence, all suites")
            fig_links.append(("reliability diagram of GraffMatch's confidence", _rel(p, out)))

    # summary
    errors = [r for r in main if r.get("status") != "ok"]
    err_by = group_by(errors, "method")
    dataset_lines = []
    for suite in suites:
        meta = pairs.get(suite, [])
        per_case = group_by(meta, "case") if meta else {}
        cs = ", ".join(
            f"{'negatives' if c[0] == 0 else f'case {c[0]}'}: {len(v)}"
            for c, v in sorted(per_case.items(), key=str)
        )
        st = stats.get(suite, {})
        dataset_lines.append(
            f"- **{suite}**: {len(meta)} pairs ({cs}); landmark-centroid distances "
            f"{fmt(st.get('mean_m'), '.1f')} ± {fmt(st.get('std_m'), '.1f')} m"
        )
    runtime_lines = ["| method | N | median [ms] | p95 [ms] |", "|---|---|---|---|"]
    for m in all_methods:
        g = group_by(main, "method").get((m,), [])
        if g:
            s = summary_row(g)
            runtime_lines.append(
                f"| {m} | {s['n']} | {fmt(s['median_ms'], '.1f')} | {fmt(s['p95_ms'], '.1f')} |"
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
            f"{r['suite']}/{r['case']}: {fmt(100 * num(r['gt_recall']), '.0f')}%"
            for r in t1["rows"]
        )
        + "\n",
        table_long_md(t1, TABLE1_LONG_COLS) + "\n",
        "The paper's wide layout: [table1.md](table1.md); CSV/JSON: [table1.csv](table1.csv), "
        "[table1.json](table1.json).\n",
        "## Table II analogue: point-based methods (GraffMatch without ICP for reference)\n",
        table_long_md(t2, TABLE2_COLS) + "\n",
        "The paper's wide layout: [table2.md](table2.md); CSV/JSON: [table2.csv](table2.csv), "
        "[table2.json](table2.json).\n",
        "## Validity: is `valid` right? (positives and negative pairs)\n",
        "Precision = correct valid results / valid results; FPR = valid results on negative "
        "pairs (places without overlap) / negatives; R@P100 = the largest recall of a threshold "
        "on the method's own validity score that accepts no wrong result. "
        "See `graffmatch.evaluation.validity`.\n",
        validity_md + "\n",
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
