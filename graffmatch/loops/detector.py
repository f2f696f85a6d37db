"""Online loop detection: ``LoopDetector(config).add(scan) -> list[LoopClosure]``.

Each added scan is reduced to its landmark map and descriptor and stored; then the earlier scans
outside the exclusion window are searched for candidates, the best ``top_k`` are verified and
those whose confidence reaches ``verification.min_confidence`` come back as loop closures.
"""

from __future__ import annotations

import time
import warnings
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from graffmatch.errors import InvalidInputError
from graffmatch.evaluation.loop_closures import keep_most_salient
from graffmatch.geometry.landmarks import LandmarkSet
from graffmatch.lidar.extractor import LandmarkExtractor, LandmarkExtractorConfig
from graffmatch.loops.database import LandmarkDatabase
from graffmatch.loops.descriptor import DescriptorConfig, landmark_descriptor
from graffmatch.loops.retrieval import RetrievalConfig, eligible_count, make_retriever
from graffmatch.loops.verify import LoopClosure, VerificationConfig, verify_candidate
from graffmatch.matcher import GraffMatchConfig
from graffmatch.pipeline import ScanMatcher, ScanMatcherConfig


class LoopDetectorConfig(BaseModel):
    """Everything that decides which loops are found (written next to every result)."""

    model_config = ConfigDict(extra="forbid")

    extractor: LandmarkExtractorConfig = Field(default_factory=LandmarkExtractorConfig)
    use_labels: bool = Field(True, description="use semantic labels when the dataset has them")
    matcher: GraffMatchConfig = Field(default_factory=GraffMatchConfig)
    descriptor: DescriptorConfig = Field(default_factory=DescriptorConfig)
    retrieval: RetrievalConfig = Field(default_factory=RetrievalConfig)
    verification: VerificationConfig = Field(default_factory=VerificationConfig)


class LoopDetector:
    """Scan-by-scan loop closure detection over a growing landmark database."""

    def __init__(self, config: LoopDetectorConfig | None = None) -> None:
        self.config = config or LoopDetectorConfig()
        self.db = LandmarkDatabase()
        self.retriever = make_retriever(self.config.retrieval)
        # One configured scan-to-scan path (graffmatch.pipeline.ScanMatcher): the same extractor
        # and verified matcher as register_scans, the CLI, the demo and the evaluation.
        self.scan_matcher = ScanMatcher(
            ScanMatcherConfig(extractor=self.config.extractor, matcher=self.config.matcher)
        )
        self.matcher = self.scan_matcher
        self.timings: dict[str, list[float]] = {"extract": [], "retrieve": [], "verify": []}

    @property
    def extractor(self) -> LandmarkExtractor:
        return self.scan_matcher.extractor

    def prepare(self, landmarks: LandmarkSet) -> tuple[LandmarkSet, NDArray[np.float32]]:
        """The stored landmark map (most salient per type) and its descriptor."""
        ls = keep_most_salient(landmarks.without_points(), self.config.verification.max_landmarks_per_type)
        return ls, landmark_descriptor(ls, self.config.descriptor)

    def add(
        self,
        scan: Any,
        timestamp: float | None = None,
        position: NDArray | None = None,
    ) -> list[LoopClosure]:
        """Add a scan and return its verified loop closures (best confidence first).

        ``scan``: a :class:`graffmatch.datasets.base.Scan`, an (N, 3|4) point array, or a
        :class:`LandmarkSet` already extracted. ``timestamp`` defaults to the scan's (or the
        index); ``position`` (odometry estimate) is needed by the radius retriever only.
        """
        t0 = time.perf_counter()
        sc = None
        if isinstance(scan, LandmarkSet):
            ls = scan
        else:
            points = getattr(scan, "points", scan)
            labels = getattr(scan, "labels", None) if self.config.use_labels else None
            points = np.asarray(points)
            if points.ndim != 2 or points.shape[1] < 3:
                raise InvalidInputError(f"scan points must be (N, >=3), got {points.shape}")
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                ls = self.extractor.extract(points, labels)
            if self.config.retrieval.method == "scan-context":
                from graffmatch.evaluation.baselines.scan_context import scan_context

                sc = scan_context(points[:, :3]).astype(np.float32)
        if timestamp is None:
            timestamp = float(getattr(scan, "timestamp", len(self.db)))
        if self.db.timestamps and timestamp < self.db.timestamps[-1]:
            raise InvalidInputError(
                f"timestamps must not decrease: {timestamp} after {self.db.timestamps[-1]}"
            )
        ls, desc = self.prepare(ls)
        self.timings["extract"].append(time.perf_counter() - t0)
        extra = {"scan_context": sc} if sc is not None else {}
        q = self.db.add(ls, desc, timestamp, position, **extra)
        return self.detect(q)

    def detect(self, query: int) -> list[LoopClosure]:
        """Retrieve and verify the candidates of a scan already in the database."""
        t1 = time.perf_counter()
        m = eligible_count(self.db.timestamps, query, self.config.retrieval)
        idx, dist = self.retriever.candidates(self.db, query, m)
        t2 = time.perf_counter()
        self.timings["retrieve"].append(t2 - t1)
        out = []
        for rank, (j, d) in enumerate(zip(idx.tolist(), dist.tolist(), strict=True)):
            v = verify_candidate(self.db.landmarks[query], self.db.landmarks[j], self.matcher, self.config.verification)
            if v["T_match_query"] is None:
                continue
            lc = LoopClosure(
                query=query,
                match=int(j),
                T_match_query=v["T_match_query"],
                confidence=v["confidence"],
                overlap=v["overlap"],
                n_associations=v["n_associations"],
                n_agreeing=v["n_agreeing"],
                retrieval_rank=rank,
                retrieval_distance=float(d),
                valid=v["confidence"] >= self.config.verification.min_confidence,
                info={"message": v["message"], "seconds": v["seconds"], "rms_offset": v.get("rms_offset")},
            )
            out.append(lc)
        self.timings["verify"].append(time.perf_counter() - t2)
        self.last_candidates = out
        return sorted((c for c in out if c.valid), key=lambda c: -c.confidence)
