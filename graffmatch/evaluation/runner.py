"""The experiment runner: every method on every loop-closure pair, one JSON record per result.

A study is the cross product (suite, pair, method). Each task is independent, so it is handed to
a pluggable :mod:`~graffmatch.evaluation.executors` engine (local process pool, Dask, Ray). The
driver writes every finished record *at once* with an atomic write (temporary file +
``os.replace``), so killing a worker or the driver loses no finished result, and a rerun skips
what is on disk and computes only the rest.

The records and the layout of a results folder are defined in
:mod:`~graffmatch.evaluation.records`, the worker side in :mod:`~graffmatch.evaluation.tasks`,
comparisons in :mod:`~graffmatch.evaluation.compare`; their public names stay importable here.

The pseudo-method ``GT-matches`` registers each pair with its true landmark matches; it is the
best a landmark-only registration can do and the first column of the error heatmaps.
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from graffmatch.errors import InvalidInputError
from graffmatch.evaluation import metrics as M
from graffmatch.evaluation.compare import COMPARE_METRICS, compare_runs, format_comparison
from graffmatch.evaluation.executors import Executor, make_executor
from graffmatch.evaluation.progress import progress_bar
from graffmatch.evaluation.records import (
    DEFAULT_RHO_VALUES,
    GT_METHOD,
    RECORD_VERSION,
    RHO_METHOD,
    StudyConfig,
    atomic_write_json,
    load_config,
    load_records,
    pair_fingerprint,
    read_record,
    record_path,
    record_without_timings,
    slug,
    task_key,
)
from graffmatch.evaluation.tasks import (
    EvaluationMethod,
    LoopClosurePair,
    PairRef,
    Task,
    _dataset_pairs,
    _jsonable_info,
    _registry_method,
    execute_task,
    method_kind,
    parse_method_spec,
    rho_spec,
)

# Names that lived here before records/tasks/compare were split out stay importable.
__all__ = [
    "COMPARE_METRICS",
    "DEFAULT_RHO_VALUES",
    "GT_METHOD",
    "QUICK_PAIRS_PER_CASE",
    "QUICK_RHO_PAIRS",
    "QUICK_SKIP_METHODS",
    "RECORD_VERSION",
    "RHO_METHOD",
    "EvaluationMethod",
    "LoopClosurePair",
    "PairRef",
    "StudyConfig",
    "Task",
    "atomic_write_json",
    "centroid_distance_stats",
    "compare_runs",
    "default_methods",
    "execute_task",
    "format_comparison",
    "git_commit",
    "load_config",
    "load_records",
    "method_kind",
    "pair_fingerprint",
    "parse_method_spec",
    "record_path",
    "record_without_timings",
    "rho_spec",
    "run_study",
    "slug",
]

#: Point methods skipped by ``quick=True`` (each takes seconds per pair on full scans).
QUICK_SKIP_METHODS = ("FPFH+RANSAC", "KISS-Matcher", "ScanContext+ICP")
#: Pairs per case and rho-study pairs per suite of ``quick=True``.
QUICK_PAIRS_PER_CASE = 3
QUICK_RHO_PAIRS = 4


# ----------------------------------------------------------------------------------------------
# the driver
# ----------------------------------------------------------------------------------------------
@dataclass
class _PairEntry:
    pair_id: str
    case: int
    ref: Any  # pair object or PairRef
    meta: dict[str, Any]


def _pair_id(pair: Any, index: int) -> str:
    for attr in ("pair_id", "name", "id"):
        v = getattr(pair, attr, None)
        if v is not None and not callable(v):
            return str(v)
    return f"{index:06d}"


def _pair_meta(pair: Any, pair_id: str) -> dict[str, Any]:
    src, tgt = pair.source, pair.target
    return M._jsonable(
        {
            "pair_id": pair_id,
            "fingerprint": pair_fingerprint(pair),
            "case": int(getattr(pair, "case", 0)),
            "negative": bool(getattr(pair, "negative", False)),
            "iir": float(getattr(pair, "iir", np.nan)),
            "distance": float(getattr(pair, "distance", np.nan)),
            "n_true_matches": len(np.asarray(pair.true_matches).reshape(-1, 2)),
            "source_counts": src.counts(),
            "target_counts": tgt.counts(),
            "source_scan_path": str(getattr(pair, "source_scan_path", "") or ""),
            "target_scan_path": str(getattr(pair, "target_scan_path", "") or ""),
        }
    )


def _entries_from(pairs: Iterable[Any], dataset_dir: str | None) -> list[_PairEntry]:
    out = []
    seen: set[str] = set()
    for i, pair in enumerate(pairs):
        pid = _pair_id(pair, i)
        if pid in seen:
            raise InvalidInputError(f"duplicate pair id {pid!r}")
        seen.add(pid)
        ref = PairRef(dataset_dir, i) if dataset_dir else pair
        out.append(_PairEntry(pid, int(getattr(pair, "case", 0)), ref, _pair_meta(pair, pid)))
    return out


#: ``{suite: pairs or dataset folder}`` or a list of dataset folders (suite = folder name).
Sources = Mapping[str, Iterable[Any] | str | Path] | Sequence[str | Path] | str | Path


def _normalize_sources(sources: Sources) -> dict[str, tuple[list[_PairEntry], list[Any]]]:
    """suite -> (entries, pairs). Dataset folders become PairRefs (workers load them)."""
    out: dict[str, tuple[list[_PairEntry], list[Any]]] = {}
    if isinstance(sources, (str, Path)):
        sources = [sources]
    named: list[tuple[str, Any]] = (
        [(str(k), v) for k, v in sources.items()]
        if isinstance(sources, Mapping)
        else [(Path(d).name, d) for d in sources]
    )
    for name, src in named:
        if name in out:
            raise InvalidInputError(f"two suites named {name!r}; rename one")
        if isinstance(src, (str, Path)):
            d = Path(src)
            if not d.is_dir():
                raise InvalidInputError(f"loop-closure dataset folder not found: {d}")
            pairs = _dataset_pairs(str(d.resolve()))
            out[name] = (_entries_from(pairs, str(d.resolve())), pairs)
        else:
            pairs = list(src)
            out[name] = (_entries_from(pairs, None), pairs)
    return out


def _subset_per_case(entries: list[_PairEntry], k: int | None) -> list[_PairEntry]:
    """Evenly spaced subset of at most k pairs per case (deterministic, representative)."""
    if k is None:
        return entries
    out: list[_PairEntry] = []
    for case in sorted({e.case for e in entries}):
        group = [e for e in entries if e.case == case]
        if len(group) > k:
            idx = np.unique(np.round(np.linspace(0, len(group) - 1, k)).astype(int))
            group = [group[i] for i in idx]
        out.extend(group)
    return out


def _evenly(entries: list[_PairEntry], k: int) -> list[_PairEntry]:
    if k <= 0 or not entries:
        return []
    if len(entries) <= k:
        return entries
    idx = np.unique(np.round(np.linspace(0, len(entries) - 1, k)).astype(int))
    return [entries[i] for i in idx]


def centroid_distance_stats(pairs: Iterable[Any], bin_width: float = 2.0) -> dict[str, Any]:
    """Histogram of intra-scan pairwise landmark-anchor distances (the paper's rho argument)."""
    from scipy.spatial.distance import pdist

    seen: set[str] = set()
    hist = np.zeros(0, dtype=np.int64)
    n = 0
    s1 = s2 = 0.0
    for pair in pairs:
        for side in ("source", "target"):
            key = str(getattr(pair, f"{side}_scan_path", "") or "")
            if key and key in seen:
                continue
            seen.add(key)
            anchors = getattr(pair, side).anchors
            if len(anchors) < 2:
                continue
            d = pdist(anchors)
            counts = np.bincount((d // bin_width).astype(np.int64))
            if len(counts) > len(hist):
                hist = np.pad(hist, (0, len(counts) - len(hist)))
            hist[: len(counts)] += counts
            n += d.size
            s1 += float(d.sum())
            s2 += float((d * d).sum())
    mean = s1 / n if n else float("nan")
    std = float(np.sqrt(max(s2 / n - mean * mean, 0.0))) if n else float("nan")
    return {
        "bin_width_m": bin_width,
        "counts": hist.tolist(),
        "n_distances": n,
        "mean_m": mean,
        "std_m": std,
    }


def git_commit() -> str | None:
    try:
        r = subprocess.run(
            ["git", "rev-parse", "HEAD"],
            cwd=Path(__file__).resolve().parent,
            capture_output=True,
            text=True,
            timeout=5,
            check=False,
        )
    except OSError:
        return None
    return r.stdout.strip() or None


def _method_params(method: str | EvaluationMethod) -> Any:
    """The parameters a method runs with, for config.json (what the paper calls its setup)."""
    try:
        obj = _registry_method(method) if isinstance(method, str) else method
        params = getattr(obj, "params", None)
        if params is None and hasattr(obj, "__dataclass_fields__"):
            params = {k: getattr(obj, k) for k in obj.__dataclass_fields__}
        return _jsonable_info(dict(params or {}))
    except Exception as exc:  # never fail a study on bookkeeping; say why it is missing
        return {"unavailable": f"{type(exc).__name__}: {exc}"}


def default_methods(quick: bool = False) -> list[str]:
    """Every registered method; quick mode keeps the fast point methods only."""
    from graffmatch.evaluation import registry

    names = list(registry.list_methods())
    if quick:
        names = [n for n in names if n not in QUICK_SKIP_METHODS]
    return names


def run_study(
    sources: Sources,
    methods: Sequence[str | EvaluationMethod] | None = None,
    out_dir: str | Path = "results",
    executor: str | Executor = "local",
    quick: bool = False,
    workers: int | None = None,
    address: str | None = None,
    config: StudyConfig | None = None,
    progress: bool = True,
    on_record: Callable[[dict[str, Any]], None] | None = None,
) -> Path:
    """Run every method on every pair and persist one record per (method, pair).

    Args:
        sources: ``{suite: iterable of pairs | dataset folder}`` (in-memory pairs, e.g. for
            tests or custom data; folders are loaded lazily by the workers) or a list of
            loop-closure dataset folders (the suite is the folder name).
        methods: registry names (``"GraffMatch"``, ``"GraffMatch[rho=20]"``) or picklable
            method objects; default: every registered method. ``GT-matches`` always runs.
        out_dir: results folder; existing records are kept and skipped (resume).
        executor: ``"local"`` (process pool), ``"serial"``, ``"dask"``, ``"ray"`` or an
            executor object.
        quick: at most 3 pairs per case, the fast point methods, a 4-pair rho study.
        workers, address: for the executor (``address`` of a Dask/Ray cluster).
        config: thresholds and subset sizes (``StudyConfig``); ``methods`` overrides its list.
        progress: show a rich progress bar with ETA.
        on_record: called in the driver after each record is saved (for monitoring, tests).

    Returns the results folder.
    """
    out = Path(out_dir)
    cfg = (config or StudyConfig()).model_copy(deep=True)
    if quick:
        if cfg.max_pairs_per_case is None:
            cfg.max_pairs_per_case = QUICK_PAIRS_PER_CASE
        cfg.rho_pairs_per_suite = min(cfg.rho_pairs_per_suite, QUICK_RHO_PAIRS)
    method_objs: dict[str, str | EvaluationMethod] = {}
    if methods is None:
        methods = cfg.methods or default_methods(quick)
    for m in methods:
        if isinstance(m, str):
            method_kind(m)  # fail early on a malformed spec or an unknown name
            method_objs[m] = m
        elif isinstance(m, EvaluationMethod):
            method_objs[str(m.name)] = m
        else:
            raise InvalidInputError(f"method must be a name or an EvaluationMethod, got {m!r}")
    method_objs.pop(GT_METHOD, None)
    cfg.methods = [GT_METHOD, *method_objs]
    rho_specs = [rho_spec(r) for r in cfg.rho_values] if RHO_METHOD in method_objs else []

    suites = _normalize_sources(sources)
    if not suites:
        raise InvalidInputError("run_study needs at least one suite")

    out.mkdir(parents=True, exist_ok=True)
    started = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    config_doc = {
        "study": cfg.model_dump(),
        "suites": {
            name: (str(e[0].ref.dataset_dir) if e and isinstance(e[0].ref, PairRef) else "memory")
            for name, (e, _) in suites.items()
        },
        "rho_study": {"method": RHO_METHOD, "specs": rho_specs},
        "quick": quick,
        "executor": executor if isinstance(executor, str) else executor.name,
        "address": address,
        "workers": workers,
        "graffmatch_commit": git_commit(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count()},
        "started_utc": started,
        "record_version": RECORD_VERSION,
    }
    config_doc["method_params"] = {
        name: _method_params(m) for name, m in [*method_objs.items(), *((r, r) for r in rho_specs)]
    }
    atomic_write_json(out / "config.json", config_doc)

    # Task list: pair-major so consecutive tasks reuse a worker's cached dataset.
    tasks: list[Task] = []
    n_done_before = 0
    for name, (entries, pairs) in suites.items():
        chosen = _subset_per_case(entries, cfg.max_pairs_per_case)
        atomic_write_json(out / "pairs" / f"{slug(name)}.json", [e.meta for e in chosen])
        stats_path = out / "stats" / f"{slug(name)}.json"
        if not stats_path.is_file():
            atomic_write_json(stats_path, centroid_distance_stats(pairs))
        rho_ids = {e.pair_id for e in _evenly(chosen, cfg.rho_pairs_per_suite)}
        for e in chosen:
            specs: list[str | EvaluationMethod] = [GT_METHOD, *method_objs.values()]
            if e.pair_id in rho_ids:
                specs += rho_specs
            for spec in specs:
                mname = spec if isinstance(spec, str) else str(spec.name)
                key = task_key(e.meta["fingerprint"], cfg)
                rec = read_record(record_path(out, name, mname, e.pair_id))
                if (
                    rec is not None
                    and rec.get("task_key") == key
                    and (rec.get("status") == "ok" or not cfg.retry_errors)
                ):
                    n_done_before += 1
                    continue
                tasks.append(
                    Task(
                        suite=name,
                        pair_id=e.pair_id,
                        method=spec,
                        pair=e.ref,
                        task_key=key,
                        tau_d_deg=cfg.tau_d_deg,
                        rho_eval=cfg.rho_eval,
                        max_rotation_deg=cfg.max_rotation_deg,
                        max_translation_m=cfg.max_translation_m,
                    )
                )

    own_executor = isinstance(executor, str)
    ex: Executor = (
        make_executor(executor, workers=workers, address=address) if own_executor else executor  # type: ignore[arg-type]
    )
    n_new = n_err = 0
    try:
        with _progress(progress, len(tasks), n_done_before) as advance:
            for i, doc in ex.imap_unordered(execute_task, tasks):
                t = tasks[i]
                atomic_write_json(record_path(out, t.suite, t.method_name, t.pair_id), doc)
                n_new += 1
                n_err += doc.get("status") != "ok"
                if on_record is not None:
                    on_record(doc)
                advance(t.method_name)
    finally:
        if own_executor:
            ex.close()
        with open(out / "runs.jsonl", "a") as f:
            f.write(
                json.dumps(
                    {
                        "started_utc": started,
                        "ended_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                        "tasks": len(tasks),
                        "skipped_existing": n_done_before,
                        "written": n_new,
                        "errors": n_err,
                        "complete": n_new == len(tasks),
                        "executor": config_doc["executor"],
                    }
                )
                + "\n"
            )
    return out


class _progress:
    """The study's bar (or nothing), used as ``with _progress(...) as advance``."""

    def __init__(self, enabled: bool, total: int, done_before: int) -> None:
        self._p = progress_bar(
            enabled and total > 0, "[bold]study[/] {task.description}", transient=False
        )
        self.total = total
        self.done_before = done_before

    def __enter__(self) -> Callable[[str], None]:
        self._p.__enter__()
        desc = f"({self.done_before} already done)" if self.done_before else ""
        tid = self._p.add_task(desc, total=self.total)

        def advance(method: str) -> None:
            self._p.update(tid, advance=1, description=f"{method:<22}")

        return advance

    def __exit__(self, *exc: object) -> None:
        self._p.__exit__(*exc)
