"""Reading a built loop-closure dataset back: ``for pair in LoopClosureDataset.load(dir)``.

Kept apart from the builder so that the evaluation's workers load pairs without importing the
LiDAR front end.
"""

from __future__ import annotations

import functools
import json
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from graffmatch.errors import InvalidInputError, MalformedFileError
from graffmatch.geometry.landmarks import LandmarkSet

FORMAT_NAME = "graffmatch-loop-closures"
FORMAT_VERSION = 1
PAIRS_FILE = "pairs.json"
LANDMARK_DIR = "landmarks"
CACHE_INDEX = "cache.json"

Array = NDArray[np.float64]


@functools.lru_cache(maxsize=1024)
def _load_landmarks(path: str, mtime_ns: int, size: int) -> LandmarkSet:
    return LandmarkSet.load(path)


def load_landmarks_cached(path: str | Path) -> LandmarkSet:
    """Load a landmark file once per process (keyed on path, mtime and size).

    Pairs share places, so the sets are shared too; treat them as read-only.
    """
    p = Path(path)
    try:
        st = p.stat()
    except OSError as exc:
        raise MalformedFileError(f"{p}: landmark file missing ({exc})") from exc
    return _load_landmarks(str(p.resolve()), st.st_mtime_ns, st.st_size)


@dataclass
class LoopClosurePair:
    """One loop closure: two landmark sets and the ground truth relating them."""

    index: int
    source_scan: int
    target_scan: int
    T_target_source: Array
    true_matches: NDArray[np.int64]
    n_possible: int
    iir: float
    case: int
    distance: float
    rotation_deg: float
    n_true_lines: int
    n_true_planes: int
    source_scan_path: Path
    target_scan_path: Path
    source_landmarks_path: Path
    target_landmarks_path: Path
    info: dict[str, Any] = field(default_factory=dict)
    #: A pair without overlap (case 0, no true matches): a valid result on it is wrong.
    negative: bool = False

    @property
    def source(self) -> LandmarkSet:
        """Landmarks of the source scan (its frame), with support points when stored."""
        return load_landmarks_cached(self.source_landmarks_path)

    @property
    def target(self) -> LandmarkSet:
        """Landmarks of the target scan (its frame)."""
        return load_landmarks_cached(self.target_landmarks_path)

    @property
    def pair_id(self) -> str:
        return f"{self.source_scan:06d}-{self.target_scan:06d}"

    def __repr__(self) -> str:
        return (
            f"LoopClosurePair({self.pair_id}, case={self.case}, iir={self.iir:.3f}, "
            f"true_matches={len(self.true_matches)}/{self.n_possible}, "
            f"distance={self.distance:.1f} m, rotation={self.rotation_deg:.0f} deg)"
        )


class LoopClosureDataset(Sequence):
    """A built loop-closure dataset: ``for pair in LoopClosureDataset.load(dir): ...``.

    Landmark sets are loaded lazily and shared between the pairs of a place.
    """

    def __init__(self, root: Path, doc: dict[str, Any]) -> None:
        self.root = Path(root)
        self.doc = doc
        # the rules' module imports the LiDAR front end's config (Open3D): only when reading
        from graffmatch.evaluation.places import LoopClosureConfig

        self.config = LoopClosureConfig.model_validate(doc["config"])
        self.summary: dict[str, Any] = doc.get("summary", {})
        self.name: str = doc.get("dataset", {}).get("name", self.root.name)
        #: Encoding of the scan files ("kitti-bin", "nclt-bin", "unknown") for point methods.
        self.scan_format: str = doc.get("dataset", {}).get("scan_format", "kitti-bin")
        self.places: dict[int, dict[str, Any]] = {int(p["scan"]): p for p in doc["places"]}
        self.pairs = [self._make_pair(k, p) for k, p in enumerate(doc["pairs"])]
        #: Pairs without overlap (``negative_min_distance`` apart); not part of iteration, which
        #: yields the loop closures; :meth:`with_negatives` gives both.
        self.negatives = [
            self._make_pair(len(self.pairs) + k, p) for k, p in enumerate(doc.get("negatives", []))
        ]

    @classmethod
    def load(cls, root: str | Path) -> LoopClosureDataset:
        root = Path(root)
        f = root / PAIRS_FILE
        if not f.is_file():
            raise InvalidInputError(f"not a loop-closure dataset (no {PAIRS_FILE}): {root}")
        try:
            doc = json.loads(f.read_text())
        except json.JSONDecodeError as exc:
            raise MalformedFileError(f"{f}: not valid JSON ({exc})") from exc
        if doc.get("format") != FORMAT_NAME:
            raise MalformedFileError(f"{f}: not a {FORMAT_NAME} file")
        if int(doc.get("version", 0)) > FORMAT_VERSION:
            raise MalformedFileError(
                f"{f}: format version {doc.get('version')} is newer than {FORMAT_VERSION}"
            )
        for key in ("config", "places", "pairs"):
            if key not in doc:
                raise MalformedFileError(f"{f}: missing {key!r}")
        return cls(root, doc)

    def landmark_path(self, scan: int) -> Path:
        place = self.places.get(int(scan))
        if place is None:
            raise MalformedFileError(f"{self.root / PAIRS_FILE}: scan {scan} is not a place")
        return self.root / place["landmarks"]

    def landmarks(self, scan: int) -> LandmarkSet:
        """Landmarks of a place by scan index."""
        return load_landmarks_cached(self.landmark_path(scan))

    def _make_pair(self, k: int, p: dict[str, Any]) -> LoopClosurePair:
        try:
            src, tgt = int(p["source_scan"]), int(p["target_scan"])
            T = np.asarray(p["T_target_source"], dtype=float).reshape(4, 4)
            m = np.asarray(p["true_matches"], dtype=np.int64).reshape(-1, 2)
            pair = LoopClosurePair(
                index=k,
                source_scan=src,
                target_scan=tgt,
                T_target_source=T,
                true_matches=m,
                n_possible=int(p["n_possible"]),
                iir=float(p["iir"]),
                case=int(p["case"]),
                distance=float(p["distance"]),
                rotation_deg=float(p["rotation_deg"]),
                n_true_lines=int(p["n_true_lines"]),
                n_true_planes=int(p["n_true_planes"]),
                source_scan_path=Path(self.places[src]["scan_path"]),
                target_scan_path=Path(self.places[tgt]["scan_path"]),
                source_landmarks_path=self.landmark_path(src),
                target_landmarks_path=self.landmark_path(tgt),
                info={
                    key: p[key]
                    for key in (
                        "path_length",
                        "kappa",
                        "gt_rotation_error_deg",
                        "gt_translation_error",
                    )
                    if key in p
                },
                negative=bool(p.get("negative", False)),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise MalformedFileError(
                f"{self.root / PAIRS_FILE}: pair {k} is malformed ({exc})"
            ) from exc
        return pair

    def __len__(self) -> int:
        return len(self.pairs)

    def __getitem__(self, i: int) -> LoopClosurePair:  # type: ignore[override]
        return self.pairs[i]

    def __iter__(self) -> Iterator[LoopClosurePair]:
        return iter(self.pairs)

    def with_negatives(self) -> list[LoopClosurePair]:
        """The loop closures, then the negative pairs (what a study evaluates)."""
        return [*self.pairs, *self.negatives]

    def of_case(self, case: int) -> list[LoopClosurePair]:
        return [p for p in self.pairs if p.case == case]

    def case_counts(self) -> dict[int, int]:
        return {c: sum(p.case == c for p in self.pairs) for c in (1, 2, 3)}

    def __repr__(self) -> str:
        c = self.case_counts()
        return (
            f"LoopClosureDataset({self.name!r}, pairs={len(self)}, cases={c}, "
            f"negatives={len(self.negatives)}, "
            f"places={len(self.places)})"
        )
