"""Records and results folders of a study: where each record lives, how it is read and keyed.

Layout of a results folder::

    config.json                 the exact configuration of the last invocation
    runs.jsonl                  one line per invocation (config, start, end, counts)
    pairs/<suite>.json          per pair: id, case, IIR, baseline distance, #true matches, counts
    stats/<suite>.json          histogram of pairwise landmark-centroid distances (rho choice)
    records/<suite>/<method>/<pair_id>.json   one record per (method, pair)

A record is :class:`graffmatch.evaluation.metrics.PairRecord` (estimate, ground truth, the
GT-aligned d_Graff distance of every selected association, timings) plus the derived numbers a
human wants to grep: rotation/translation error, success, OIR and the inlier mask at tau_d.
This module is the bottom of the study code: the runner writes what it defines, the report
reads it, and neither imports the other.
"""

from __future__ import annotations

import hashlib
import json
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from graffmatch.atomic_files import write_json_atomic
from graffmatch.errors import MalformedFileError
from graffmatch.evaluation import metrics as M

GT_METHOD = "GT-matches"
RECORD_VERSION = 1
DEFAULT_RHO_VALUES = (5.0, 10.0, 20.0, 40.0, 80.0, 160.0)
RHO_METHOD = "GraffMatch"


class StudyConfig(BaseModel):
    """Everything that determines the records of a study (written to ``config.json``)."""

    model_config = ConfigDict(extra="forbid")

    methods: list[str] = Field(
        default_factory=list,
        description="Method names in column order; GT-matches is always added first.",
    )
    tau_d_deg: float = Field(
        M.DEFAULT_TAU_D_DEG, gt=0, description="Inlier threshold on GT-aligned d_Graff [deg]."
    )
    rho_eval: float = Field(
        M.DEFAULT_RHO, gt=0, description="rho of the invariant d_Graff used for the inlier test."
    )
    max_rotation_deg: float = Field(
        M.DEFAULT_MAX_ROTATION_DEG, gt=0, description="Success threshold on rotation error [deg]."
    )
    max_translation_m: float = Field(
        M.DEFAULT_MAX_TRANSLATION_M, gt=0, description="Success threshold on translation [m]."
    )
    max_pairs_per_case: int | None = Field(
        None, ge=1, description="Evenly spaced subset of at most this many pairs per case."
    )
    rho_values: list[float] = Field(
        default_factory=lambda: list(DEFAULT_RHO_VALUES),
        description="rho values of the GraffMatch sensitivity study (empty: no study).",
    )
    rho_pairs_per_suite: int = Field(
        24, ge=0, description="Pairs per suite (evenly spaced) used for the rho study."
    )
    retry_errors: bool = Field(
        False, description="Rerun tasks whose saved record says the method raised."
    )


def slug(text: str) -> str:
    """A file-name-safe, readable and injective-enough form of a method or pair name."""
    s = re.sub(r"[^A-Za-z0-9._+=-]+", "_", text).strip("_")
    return s or "_"


def record_path(out_dir: str | Path, suite: str, method: str, pair_id: str) -> Path:
    return Path(out_dir) / "records" / slug(suite) / slug(method) / f"{slug(pair_id)}.json"


def atomic_write_json(path: Path, doc: Any) -> None:
    """Write JSON so that a reader sees the old file or the complete new one, never half."""
    write_json_atomic(path, doc, fsync=True)


def read_record(path: Path) -> dict[str, Any] | None:
    try:
        doc = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None
    return doc if isinstance(doc, dict) and doc.get("record_version") == RECORD_VERSION else None


def load_records(results_dir: str | Path, current_only: bool = True) -> list[dict[str, Any]]:
    """The records of a results folder, sorted by (suite, method, pair_id).

    ``current_only``: keep only records of the pairs selected by the last run (``pairs/``),
    computed on the same pair content and settings; stale records of a rebuilt dataset or of a
    larger earlier selection stay on disk but are not reported.
    """
    root = Path(results_dir) / "records"
    if not root.is_dir():
        raise MalformedFileError(f"{results_dir} is not a results folder (no records/)")
    out = [r for p in sorted(root.glob("*/*/*.json")) if (r := read_record(p)) is not None]
    if current_only:
        keys = _current_task_keys(Path(results_dir))
        if keys is not None:
            out = [
                r for r in out if keys.get((slug(r["suite"]), r["pair_id"])) == r.get("task_key")
            ]
    out.sort(key=lambda r: (r["suite"], r["method"], r["pair_id"]))
    return out


def _current_task_keys(results_dir: Path) -> dict[tuple[str, str], str] | None:
    """(suite slug, pair_id) -> task key of the latest selection per suite; None if unknown."""
    cfg = load_config(results_dir)
    pairs_dir = results_dir / "pairs"
    if not cfg.get("study") or not pairs_dir.is_dir():
        return None
    study = StudyConfig.model_validate(cfg["study"])
    out: dict[tuple[str, str], str] = {}
    for f in sorted(pairs_dir.glob("*.json")):
        for meta in json.loads(f.read_text()):
            out[(f.stem, str(meta["pair_id"]))] = task_key(str(meta.get("fingerprint")), study)
    return out


def load_config(results_dir: str | Path) -> dict[str, Any]:
    p = Path(results_dir) / "config.json"
    return json.loads(p.read_text()) if p.is_file() else {}


def record_without_timings(rec: Mapping[str, Any]) -> dict[str, Any]:
    """A record minus what legitimately differs between runs (timings)."""
    drop = {"timings"}
    return {k: v for k, v in rec.items() if k not in drop}


def pair_fingerprint(pair: Any) -> str:
    """Hash of what defines a pair (ground truth, true matches, case, both landmark sets).

    A record is reused on resume only if the pair it was computed on is unchanged: a rebuilt
    dataset may keep pair ids while their landmarks or cases change.
    """
    h = hashlib.sha1()
    for a in (
        np.round(np.asarray(pair.T_target_source, dtype=float), 9),
        np.asarray(pair.true_matches, dtype=np.int64),
        np.asarray([int(getattr(pair, "case", 0))]),
    ):
        h.update(np.ascontiguousarray(a).tobytes())
    for ls in (pair.source, pair.target):
        h.update(np.ascontiguousarray(ls.types).tobytes())
        h.update(np.ascontiguousarray(np.round(ls.anchors, 9)).tobytes())
        h.update(np.ascontiguousarray(np.round(ls.bases, 9)).tobytes())
        h.update(str(None if ls.points is None else ls.points.shape).encode())
    return h.hexdigest()[:16]


def task_key(fingerprint: str, cfg: StudyConfig) -> str:
    params = (cfg.tau_d_deg, cfg.rho_eval, cfg.max_rotation_deg, cfg.max_translation_m)
    return hashlib.sha1(f"{fingerprint}|{params!r}".encode()).hexdigest()[:16]
