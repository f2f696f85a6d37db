"""One call from suite names to a report: build the suites, run the study, write the report.

``run_benchmark(["balm_courtyard"], "bench_out", quick=True)`` makes::

    <out_dir>/data/<suite>[-quick]/   the loop-closure datasets (cached: rebuilt only if stale)
    <out_dir>/results/                one JSON record per (suite, pair, method); resumable
    <out_dir>/report/                 tables, figures, summary.md
    <out_dir>/benchmark.json          what ran, and how long each phase took

Rerunning the same command resumes: built suites and finished records are reused.
"""

from __future__ import annotations

import json
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from graffmatch.errors import InvalidInputError
from graffmatch.evaluation.executors import make_executor
from graffmatch.evaluation.loop_closure_dataset import PAIRS_FILE
from graffmatch.evaluation.report import make_report
from graffmatch.evaluation.runner import StudyConfig, atomic_write_json, git_commit, run_study

#: Real data suite of the default benchmark (the simulated ones are added by name prefix).
REAL_DEFAULT_SUITES = ("balm_courtyard",)
#: Pairs per case of the full benchmark: an evenly spaced subset keeps the default study within
#: an hour on a 2-core machine (about 15 methods x ~5 s of CPU per pair); pass a StudyConfig with
#: ``max_pairs_per_case=None`` for every pair.
FULL_MAX_PAIRS_PER_CASE = 40


def default_suites() -> list[str]:
    """The simulated suites (``sim-*``), ``balm_courtyard``, and the cross-dataset negatives
    when a real dataset is there to pair with the simulated one."""
    from graffmatch.evaluation.suites import available_suites, cross_sources_available

    names = available_suites()
    out = [n for n in names if n.startswith("sim")] + [n for n in REAL_DEFAULT_SUITES if n in names]
    if "cross-dataset" in names and cross_sources_available():
        out.append("cross-dataset")
    return out


def benchmark_request(
    suites: Sequence[str] | None,
    quick: bool,
    methods: Sequence[str] | None,
    data_dir: Path,
    config: StudyConfig | None,
) -> dict[str, Any]:
    """What decides a benchmark's results: a finished run with the same request is complete.

    The code's commit is part of it, so that new code rebuilds the report (the study itself
    still reuses every record whose pair and settings are unchanged).
    """
    return {
        "suites": list(suites) if suites else None,  # None: the default suites
        "quick": bool(quick),
        "methods": None if methods is None else list(methods),
        "data_dir": str(Path(data_dir).resolve()),
        "study": None if config is None else config.model_dump(mode="json"),
        "graffmatch_commit": git_commit(),
    }


def benchmark_complete(out_dir: str | Path, request: Mapping[str, Any]) -> bool:
    """True when ``out_dir`` holds a finished run of ``request`` on unchanged suites.

    Reads two small JSON files and stats one file per suite: no dataset is loaded or built, so
    re-running a finished benchmark returns at once.
    """
    out = Path(out_dir)
    try:
        log = json.loads((out / "benchmark.json").read_text())
        runs = (out / "results" / "runs.jsonl").read_text().splitlines()
        last_run = json.loads(runs[-1]) if runs else {}
    except (OSError, json.JSONDecodeError):
        return False
    if not log.get("ended_utc") or log.get("request") != dict(request):
        return False
    if not last_run.get("complete") or not (out / "report" / "summary.md").is_file():
        return False
    for entry in log.get("build", {}).values():
        folder = Path(entry.get("folder", ""))
        if entry.get("pairs_mtime_ns") != _mtime_ns(folder / PAIRS_FILE):
            return False  # a suite was rebuilt since
    return True


def is_benchmark_complete(
    out_dir: str | Path,
    suites: Sequence[str] | None = None,
    quick: bool = False,
    methods: Sequence[str] | None = None,
    data_dir: str | Path | None = None,
    config: StudyConfig | None = None,
) -> bool:
    """Would :func:`run_benchmark` with these arguments find nothing to do? (Fast: it does not
    even import the suites, whose datasets pull in the LiDAR front end.)"""
    out = Path(out_dir)
    return benchmark_complete(out, _resolve(suites, out, quick, methods, data_dir, config)[2])


def _resolve(
    suites: Sequence[str] | None,
    out: Path,
    quick: bool,
    methods: Sequence[str] | None,
    data_dir: str | Path | None,
    config: StudyConfig | None,
) -> tuple[Path, StudyConfig | None, dict[str, Any]]:
    """The data folder, the study config and the request of a benchmark's arguments."""
    data = Path(data_dir) if data_dir is not None else out / "data"
    if config is None and not quick:
        config = StudyConfig(max_pairs_per_case=FULL_MAX_PAIRS_PER_CASE)
    return data, config, benchmark_request(suites, quick, methods, data, config)


def _mtime_ns(path: Path) -> int | None:
    try:
        return path.stat().st_mtime_ns
    except OSError:
        return None


def run_benchmark(
    suites: Sequence[str] | None = None,
    out_dir: str | Path = "graffmatch-benchmark",
    quick: bool = False,
    executor: str = "local",
    address: str | None = None,
    workers: int | None = None,
    methods: Sequence[str] | None = None,
    data_dir: str | Path | None = None,
    data_root: str | Path | None = None,
    config: StudyConfig | None = None,
    progress: bool = True,
) -> Path:
    """Build ``suites``, run every method on every pair, write the report; returns ``out_dir``.

    A finished run of the same request (:func:`benchmark_complete`) returns at once.

    Args:
        suites: suite names (see ``graffmatch.evaluation.suites.available_suites()``);
            None or empty: :func:`default_suites`.
        out_dir: where data, results and the report go.
        quick: small suites, a few pairs per case, the fast point methods (minutes).
        executor: "local" (process pool, default), "serial", "dask" or "ray".
        address: scheduler address of a Dask/Ray cluster (``tcp://host:8786``); without it,
            dask starts a local cluster.
        workers: worker processes for local execution / a local cluster (default: all cores).
        methods: method names; None: every registered method (``quick``: without the slow
            point methods).
        data_dir: where built suites are cached (default ``<out_dir>/data``); share it
            between benchmarks to build each suite once.
        data_root: folder of the real datasets (default ``../shared/data``).
        config: thresholds and subset sizes of the study (default: at most
            ``FULL_MAX_PAIRS_PER_CASE`` pairs per case, or the quick subset).
        progress: rich progress bars.
    """
    out = Path(out_dir)
    data, config, request = _resolve(suites, out, quick, methods, data_dir, config)
    if benchmark_complete(out, request):
        return out
    from graffmatch.evaluation.suites import build_suite

    names = list(suites or default_suites())
    if not names:
        raise InvalidInputError("no suites to run (none given and none registered)")
    out.mkdir(parents=True, exist_ok=True)
    log: dict[str, Any] = {
        "request": request,
        "suites": names,
        "quick": quick,
        "executor": executor,
        "address": address,
        "workers": workers,
        "methods": list(methods) if methods is not None else None,
        "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "build": {},
    }
    # Fail on a bad executor before spending minutes on building data.
    ex = make_executor(executor, workers=workers, address=address)
    try:
        t0 = time.perf_counter()
        built: dict[str, Path] = {}
        for name in names:
            t = time.perf_counter()
            summary = build_suite(name, data, quick=quick, data_root=data_root, progress=progress)
            folder = data / (f"{name}-quick" if quick else name)
            log["build"][name] = {
                "folder": str(folder),
                "pairs_mtime_ns": _mtime_ns(folder / PAIRS_FILE),
                "pairs": summary.get("n_valid"),
                "cases": {k: v.get("pairs") for k, v in summary.get("cases", {}).items()},
                "seconds": time.perf_counter() - t,
            }
            log["build"][name]["negatives"] = summary.get("n_negatives", 0)
            if summary.get("n_valid", 0) or summary.get("n_negatives", 0):
                built[name] = folder
        log["build_s"] = time.perf_counter() - t0
        if not built:
            raise InvalidInputError(f"no suite produced a loop closure: {log['build']}")
        t0 = time.perf_counter()
        results = run_study(
            built,
            methods,
            out / "results",
            executor=ex,
            quick=quick,
            workers=workers,
            address=address,
            config=config,
            progress=progress,
        )
        log["study_s"] = time.perf_counter() - t0
    finally:
        ex.close()
        atomic_write_json(out / "benchmark.json", log)
    t0 = time.perf_counter()
    make_report(results, out / "report")
    log["report_s"] = time.perf_counter() - t0
    log["ended_utc"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    atomic_write_json(out / "benchmark.json", log)
    return out
