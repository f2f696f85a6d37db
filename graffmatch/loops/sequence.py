"""Loop closure over a whole recorded drive: ``run_loops(dataset, out_dir, config)``.

1. **Landmarks** of every scan, extracted in parallel (any executor: local processes, Dask,
   Ray) and cached in ``<out>/landmarks/NNNNNN.npz`` (a compact table, :mod:`.database`); the
   cache key covers the scan file, the labels and the extractor config, so a rerun only
   extracts what changed.
2. **Database** of landmark maps and descriptors, in scan order.
3. **Queries**: for every scan, the candidates among the earlier scans outside the exclusion
   window (:mod:`.retrieval`), pre-screened by the BEV quick check (:mod:`.quickcheck`, its
   per-scan index built before the query's clock starts) and the passing ones verified with the
   matcher, best first, until one is accepted (:func:`.verify.verify_query`), in parallel chunks.
   Every finished query is appended to ``<out>/queries.jsonl`` at once, so a killed run resumes
   where it stopped. ``queries.meta.json`` holds the fingerprint of the database (every scan's
   cache key) and the config those records were computed with; when either changed (scans
   re-simulated or re-extracted, another config), the old records are moved aside to
   ``queries.stale.jsonl`` and the queries start again.
4. **Outputs**: ``loops.csv``, ``loops.g2o`` (loop edges; vertices when poses are known),
   ``retrieval.csv``, ``summary.json``, ``config.yaml``; with ``optimize`` also the pose graph
   (:mod:`.posegraph`): ``odometry_kitti.txt``, ``optimized_kitti.txt``, ``optimized_tum.txt``.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
import warnings
from collections import OrderedDict
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import NDArray

from graffmatch.atomic_files import write_bytes_atomic
from graffmatch.datasets.base import ASSUMED_SCAN_RATE_HZ, Dataset
from graffmatch.errors import InvalidInputError, MalformedFileError
from graffmatch.evaluation.executors import make_executor
from graffmatch.geometry.pose_files import write_kitti, write_tum
from graffmatch.loops.consistency import apply_sequence_consistency, refused_by_odometry
from graffmatch.loops.database import (
    POINT_QUANTUM_M,
    LandmarkDatabase,
    landmarks_to_bytes,
    load_landmarks,
    load_scan_cloud,
    save_landmarks,
)
from graffmatch.loops.descriptor import landmark_descriptor
from graffmatch.loops.detector import (
    LoopDetector,
    LoopDetectorConfig,
    has_point_pairs,
    warm_up_once,
)
from graffmatch.loops.io import loop_edges, write_g2o, write_loops_csv
from graffmatch.loops.local_map import attach_local_maps
from graffmatch.loops.place_check import place_check_scans, scan_place_cloud
from graffmatch.loops.plan import verify_query
from graffmatch.loops.quickcheck import QuickIndex, quick_index
from graffmatch.loops.retrieval import eligible_count
from graffmatch.loops.verify import LoopClosure

Progress = Callable[[str, int, int], None]
LANDMARK_DIR = "landmarks"
LOCAL_MAP_DIR = "local_maps"  # the local maps of landmark-poor scans (loops/local_map.py), rewritten every run
QUERIES_FILE = "queries.jsonl"
QUERIES_META = "queries.meta.json"
PLACE_CACHE_SCANS = 64  # place-check clouds a worker keeps (~100 kB each; few scans are ever re-measured)


def _stamp(path: Path | None) -> str:
    if path is None:
        return "none"
    st = Path(path).stat()
    return f"{Path(path).resolve()}|{st.st_size}|{st.st_mtime_ns}"


def _front_end_json(config: LoopDetectorConfig) -> str:
    front = {
        "extractor": config.extractor.model_dump(mode="json"),
        "use_labels": config.use_labels,
        "max_per_type": config.verification.max_landmarks_per_type,
        "scan_context": config.retrieval.method == "scan-context",
    }
    if config.verification.evidence_points_below > 0:  # without points: the keys of tables without points
        v = config.matcher.verification
        front["evidence_points"] = [config.verification.evidence_points_below, v.voxel, v.max_points, POINT_QUANTUM_M]
    if config.verification.scan_cloud_below > 0:  # without scan clouds: the keys of tables without them
        v = config.matcher.verification
        front["scan_cloud"] = [config.verification.scan_cloud_below, v.scan_voxel, v.scan_max_points, POINT_QUANTUM_M]
    return json.dumps(front, sort_keys=True)


def _scan_key(dataset: Dataset, i: int, config: LoopDetectorConfig) -> str:
    parts = [_stamp(dataset.scan_path(i)), _stamp(dataset.label_path(i)) if config.use_labels else "nolabels", _front_end_json(config)]
    tag = getattr(dataset, "cache_tag", None)  # e.g. de-skewed points: other landmarks, same files
    if tag:
        parts.append(str(tag))
    return hashlib.sha256("\n".join(parts).encode()).hexdigest()[:20]


def _extract_task(args: tuple[Dataset, int, str, str]) -> tuple[int, float]:
    """Worker: read scan i, extract, keep the most salient landmarks, write the table."""
    dataset, i, config_json, out_file = args
    t0 = time.perf_counter()
    config = LoopDetectorConfig.model_validate_json(config_json)
    det = LoopDetector(config)
    scan = dataset[i]
    labels = scan.labels if config.use_labels else None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        ls = det.extractor.extract(scan.points, labels)
    cloud = None if det.extractor.last_cloud is None else det.extractor.last_cloud.points
    ls, _ = det.prepare(ls)
    if config.retrieval.method == "scan-context":
        from graffmatch.evaluation.baselines.scan_context import scan_context

        np.save(out_file.replace(".npz", ".sc.npy"), scan_context(scan.points[:, :3]).astype(np.float32))
    save_landmarks(out_file, ls, det.stored_scan(ls, cloud))
    return i, time.perf_counter() - t0


class _ScanCache:
    """A worker process's landmark maps and quick-check indices, kept across the chunks it runs.

    Per-scan work (loading the table, building the BEV index) is done once per worker, not once
    per chunk: a candidate scan recurs in the chunks of many queries. Keyed by the run folder
    and its database fingerprint (a long-lived Dask/Ray worker may see another run next); the
    least recently used scans are dropped beyond ``max_scans``.
    """

    def __init__(self, max_scans: int = 20_000) -> None:
        self.key: tuple[str, str] | None = None
        self.max_scans = max_scans
        self.landmarks: OrderedDict[int, Any] = OrderedDict()
        self.local: OrderedDict[int, Any] = OrderedDict()
        self.quick: OrderedDict[int, QuickIndex] = OrderedDict()
        self.own_quick: OrderedDict[int, QuickIndex] = OrderedDict()  # own maps' of scans with a local map
        self.scans: OrderedDict[int, Any] = OrderedDict()
        self.place: OrderedDict[int, Any] = OrderedDict()  # the place check's scan clouds (loops/place_check.py)

    def reset(self, key: tuple[str, str]) -> None:
        if key != self.key:
            self.key = key
            self.landmarks.clear()
            self.local.clear()
            self.quick.clear()
            self.own_quick.clear()
            self.scans.clear()
            self.place.clear()

    def get(self, store: OrderedDict, i: int, make: Callable[[], Any], limit: int | None = None) -> Any:
        """``store[i]``, made by ``make()`` on a miss (at most ``limit`` entries, default ``max_scans``)."""
        if i in store:
            store.move_to_end(i)
            return store[i]
        v = store[i] = make()
        if len(store) > (self.max_scans if limit is None else limit):
            store.popitem(last=False)
        return v


_CACHE = _ScanCache()


def _verify_task(args: tuple) -> list[dict]:
    """Worker: verify a chunk of queries (kernels warmed up first, once a process); a record a query.

    ``args``: out_dir, database key, config JSON, the chunk's (query, candidates), whether to warm up
    the point kernels, the odometry poses of the chunk's scans ({scan: 4x4}, or None), and the scans
    matched on their local maps with those maps' key (``(frozenset(), "")`` without), and the dataset the place check
    reads the scans from (None: no place check)."""
    out_dir, database_key, config_json, chunk, warm_points = args[:5]
    poses = args[5] if len(args) > 5 else None
    local_ids, local_key = args[6] if len(args) > 6 else (frozenset(), "")
    dataset = args[7] if len(args) > 7 else None
    config = LoopDetectorConfig.model_validate_json(config_json)
    det = LoopDetector(config, scans=dataset)  # the scans only for its warm-up: the place check's reader
    _CACHE.reset((out_dir, database_key + config.quick.model_dump_json() + local_key))
    warm_s, warm_cpu_s = warm_up_once(det, warm_points)
    index_s = [0.0]

    def own(i: int):
        return _CACHE.get(_CACHE.landmarks, i, lambda: load_landmarks(Path(out_dir) / LANDMARK_DIR / f"{i:06d}.npz"))

    def lm(i: int):  # the map scan i is matched on
        if i not in local_ids:
            return own(i)
        return _CACHE.get(_CACHE.local, i, lambda: load_landmarks(Path(out_dir) / LOCAL_MAP_DIR / f"{i:06d}.npz"))

    def scan(i: int):
        if not config.verification.keeps_scan_cloud(len(own(i))):
            return None
        return _CACHE.get(_CACHE.scans, i, lambda: load_scan_cloud(Path(out_dir) / LANDMARK_DIR / f"{i:06d}.npz"))

    def indexed(store: OrderedDict, i: int, ls: Callable[[int], Any]) -> QuickIndex:
        # per-scan precomputation (like the landmarks themselves): timed apart from the query
        t, hit = time.perf_counter(), i in store
        v = _CACHE.get(store, i, lambda: quick_index(ls(i), config.quick))
        if not hit:
            index_s[0] += time.perf_counter() - t
        return v

    def qi(i: int) -> QuickIndex:
        return indexed(_CACHE.quick, i, lm)

    def own_qi(i: int) -> QuickIndex:  # a pair verified on the own maps is screened on them (plan.on_own_maps)
        return qi(i) if i not in local_ids else indexed(_CACHE.own_quick, i, own)

    def place(i: int):  # read when the place check needs scan i: inside the query's clock
        return _CACHE.get(_CACHE.place, i, lambda: scan_place_cloud(dataset, i), PLACE_CACHE_SCANS)

    place_of = place if dataset is not None and config.verification.place_check else None
    records = []
    for q, cands in chunk:
        for j in [q, *(c for c, _ in cands)]:  # load and index before the query's clock starts
            lm(j)
            if config.verification.scan_cloud_below > 0:
                scan(j)
            if config.verification.quick_check:
                qi(j)
        t0, c0 = time.perf_counter(), time.process_time()
        recs = verify_query(q, cands, lm, qi, det.matcher, config.verification, config.quick,
                            scan if config.verification.scan_cloud_below > 0 else None,
                            None if poses is None else poses.get, own, own_qi, place_of)
        records.append({"query": int(q), "candidates": recs, "verify_s": time.perf_counter() - t0, "verify_cpu_s": time.process_time() - c0})
    if records:
        records[-1]["index_s"] = index_s[0]
        records[0].update(warmup_s=warm_s, warmup_cpu_s=warm_cpu_s)  # 0 when done before
    return records


def _chunk_poses(odometry: NDArray, chunk: list[tuple[int, list[tuple[int, float]]]]) -> dict[int, NDArray]:
    """The odometry poses a chunk's queries and candidates need (not the whole drive's, per task)."""
    ids = {i for q, cands in chunk for i in [q, *(j for j, _ in cands)]}
    return {i: odometry[i] for i in sorted(ids)}


def read_queries(out_dir: str | Path) -> dict[int, dict]:
    """The finished query records of a (possibly interrupted) run; a torn last line is ignored."""
    p = Path(out_dir) / QUERIES_FILE
    done: dict[int, dict] = {}
    if not p.is_file():
        return done
    for line in p.read_text().splitlines():
        try:
            rec = json.loads(line)
        except json.JSONDecodeError:
            continue  # the line a kill cut short
        done[int(rec["query"])] = rec
    return done


def _keep_matching_queries(out: Path, fingerprint: str) -> None:
    """Move query records of another database or config aside (``queries.stale.jsonl``)."""
    qfile, meta = out / QUERIES_FILE, out / QUERIES_META
    try:
        old = json.loads(meta.read_text()).get("fingerprint") if meta.is_file() else None
    except json.JSONDecodeError:
        old = None
    if qfile.is_file() and old != fingerprint:
        warnings.warn(
            f"{qfile}: computed on another database or config; moved to {QUERIES_FILE.replace('.jsonl', '.stale.jsonl')} "
            "and the queries start again",
            stacklevel=3,
        )
        qfile.replace(out / QUERIES_FILE.replace(".jsonl", ".stale.jsonl"))
    meta.write_text(json.dumps({"fingerprint": fingerprint}))


def _drop_torn_tail(path: Path) -> None:
    """Cut a half-written last line (a kill mid-write) so that appends start on a new line."""
    if not path.is_file():
        return
    data = path.read_bytes()
    if data and not data.endswith(b"\n"):
        path.write_bytes(data[: data.rfind(b"\n") + 1])


def loops_from_records(records: dict[int, dict], min_confidence: float) -> list[LoopClosure]:
    """Every verified candidate at or above ``min_confidence``, in query order."""
    out = []
    for q in sorted(records):
        for c in records[q]["candidates"]:
            if c["T"] is None or c["confidence"] < min_confidence:
                continue
            out.append(
                LoopClosure(
                    query=q,
                    match=c["match"],
                    T_match_query=np.asarray(c["T"], float).reshape(4, 4),
                    confidence=c["confidence"],
                    overlap=c["overlap"],
                    n_associations=c["n_associations"],
                    n_agreeing=c["n_agreeing"],
                    retrieval_rank=c["rank"],
                    retrieval_distance=c["retrieval_distance"],
                    valid=True,
                    info={"rms_offset": c.get("rms_offset"), "consistent_with": c.get("consistent_with")},
                )
            )
    return out


def prepare_drive(
    dataset: Dataset,
    odometry: str | None = None,
    deskew: bool = False,
    drift: Any = None,
) -> tuple[Dataset, NDArray | None]:
    """The drive as the loop pipeline sees it, and its odometry poses (or None).

    ``odometry``: ``drift`` | ``gt`` | ``kiss-icp`` | a KITTI pose file (see
    :func:`graffmatch.loops.posegraph.odometry_for`; ``drift`` with ``drift``, an
    ``OdometryDriftConfig``; ``kiss-icp`` de-skews the raw scans itself when ``deskew``). With
    ``deskew`` every raw scan is moved into its mid-sweep frame with that odometry's motion
    (:class:`graffmatch.datasets.Deskewed`: another name and cache tag, so its landmarks never
    mix with the raw scans'). One function for ``graffmatch loops`` and ``graffmatch
    benchmark-loops``, so both see the same scans.
    """
    if deskew and odometry is None:
        raise InvalidInputError("deskew needs an odometry (drift, gt, kiss-icp or a KITTI pose file)")
    odo = None
    if odometry is not None:
        from graffmatch.loops.posegraph import odometry_for

        odo = odometry_for(dataset, odometry, drift, deskew=deskew)
    if deskew:
        from graffmatch.datasets.deskewed import Deskewed

        dataset = Deskewed(dataset, odo)
    return dataset, odo


def build_database(
    dataset: Dataset,
    out_dir: Path,
    config: LoopDetectorConfig,
    executor: str = "local",
    workers: int | None = None,
    address: str | None = None,
    progress: Progress | None = None,
) -> tuple[LandmarkDatabase, dict]:
    """Extract (or load cached) landmarks of every scan and build the database."""
    n = len(dataset)
    lm_dir = out_dir / LANDMARK_DIR
    lm_dir.mkdir(parents=True, exist_ok=True)
    index_file = lm_dir / "index.json"
    try:
        index = json.loads(index_file.read_text()) if index_file.is_file() else {}
    except json.JSONDecodeError:
        index = {}
    keys = {i: _scan_key(dataset, i, config) for i in range(n)}
    todo = [i for i in range(n) if index.get(str(i)) != keys[i] or not (lm_dir / f"{i:06d}.npz").is_file()]
    cfg_json = config.model_dump_json()
    stats: dict[str, Any] = {
        "extracted": len(todo), "cached": n - len(todo), "extract_cpu_s": 0.0,
        "database_key": hashlib.sha256("\n".join(keys[i] for i in range(n)).encode()).hexdigest()[:20],
    }
    if todo:
        ex = make_executor("serial" if (workers == 1 and executor == "local") else executor, workers=workers, address=address)
        tasks = [(dataset, i, cfg_json, str(lm_dir / f"{i:06d}.npz")) for i in todo]
        done = 0
        try:
            for _, (i, dt) in ex.imap_unordered(_extract_task, tasks):
                index[str(i)] = keys[i]
                stats["extract_cpu_s"] += dt
                done += 1
                if progress:
                    progress("landmarks", done, len(todo))
                if done % 50 == 0:
                    index_file.write_text(json.dumps(index))
        finally:
            ex.close()
            index_file.write_text(json.dumps(index))
    det = LoopDetector(config)
    db = det.db
    times = np.asarray(getattr(dataset, "timestamps", np.arange(n, dtype=float)), float)
    if np.any(np.diff(times) < 0):
        raise InvalidInputError(f"{getattr(dataset, 'name', 'dataset')}: timestamps decrease")
    if getattr(dataset, "times_assumed", False) and config.retrieval.exclude_seconds > 0:
        warnings.warn(
            f"{getattr(dataset, 'name', 'dataset')}: no times.txt, so its scans are taken as {ASSUMED_SCAN_RATE_HZ:g} Hz "
            f"for the {config.retrieval.exclude_seconds:g} s exclusion window; add times.txt, or give the window in "
            "frames (--exclude-frames, with --exclude-seconds 0)",
            stacklevel=2,
        )
    for i in range(n):
        ls = load_landmarks(lm_dir / f"{i:06d}.npz")
        extra = {"scan": load_scan_cloud(lm_dir / f"{i:06d}.npz") if config.verification.scan_cloud_below > 0 else None}
        if config.retrieval.method == "scan-context":
            extra["scan_context"] = np.load(lm_dir / f"{i:06d}.sc.npy")
        db.add(ls, landmark_descriptor(ls, config.descriptor), float(times[i]), **extra)
    return db, stats


def _write_local_maps(db: LandmarkDatabase, out: Path, config: LoopDetectorConfig,
                      odometry: NDArray | None) -> tuple[frozenset[int], str]:
    """Build the local maps of the drive's landmark-poor scans (needs odometry), write them for the
    workers, and give those scans their local map's descriptor (the retriever reads the database's).
    Returns the scans with a local map and a key of the maps' contents (workers' caches)."""
    if odometry is None or config.verification.local_map_frames <= 0:
        return frozenset(), ""
    v = config.matcher.verification
    maps = attach_local_maps(db, odometry, config.verification, config.descriptor, v.voxel, v.max_points)
    d = out / LOCAL_MAP_DIR
    d.mkdir(parents=True, exist_ok=True)
    h = hashlib.sha256()
    for i, ls in sorted(maps.items()):
        data = landmarks_to_bytes(ls)
        write_bytes_atomic(d / f"{i:06d}.npz", data)
        h.update(i.to_bytes(8, "little") + data)
    return frozenset(maps), h.hexdigest()[:20]


def run_loops(
    dataset: Dataset,
    out_dir: str | Path,
    config: LoopDetectorConfig | None = None,
    executor: str = "local",
    workers: int | None = None,
    address: str | None = None,
    positions: NDArray | None = None,
    progress: Progress | None = None,
    chunk_size: int = 20,
    odometry: NDArray | None = None,
) -> dict:
    """Detect the loop closures of a whole drive; writes the files listed in the module doc.

    ``positions`` (n, 3): odometry estimates, needed by the radius retriever and written as
    g2o vertices. ``odometry`` (n, 4, 4): odometry poses (world <- scan, drift allowed), with
    which weak point-verified loops are accepted when a neighbouring query's loop agrees
    (:mod:`.consistency`); their positions serve as ``positions`` when those are not given.
    Returns the summary (also in ``summary.json``).
    """
    config = config or LoopDetectorConfig()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    (out / "config.yaml").write_text(yaml.safe_dump(config.model_dump(mode="json"), sort_keys=False))
    db, stats = build_database(dataset, out, config, executor, workers, address, progress)
    n = len(db)
    if odometry is not None:
        odometry = np.asarray(odometry, float)
        if odometry.shape != (n, 4, 4):
            raise InvalidInputError(f"odometry must be ({n}, 4, 4) poses, got {odometry.shape}")
        if positions is None:
            positions = odometry[:, :3, 3]
    if positions is not None:
        positions = np.asarray(positions, float)
        if positions.shape != (n, 3):
            raise InvalidInputError(f"positions must be ({n}, 3), got {positions.shape}")
        db.positions = list(positions)
    elif config.retrieval.method == "radius":
        raise InvalidInputError("the radius retriever needs positions (poses or odometry)")

    local_ids, local_key = _write_local_maps(db, out, config, odometry)

    # retrieval in the driver: fast, and it needs the whole database
    det = LoopDetector(config)
    det.db = db
    t0 = time.perf_counter()
    cands: dict[int, list[tuple[int, float]]] = {}
    for q in range(n):
        m = eligible_count(db.timestamps, q, config.retrieval)
        idx, dist = det.retriever.candidates(db, q, m)
        cands[q] = list(zip(idx.tolist(), dist.tolist(), strict=True))
    retrieve_s = time.perf_counter() - t0
    with open(out / "retrieval.csv", "w") as f:
        f.write("query,rank,match,distance\n")
        for q, cs in cands.items():
            for r, (j, d) in enumerate(cs):
                f.write(f"{q},{r},{j},{d:.6g}\n")

    # verification, resumable: records of the same database, config and positions are kept
    cfg_json = config.model_dump_json()
    fingerprint = hashlib.sha256(
        "\n".join([stats["database_key"], cfg_json,
                   "none" if positions is None else hashlib.sha256(positions.tobytes()).hexdigest()]).encode()
    ).hexdigest()[:20]
    _keep_matching_queries(out, fingerprint)
    done = read_queries(out)
    todo = [q for q in range(n) if q not in done and cands[q]]
    empty = [q for q in range(n) if q not in done and not cands[q]]
    qfile = out / QUERIES_FILE
    _drop_torn_tail(qfile)
    t1 = time.perf_counter()
    with open(qfile, "a") as f:
        for q in empty:
            rec = {"query": q, "candidates": [], "verify_s": 0.0}
            f.write(json.dumps(rec) + "\n")
            done[q] = rec
        chunks = [[(q, cands[q]) for q in todo[k : k + chunk_size]] for k in range(0, len(todo), chunk_size)]
        if chunks:
            name = "serial" if (workers == 1 and executor == "local") or len(chunks) == 1 else executor
            ex = make_executor(name, workers=workers, address=address)
            n_done = 0
            try:
                warm_points = has_point_pairs(db)
                place_scans = place_check_scans(dataset, config.verification)  # None: no place check
                tasks = [(str(out), stats["database_key"], cfg_json, c, warm_points,
                          None if odometry is None else _chunk_poses(odometry, c), (local_ids, local_key), place_scans)
                         for c in chunks]
                for _, recs in ex.imap_unordered(_verify_task, tasks):
                    for rec in recs:
                        f.write(json.dumps(rec) + "\n")
                        done[rec["query"]] = rec
                    f.flush()
                    os.fsync(f.fileno())
                    n_done += len(recs)
                    if progress:
                        progress("queries", n_done, len(todo))
            finally:
                ex.close()
    verify_wall = time.perf_counter() - t1
    final = apply_sequence_consistency(done, odometry, config.verification)
    loops = loops_from_records(final, config.verification.min_confidence)
    write_loops_csv(out / "loops.csv", loops)
    write_g2o(out / "loops.g2o", loop_edges(loops))  # vertices: posegraph.g2o (--optimize)
    n_verified = sum(c.get("verified", True) for r in done.values() for c in r["candidates"])
    n_retrieved = sum(len(r["candidates"]) for r in done.values())
    verify_cpu = sum(r["verify_s"] for r in done.values())
    summary = {
        "dataset": getattr(dataset, "name", "dataset"),
        "n_scans": n,
        "n_loops": len(loops),
        "n_queries_with_loop": len({lc.query for lc in loops}),
        "n_candidates_retrieved": n_retrieved,
        "n_candidates_verified": n_verified,
        "n_loops_sequence_consistent": sum(lc.info.get("consistent_with") is not None for lc in loops),
        "n_loops_refused_by_odometry": refused_by_odometry(done, final, config.verification.min_confidence),
        "n_scans_on_local_maps": len(local_ids),
        "quick_index_cpu_s": sum(r.get("index_s", 0.0) for r in done.values()),
        "worker_warmup_cpu_s": sum(r.get("warmup_cpu_s", 0.0) for r in done.values()),  # numba kernels, not in queries
        "retrieval": config.retrieval.method,
        "top_k": config.retrieval.top_k,
        "min_confidence": config.verification.min_confidence,
        "landmarks": stats,
        "retrieve_ms_per_query": 1e3 * retrieve_s / max(n, 1),
        "verify_ms_per_query": 1e3 * verify_cpu / max(len(done), 1),
        "verify_cpu_ms_per_query": 1e3 * sum(r.get("verify_cpu_s", 0.0) for r in done.values()) / max(len(done), 1),
        "verify_wall_s": verify_wall,
        "database_bytes_per_scan": db.bytes_per_scan(),
        "database_bytes_max_scan": int(db.stored_bytes().max()) if n else 0,
        "scans_with_scan_cloud": sum(x is not None for x in db.extra.get("scan", [])),
        "total_wall_s": time.perf_counter() - t_start,
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    return summary


def load_run(out_dir: str | Path) -> tuple[list[LoopClosure], dict]:
    """(loops, summary) of a finished run folder."""
    out = Path(out_dir)
    if not (out / "summary.json").is_file():
        raise MalformedFileError(f"{out}: no summary.json (not a finished 'graffmatch loops' run)")
    from graffmatch.loops.io import read_loops_csv

    return read_loops_csv(out / "loops.csv"), json.loads((out / "summary.json").read_text())


def optimize_run(
    out_dir: str | Path,
    odometry: NDArray,
    timestamps: NDArray,
    reference: NDArray | None = None,
    config: Any = None,
) -> dict:
    """Pose-graph optimisation of a finished run's loops with the given odometry.

    Writes odometry_kitti.txt, optimized_kitti.txt, optimized_tum.txt, posegraph.g2o (vertices +
    odometry and loop edges), trajectory.png, and ATE/RPE before and after (with ``reference``)
    into summary.json under "posegraph".
    """
    from graffmatch.geometry.transforms import invert
    from graffmatch.loops.posegraph import optimize_pose_graph, plot_trajectories, trajectory_errors

    out = Path(out_dir)
    loops, summary = load_run(out)
    P = np.asarray(odometry, float)
    edges = loop_edges(loops)
    opt, info = optimize_pose_graph(P, edges, config)
    write_kitti(out / "odometry_kitti.txt", P)
    write_kitti(out / "optimized_kitti.txt", opt)
    write_tum(out / "optimized_tum.txt", opt, timestamps)
    odo_edges = [(i, i + 1, invert(P[i]) @ P[i + 1], np.eye(6)) for i in range(len(P) - 1)]
    write_g2o(out / "posegraph.g2o", odo_edges + edges, opt)
    if reference is not None:
        info["before"] = trajectory_errors(P, reference)
        info["after"] = trajectory_errors(opt, reference)
    plot_trajectories(out / "trajectory.png", reference, P, opt, loops)
    summary["posegraph"] = info
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    return info
