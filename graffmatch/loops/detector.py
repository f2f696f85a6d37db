"""Online loop detection: ``LoopDetector(config).add(scan) -> list[LoopClosure]``.

Each added scan is reduced to its landmark map and descriptor and stored; then the earlier scans
outside the exclusion window are searched for candidates, the best ``top_k`` are verified and
those whose confidence reaches ``verification.min_confidence`` come back as loop closures.
"""

from __future__ import annotations

import time
import warnings
from collections import OrderedDict
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from graffmatch.errors import InvalidInputError
from graffmatch.evaluation.loop_closures import keep_most_salient
from graffmatch.geometry.landmarks import LandmarkSet
from graffmatch.lidar.extractor import LandmarkExtractor, LandmarkExtractorConfig
from graffmatch.loops.consistency import apply_sequence_consistency
from graffmatch.loops.database import (
    LandmarkDatabase,
    decode_points,
    encode_points,
    with_evidence_points,
)
from graffmatch.loops.descriptor import DescriptorConfig, landmark_descriptor
from graffmatch.loops.local_map import local_map_at
from graffmatch.loops.place_check import (
    PlaceCloud,
    place_check_scans,
    place_cloud,
    remeasure,
    scan_place_cloud,
)
from graffmatch.loops.plan import verify_query
from graffmatch.loops.quickcheck import QuickCheckConfig, QuickIndex, quick_check_many, quick_index
from graffmatch.loops.retrieval import RetrievalConfig, eligible_count, make_retriever
from graffmatch.loops.verification_config import LOOP_POINT_HYPOTHESES, VerificationConfig
from graffmatch.loops.verify import LoopClosure, scan_pass, verify_candidate
from graffmatch.matcher import GraffMatchConfig
from graffmatch.pipeline import ScanMatcher, ScanMatcherConfig
from graffmatch.verification.evidence import evidence_points as matcher_evidence_points
from graffmatch.verification.evidence import voxel_downsample


def loop_matcher_config() -> GraffMatchConfig:
    """The loop detector's verified matcher: the defaults with point hypotheses on (they only act on
    the scan pass's raw-scan evidence; ``verification_config.LOOP_POINT_HYPOTHESES``, session 16)."""
    cfg = GraffMatchConfig()
    cfg.verification.point_hypotheses = LOOP_POINT_HYPOTHESES
    return cfg


class LoopDetectorConfig(BaseModel):
    """Everything that decides which loops are found (written next to every result)."""

    model_config = ConfigDict(extra="forbid")

    extractor: LandmarkExtractorConfig = Field(default_factory=LandmarkExtractorConfig)
    use_labels: bool = Field(True, description="use semantic labels when the dataset has them")
    matcher: GraffMatchConfig = Field(default_factory=loop_matcher_config)
    descriptor: DescriptorConfig = Field(default_factory=DescriptorConfig)
    retrieval: RetrievalConfig = Field(default_factory=RetrievalConfig)
    verification: VerificationConfig = Field(default_factory=VerificationConfig)
    quick: QuickCheckConfig = Field(default_factory=QuickCheckConfig)


class LoopDetector:
    """Scan-by-scan loop closure detection over a growing landmark database."""

    def __init__(self, config: LoopDetectorConfig | None = None, scans: Any = None) -> None:
        """``scans``: the added scans, indexable in the order they were added (the dataset being played, or a list of
        point arrays): ``scans[i]`` is read when the place check re-measures a loop estimated just beyond
        ``verification.max_translation_m`` (:mod:`.place_check`); without it such a loop stays refused, because the
        database keeps landmarks only."""
        self.config = config or LoopDetectorConfig()
        self.scans = scans
        self._place: OrderedDict[int, PlaceCloud] = OrderedDict()
        self._place_ok: bool | None = None  # whether the place check runs on ``scans`` (decided at the first query)
        self.db = LandmarkDatabase()
        self.retriever = make_retriever(self.config.retrieval)
        # One configured scan-to-scan path (graffmatch.pipeline.ScanMatcher): the same extractor
        # and verified matcher as register_scans, the CLI, the demo and the evaluation.
        # The database keeps landmarks (and, for landmark-poor scans, a quantised evidence
        # cloud), never the whole scan's range image (LandmarkSet.scan_ranges, ~4 ms a scan),
        # which would be computed and dropped: skip it. The stored tables are the same (tests/loops/test_units.py).
        extractor = self.config.extractor.model_copy(update={"scan_ranges": False})
        self.scan_matcher = ScanMatcher(ScanMatcherConfig(extractor=extractor, matcher=self.config.matcher))
        self.matcher = self.scan_matcher
        self.timings: dict[str, list[float]] = {"extract": [], "retrieve": [], "verify": []}
        self._poses: list[NDArray | None] = []  # odometry poses given to add(), for consistency
        self._recent: dict[int, dict] = {}  # verification records of the last queries

    @property
    def extractor(self) -> LandmarkExtractor:
        return self.scan_matcher.extractor

    def prepare(self, landmarks: LandmarkSet) -> tuple[LandmarkSet, NDArray[np.float32]]:
        """The stored landmark map (most salient per type) and its descriptor; a landmark-poor
        map (fewer than ``evidence_points_below`` landmarks) also keeps the evidence cloud of
        its support points, as the database stores it (quantised)."""
        ls = keep_most_salient(landmarks.without_points(), self.config.verification.max_landmarks_per_type)
        if len(ls) < self.config.verification.evidence_points_below:
            ls = with_evidence_points(ls, self.evidence_points(landmarks))
        return ls, landmark_descriptor(ls, self.config.descriptor)

    def stored_scan(self, stored: LandmarkSet, cloud_points: NDArray | None) -> NDArray[np.float32] | None:
        """The scan cloud the database keeps for a landmark-poor scan (fewer than ``scan_cloud_below``
        stored landmarks): its non-ground points (the extractor's ``last_cloud``) voxelised and capped
        as raw-scan evidence uses them (``scan_voxel``, ``scan_max_points``), on the storage grid;
        None otherwise. Why: landmark-poor pairs can then be verified on whole scans (verify.scan_pass)."""
        if cloud_points is None or not self.config.verification.keeps_scan_cloud(len(stored)):
            return None
        v = self.config.matcher.verification
        P = voxel_downsample(np.asarray(cloud_points, float).reshape(-1, 3), v.scan_voxel, v.scan_max_points)
        return decode_points(encode_points(P)) if len(P) >= 10 else None

    def evidence_points(self, landmarks: LandmarkSet) -> NDArray[np.float32] | None:
        """The verified matcher's evidence cloud of a scan's landmarks (non-ground support points,
        its voxel size and cap), on the database's storage grid; None without points."""
        v = self.config.matcher.verification
        P = matcher_evidence_points(landmarks, v.voxel, v.max_points)
        return None if P is None else decode_points(encode_points(P))

    def add(
        self,
        scan: Any,
        timestamp: float | None = None,
        position: NDArray | None = None,
        pose: NDArray | None = None,
    ) -> list[LoopClosure]:
        """Add a scan and return its verified loop closures (best confidence first).

        ``scan``: a :class:`graffmatch.datasets.base.Scan`, an (N, 3|4) point array, or a
        :class:`LandmarkSet` already extracted. ``timestamp`` defaults to the scan's (or the
        index); ``position`` (odometry estimate) is needed by the radius retrievers only;
        ``pose`` (4x4 odometry pose, world <- scan; its translation serves as ``position``) lets
        a weak point-verified loop count when an earlier query's loop agrees with it
        (:mod:`.consistency`; online only the earlier side of the window is known, so
        ``graffmatch loops`` may confirm a few more).
        """
        t0 = time.perf_counter()
        sc = None
        cloud = None
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
            if self.extractor.last_cloud is not None:
                cloud = self.extractor.last_cloud.points
            if self.config.retrieval.method == "scan-context":
                from graffmatch.evaluation.baselines.scan_context import scan_context

                sc = scan_context(points[:, :3]).astype(np.float32)
        if timestamp is None:
            timestamp = float(getattr(scan, "timestamp", len(self.db)))
        if self.db.timestamps and timestamp < self.db.timestamps[-1]:
            raise InvalidInputError(
                f"timestamps must not decrease: {timestamp} after {self.db.timestamps[-1]}"
            )
        if pose is not None:
            pose = np.asarray(pose, float)
            if pose.shape != (4, 4):
                raise InvalidInputError(f"pose must be a 4x4 matrix, got {pose.shape}")
            if position is None:
                position = pose[:3, 3]
        ls, desc = self.prepare(ls)
        stored_scan = self.stored_scan(ls, cloud)
        self._poses.append(pose)
        self.timings["extract"].append(time.perf_counter() - t0)
        extra: dict[str, Any] = {"scan_context": sc} if sc is not None else {}
        extra["scan"] = stored_scan
        extra["local"] = None
        q = self.db.add(ls, desc, timestamp, position, **extra)
        v = self.config.matcher.verification
        local = local_map_at(q, self.db.landmarks.__getitem__, self._pose_of, self.config.verification, v.voxel,
                             v.max_points)
        if local is not None:  # matched on its local map: its descriptor too (loops/local_map.py)
            self.db.extra["local"][q] = local  # the database.add above made the slot
            self.db.descriptors[q] = landmark_descriptor(local, self.config.descriptor)
        self.timings["extract"][-1] = time.perf_counter() - t0
        if self.config.verification.quick_check:  # per-scan precomputation, with the extraction
            t_q = time.perf_counter()
            self.quick_index(q)
            self.timings["extract"][-1] += time.perf_counter() - t_q
        return self.detect(q)

    def warm_up(self, points: bool = True) -> float:
        """Load, or on a fresh install compile, the numba kernels a query runs, before any query
        is timed; returns the seconds it took.

        Why: otherwise the first query of a process pays for them and its time says so. In a
        worker with a cold numba cache the first verification on points took ~300 s (niced, load
        7-9) and was booked as that query's time: the 291 ms a query of session 12's KISS-ICP
        downtown-s1 row (docs/loops.md, session 13). With a warm cache the loading still costs
        ~1-2 s a process. The scenes are synthetic, stored as the database stores scans (same
        dtypes and codec), so verification compiles for the same argument types; whatever a
        drive's own data reaches beyond them (rare branches) still loads at first use. No loop
        depends on it: the matcher keeps no state between calls. ``points``: also a pair verified
        on evidence points (the path of landmark-poor scans)."""
        from graffmatch.datasets.landmark_scene import make_scene_pair
        from graffmatch.geometry.transforms import invert
        from graffmatch.loops.database import decode_landmarks, encode_landmarks
        from graffmatch.registration.closed_form import warm_up_exact

        t0 = time.perf_counter()
        cfg = self.config

        def stored(ls: LandmarkSet, P: NDArray | None = None) -> LandmarkSet:
            out = decode_landmarks(encode_landmarks(ls))
            return with_evidence_points(out, None if P is None else decode_points(encode_points(P)))

        warm_up_exact()  # the registration's exact path for rounding-fragile groups
        # landmark-poor, medium (the solver cuts subgraphs of its active set), rich with outliers,
        # and noise-free
        for n_poles, n_planes, noise, outliers, seed in ((4, 6, 1.0, 0, 0), (9, 17, 1.0, 0, 3), (15, 30, 1.0, 12, 0),
                                                         (6, 20, 0.0, 0, 0)):
            sc = make_scene_pair(n_poles, n_planes, seed=seed, yaw_deg=30.0, translation=(2.0, 1.0, 0.0),
                                 angle_noise_deg=noise, anchor_noise=0.1 * noise, n_outliers=outliers)
            src, tgt = stored(sc.source), stored(sc.target)
            verify_candidate(src, tgt, self.matcher, cfg.verification)
            if cfg.verification.quick_check:
                qs, qt = quick_index(src, cfg.quick), quick_index(tgt, cfg.quick)
                quick_check_many(qs, [qt, qs], cfg.quick)
        if points:
            sc = make_scene_pair(4, 6, seed=0, yaw_deg=30.0, translation=(2.0, 1.0, 0.0))
            P_t = np.random.default_rng(0).uniform([-30, -30, 0], [30, 30, 6], (1500, 3))
            T_s_t = invert(sc.T_target_source)
            P_s = P_t @ T_s_t[:3, :3].T + T_s_t[:3, 3]
            src, tgt = stored(sc.source, P_s), stored(sc.target, P_t)
            verify_candidate(src, tgt, self.matcher, cfg.verification)
            if cfg.verification.scan_cloud_below > 0:  # the raw-scan pass of landmark-poor pairs
                scan_pass(src, tgt, decode_points(encode_points(P_s)), decode_points(encode_points(P_t)),
                          self.matcher, cfg.verification)
        if cfg.verification.place_check and cfg.verification.max_translation_m is not None:
            # the place check's ICP: Open3D's first registration call in a process takes ~1 s
            P = place_cloud(np.random.default_rng(1).uniform([-20, -20, 0], [20, 20, 6], (2000, 3)))
            remeasure(P, P, np.eye(4))
            if self.scans is not None and (getattr(self.scans, "__len__", None) and len(self.scans) > 0):
                scan_place_cloud(self.scans, 0)  # the scan reader's compiled row check, de-skewing
        return time.perf_counter() - t0

    def place_cloud(self, i: int) -> PlaceCloud:
        """Scan i's place-check cloud from ``scans`` (the last few kept)."""
        if i not in self._place:
            self._place[i] = scan_place_cloud(self.scans, i)
            if len(self._place) > 64:
                self._place.popitem(last=False)
        return self._place[i]

    def _pose_of(self, i: int) -> NDArray | None:
        return self._poses[i] if 0 <= i < len(self._poses) else None

    def landmarks(self, i: int) -> LandmarkSet:
        """The map scan i is matched on: its local map when it has one, else its stored landmarks."""
        local = self.db.extra.get("local")
        if local is not None and i < len(local) and local[i] is not None:
            return local[i]
        return self.db.landmarks[i]

    def scan_of(self, i: int) -> NDArray[np.float32] | None:
        """Scan i's stored scan cloud (None: it keeps none, or has ``scan_cloud_below`` landmarks or
        more: a database stored with a larger setting verifies as this config says)."""
        scans = self.db.extra.get("scan")
        if scans is None or i >= len(scans) or not self.config.verification.keeps_scan_cloud(len(self.db.landmarks[i])):
            return None
        return scans[i]

    def _per_scan(self, key: str, i: int, make: Callable[[], QuickIndex]) -> QuickIndex:
        """Scan i's entry of the database's per-scan cache ``key``, made once."""
        cache = self.db.extra.setdefault(key, [])
        if len(cache) < len(self.db):
            cache.extend([None] * (len(self.db) - len(cache)))
        if cache[i] is None:
            cache[i] = make()
        return cache[i]

    def quick_index(self, i: int) -> QuickIndex:
        """The BEV quick-check index of scan i (of its local map when it has one), kept in the database."""
        return self._per_scan("quick", i, lambda: quick_index(self.landmarks(i), self.config.quick))

    def own_quick_index(self, i: int) -> QuickIndex:
        """The quick-check index of scan i's own landmarks: a pair verified on the own maps is screened on them
        (``plan.on_own_maps``); the same index as :meth:`quick_index` for a scan without a local map."""
        if self.landmarks(i) is self.db.landmarks[i]:
            return self.quick_index(i)
        return self._per_scan("own_quick", i, lambda: quick_index(self.db.landmarks[i], self.config.quick))

    def _consistent(self, query: int, recs: list[dict]) -> list[dict]:
        """The query's records after the odometry's post-pass (given poses): weak loops far from the odometry
        refused, weak loops that an earlier query's loop confirms accepted (``apply_sequence_consistency``)."""
        W = max(self.config.verification.consistency_window, 0)
        self._recent[query] = {"query": query, "candidates": recs}
        for q in [q for q in self._recent if q < query - W]:
            del self._recent[q]
        if len(self._poses) <= query or any(p is None for p in self._poses[: query + 1]):
            return recs
        window = {q: r for q, r in self._recent.items() if q <= query}
        out = apply_sequence_consistency(window, np.stack(self._poses[: query + 1]), self.config.verification)
        return out[query]["candidates"]

    def detect(self, query: int) -> list[LoopClosure]:
        """Retrieve and verify the candidates of a scan already in the database."""
        if self._place_ok is None:  # once: without scans, or with smeared ones, the check is off and says why
            self._place_ok = place_check_scans(self.scans, self.config.verification) is not None
        t1 = time.perf_counter()
        m = eligible_count(self.db.timestamps, query, self.config.retrieval)
        idx, dist = self.retriever.candidates(self.db, query, m)
        t2 = time.perf_counter()
        self.timings["retrieve"].append(t2 - t1)
        recs = verify_query(
            query, list(zip(idx.tolist(), dist.tolist(), strict=True)), self.landmarks,
            self.quick_index, self.matcher, self.config.verification, self.config.quick, self.scan_of, self._pose_of,
            self.db.landmarks.__getitem__, self.own_quick_index,
            self.place_cloud if self._place_ok else None,
        )
        recs = self._consistent(query, recs)
        out = []
        for r in recs:
            if r["T"] is None:
                continue
            out.append(LoopClosure(
                query=query,
                match=r["match"],
                T_match_query=np.asarray(r["T"], float).reshape(4, 4),
                confidence=r["confidence"],
                overlap=r["overlap"],
                n_associations=r["n_associations"],
                n_agreeing=r["n_agreeing"],
                retrieval_rank=r["rank"],
                retrieval_distance=r["retrieval_distance"],
                valid=r["confidence"] >= self.config.verification.min_confidence,
                info={"seconds": r["seconds"], "rms_offset": r["rms_offset"], "quick_score": r["quick_score"],
                      "consistent_with": r.get("consistent_with")},
            ))
        self.timings["verify"].append(time.perf_counter() - t2)
        self.last_candidates = out
        self.last_records = recs
        return sorted((c for c in out if c.valid), key=lambda c: -c.confidence)


#: What this process has warmed up (:meth:`LoopDetector.warm_up`): "landmarks", "points", "place" (the scan reader).
_WARMED: set[str] = set()


def has_point_pairs(db: LandmarkDatabase) -> bool:
    """Whether a query can verify a pair on points (two scans keep evidence points): then the warm-up covers that
    path, and the raw-scan pass, too (``run_loops``' workers and ``bench_loops_speed.py``)."""
    return sum(ls.points is not None for ls in db.landmarks) >= 2


def warm_up_once(det: LoopDetector, points: bool) -> tuple[float, float]:
    """(wall, CPU) seconds of this process's kernel warm-up; (0, 0) when it was done before.

    Why: a query's time should be the query's; loading or compiling numba kernels is a cost of
    the process (once, like starting it), so ``run_loops``' workers do it first and report it
    apart (``warmup_s``)."""
    v = det.config.verification
    place = det.scans is not None and v.place_check and v.max_translation_m is not None
    need = {"landmarks"} | ({"points"} if points else set()) | ({"place"} if place else set())
    if need <= _WARMED:
        return 0.0, 0.0
    c0 = time.process_time()
    wall = det.warm_up(points="points" in need - _WARMED)
    _WARMED.update(need)
    return wall, time.process_time() - c0
