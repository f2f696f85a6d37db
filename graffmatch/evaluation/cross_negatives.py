"""Negative pairs across datasets: a KITTI scan against a courtyard scan or a simulated one.

No two such places share anything, so a method that calls one of these pairs valid is wrong.
The builder extracts landmarks for a few evenly spaced scans of each source (each with its own
suite's front end), pairs every source with every other, and writes a loop-closure dataset
with only ``negatives`` (``pairs.json`` format of :mod:`~graffmatch.evaluation.loop_closures`),
which the runner and the report treat like any suite's negative pairs.

Place ids are global: source ``k``'s scan ``i`` is place ``k * PLACE_ID_STRIDE + i``, and its
landmark file lives under ``sources/<name>/``.
"""

from __future__ import annotations

import json
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from graffmatch.datasets.base import Dataset
from graffmatch.errors import InvalidInputError
from graffmatch.evaluation.loop_closure_dataset import (
    FORMAT_NAME,
    FORMAT_VERSION,
    LANDMARK_DIR,
    PAIRS_FILE,
)
from graffmatch.evaluation.loop_closures import extract_place_landmarks
from graffmatch.evaluation.places import LoopClosureConfig, possible_matches
from graffmatch.geometry.landmarks import LandmarkSet

PLACE_ID_STRIDE = 1_000_000


@dataclass
class NegativeSource:
    """One dataset the negatives are drawn from, with the front end its suite uses."""

    name: str
    dataset: Dataset
    config: LoopClosureConfig
    n_places: int


def _evenly(n: int, k: int) -> list[int]:
    if n <= 0 or k <= 0:
        return []
    return np.unique(np.linspace(0, n - 1, min(k, n)).round().astype(int)).tolist()


def build_cross_negatives(
    sources: Sequence[NegativeSource],
    out_dir: str | Path,
    max_pairs: int,
    progress: bool = True,
) -> dict[str, Any]:
    """Write a dataset of cross-dataset negative pairs into ``out_dir``; returns its summary."""
    if len(sources) < 2:
        raise InvalidInputError(
            f"cross-dataset negatives need two sources, got {[s.name for s in sources]}"
        )
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    places: list[dict[str, Any]] = []
    sets: dict[int, LandmarkSet] = {}
    by_source: list[list[int]] = []
    for k, src in enumerate(sources):
        folder = out / "sources" / src.name
        scans = _evenly(len(src.dataset), src.n_places)
        extract_place_landmarks(src.dataset, scans, folder, src.config, progress)
        ids = []
        for i in scans:
            pid = k * PLACE_ID_STRIDE + i
            rel = f"sources/{src.name}/{LANDMARK_DIR}/{i:06d}.npz"
            sets[pid] = LandmarkSet.load(out / rel)
            places.append(
                {
                    "scan": pid,
                    "scan_path": str(Path(src.dataset.scan_path(i)).resolve()),
                    "landmarks": rel,
                    "source": src.name,
                    "counts": sets[pid].counts(),
                }
            )
            ids.append(pid)
        by_source.append(ids)
    candidates = [
        (b, a)
        for ka in range(len(by_source))
        for kb in range(ka + 1, len(by_source))
        for a in by_source[ka]
        for b in by_source[kb]
    ]
    chosen = [candidates[i] for i in _evenly(len(candidates), max_pairs)]
    negatives = [
        {
            "source_scan": int(s),
            "target_scan": int(t),
            "T_target_source": np.eye(4).tolist(),  # no relative pose exists
            "true_matches": [],
            "n_possible": possible_matches(sets[s], sets[t]),
            "iir": 0.0,
            "case": 0,
            "distance": float("inf"),
            "rotation_deg": 0.0,
            "n_true_lines": 0,
            "n_true_planes": 0,
            "negative": True,
        }
        for s, t in chosen
    ]
    summary = {
        "dataset": "cross-dataset",
        "sources": {s.name: len(ids) for s, ids in zip(sources, by_source, strict=True)},
        "n_scans": len(places),
        "n_places": len(places),
        "n_revisits": 0,
        "n_valid": 0,
        "n_negatives": len(negatives),
        "cases": {},
        "total_s": time.perf_counter() - t0,
    }
    doc = {
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "dataset": {"name": "cross-dataset", "loader": "cross", "scan_format": "kitti-bin"},
        "config": LoopClosureConfig(negative_min_distance=None).model_dump(mode="json"),
        "places": places,
        "pairs": [],
        "negatives": negatives,
        "summary": summary,
    }
    (out / PAIRS_FILE).write_text(json.dumps(doc, indent=1))
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    return summary
