"""Point-level and landmark-level evidence for a hypothesis ``T_target_source``.

Default evidence is the landmarks' own support points, which the extractor stores (a few
thousand per scan): how much of the non-ground support of each scan lands within
``inlier_m`` of the other's under the hypothesis, in both directions. With the raw scans at
hand (``ScanMatcher``), :func:`scan_cloud` gives the same score on the scans' non-ground voxel
clouds instead. KD-trees (scipy) and no
Python loop over points. Bare landmark sets without points fall back to landmark-level
evidence: the share of landmarks that land on a counterpart of the same type.

Speed: nearest-neighbour queries run on a cell hash of each cloud (:mod:`.cell_hash`), which
returns exactly what ``cKDTree.query(..., distance_upper_bound=r)`` returns at a fraction of
its cost on clouds of a few thousand points; a cloud whose coordinates do not fit the cell keys
falls back to the KD-tree. What depends on one scan only (downsampled support,
cell hashes, dilated occupancy) is computed once per :class:`LandmarkSet` and kept in
:data:`evidence_cache`, so one scan verified against k candidates pays for it once.

The module runs past 600 lines on purpose: each compiled pass (downsampling, occupancy,
alignment, landmark pairs) sits next to the numpy reference that specifies it and that the
tests compare it with, bit for bit; split apart, the pair would drift.
"""

from __future__ import annotations

import threading
import weakref
from collections import OrderedDict
from dataclasses import dataclass, field

import numba as nb
import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from graffmatch.geometry.landmarks import LandmarkSet, LandmarkType
from graffmatch.geometry.set_cache import derived_cache
from graffmatch.verification.cell_hash import (
    CellHash,
    _slot,
    occupancy_bitmap,
    occupancy_lookup,
    occupied_hits,
    voxel_keys,
)
from graffmatch.verification.free_space import RangeImage
from graffmatch.verification.view import view_mask_of


@dataclass
class SupportCloud:
    """Voxel-downsampled non-ground evidence points of one scan, with what queries them: cell
    hashes per radius (built on first use), a KD-tree (only for clouds too far out for the
    hashes) and a dilated voxel occupancy that scores many hypotheses in one lookup."""

    points: NDArray[np.float64]
    #: support points *with* the ground, downsampled: the returns whose beams show free space
    free_points: NDArray[np.float64] | None = None
    #: the sensor's pose in this frame (None: unknown, no free-space evidence)
    sensor_pose: NDArray[np.float64] | None = None
    #: the whole scan's nearest return per cell, in the sensor's frame (``LandmarkSet.scan_ranges``)
    scan_ranges: NDArray[np.float32] | None = None
    occupancy: NDArray[np.int64] | None = None
    occupancy_voxel: float = 0.0
    occupancy_origin: NDArray[np.float64] | None = None
    _tree: cKDTree | None = field(default=None, repr=False)
    _hashes: dict = field(default_factory=dict, repr=False)
    _occ_table: tuple | None = field(default=None, repr=False)
    _occ_table_voxel: float = field(default=0.0, repr=False)
    _range_images: dict = field(default_factory=dict, repr=False)
    _samples: dict = field(default_factory=dict, repr=False)
    _view: tuple | None = field(default=None, repr=False)

    def view_mask(self) -> NDArray[np.bool_] | None:
        """Which azimuth cells of the whole-scan range image hold a return (``view.azimuth_mask``,
        built once; None without ``scan_ranges`` or sensor pose: the view is unknown)."""
        if self._view is None:
            self._view = (view_mask_of(self.sensor_pose, self.scan_ranges),)
        return self._view[0]

    def __len__(self) -> int:
        return len(self.points)

    def sample(self, n: int) -> NDArray[np.float64]:
        """``min(n, len)`` points evenly spread over the cloud (C-contiguous; built once per n):
        what the occupancy pass moves."""
        P = self._samples.get(n)
        if P is None:
            k = min(n, len(self.points))
            idx = np.linspace(0, len(self.points) - 1, k).astype(np.int64)
            P = self._samples[n] = np.ascontiguousarray(self.points[idx], dtype=np.float64)
        return P

    def range_image(self, az_deg: float, el_deg: float, neighbours: int,
                    scan_neighbours: int = 0, use_scan_ranges: bool = True) -> RangeImage | None:
        """The free-space image of this scan (built on first use): from the whole scan's returns
        when the set carries them (min-filtered over ``scan_neighbours`` cells), else from the
        support points (over ``neighbours``); None without returns or sensor pose."""
        if self.sensor_pose is None:
            return None
        if self.scan_ranges is not None and use_scan_ranges:
            key = ("scan", float(az_deg), float(el_deg), int(scan_neighbours))
            img = self._range_images.get(key)
            if img is None:
                img = RangeImage.from_cell_minima(self.scan_ranges, az_deg, el_deg, scan_neighbours)
                if img is not None:
                    self._range_images[key] = img
            if img is not None:
                return img
        if self.free_points is None:
            return None
        key = (float(az_deg), float(el_deg), int(neighbours))
        img = self._range_images.get(key)
        if img is None:
            R, t = self.sensor_pose[:3, :3], self.sensor_pose[:3, 3]
            img = self._range_images[key] = RangeImage.from_points((self.free_points - t) @ R, az_deg, el_deg, neighbours)
        return img

    @property
    def tree(self) -> cKDTree:
        """KD-tree of the points (built on first use)."""
        if self._tree is None:
            self._tree = cKDTree(self.points)
        return self._tree

    def neighbours(self, q: NDArray[np.float64], radius: float, nearest: bool = True) -> NDArray[np.int64]:
        """Index of the nearest point within ``radius`` (strictly) of each row of ``q``, -1 if
        none; ``nearest=False``: of any point within the radius."""
        h = self.cell_hash(radius)
        if h.ok:
            return h.query(q, nearest)
        _, idx = self.tree.query(q, k=1, distance_upper_bound=radius)
        return np.where(idx < len(self.points), idx, -1)

    def cell_hash(self, radius: float) -> CellHash:
        """The points' cell hash for ``radius`` (built on first use; ``.ok`` False when the
        coordinates do not fit it)."""
        h = self._hashes.get(radius)
        if h is None:
            h = self._hashes[radius] = CellHash(self.points, radius)
        return h

    def occupied(self, voxel: float) -> NDArray[np.int64]:
        """Sorted keys of the voxels that hold a point or touch one by a face (built once),
        counted from ``occupancy_origin`` (the cloud's lowest voxel: any coordinates fit)."""
        if self.occupancy is None or self.occupancy_voxel != voxel:
            off = np.array([[0, 0, 0], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]])
            base = np.floor(self.points / voxel)
            self.occupancy_origin = base.min(axis=0) if len(base) else np.zeros(3)
            pts = ((base[:, None, :] + off[None]) + 0.5) * voxel
            keys, inside = voxel_keys(pts.reshape(-1, 3), voxel, self.occupancy_origin)
            self.occupancy = np.unique(keys[inside])
            self.occupancy_voxel = voxel
        return self.occupancy

    def occupied_table(self, voxel: float) -> tuple:
        """The occupied voxels for :func:`occupied_hits` (sets ``occupancy_origin``): a bitmap
        over their box when it has at most ``OCCUPANCY_BITS`` voxels (a few cycles a lookup;
        built straight from the points, :func:`occupancy_bitmap`), else a hash table of the
        sorted keys of :meth:`occupied`. Built once per voxel size."""
        if self._occ_table is None or self._occ_table_voxel != voxel:
            built = occupancy_bitmap(self.points, voxel)
            if built is None:
                table = occupancy_lookup(self.occupied(voxel))
            else:
                self.occupancy_origin, table = built
            self._occ_table, self._occ_table_voxel = table, voxel
        return self._occ_table


def occupancy_overlap(
    source: SupportCloud, target: SupportCloud, Ts: NDArray[np.float64], voxel: float, n_points: int = 256,
) -> NDArray[np.float64]:
    """(H, 2) approximate shares explained in both directions for H transforms at once: a point
    counts when it falls in a voxel next to an occupied one (distance up to ~2 voxels)."""
    out = np.zeros((len(Ts), 2))
    Ts = np.ascontiguousarray(Ts, dtype=np.float64)
    for k, (a, b) in enumerate(((source, target), (target, source))):
        P = a.sample(n_points)
        n = len(P)
        table = b.occupied_table(voxel)  # target -> source (k = 1): the inverse transforms
        out[:, k] = occupied_hits(P, Ts, k == 1, voxel, b.occupancy_origin, *table) / n
    return out


def _occupancy_overlap_reference(
    source: SupportCloud, target: SupportCloud, Ts: NDArray[np.float64], voxel: float, n_points: int = 256,
) -> NDArray[np.float64]:
    """numpy specification of :func:`occupancy_overlap` (sorted keys and a binary search)."""
    out = np.zeros((len(Ts), 2))
    for k, (a, b, T) in enumerate(((source, target, Ts), (target, source, None))):
        P = a.points[np.linspace(0, len(a) - 1, min(n_points, len(a))).astype(np.int64)]
        if T is None:
            R = np.swapaxes(Ts[:, :3, :3], 1, 2)
            t = -np.einsum("hij,hj->hi", R, Ts[:, :3, 3])
        else:
            R, t = T[:, :3, :3], T[:, :3, 3]
        q = P @ np.swapaxes(R, 1, 2) + t[:, None, :]
        occ = b.occupied(voxel)
        keys, inside = voxel_keys(q, voxel, b.occupancy_origin)
        pos = np.searchsorted(occ, keys)
        hit = (occ[np.minimum(pos, len(occ) - 1)] == keys) & inside
        out[:, k] = hit.mean(axis=1)
    return out


def voxel_sample_rows(points: NDArray, voxel: float, max_points: int) -> NDArray[np.int64]:
    """Rows of :func:`voxel_downsample`'s sample of ``points``, in row order. Why rows: a caller can then transform
    only the sampled points (``Deskewed.points_subset``)."""
    P = np.asarray(points)
    P = np.ascontiguousarray(P[:, :3] if P.ndim == 2 else P.reshape(-1, 3), dtype=np.float64)
    ok, rows, flat = _voxel_keys(P, float(voxel))
    if ok:
        # first_of_each called from Python, not from inside the kernel: nested in the kernel it took ~10 ms for a
        # 120k-point scan, alone 0.8 ms (same keys, same rows; session 24)
        rows = rows[first_of_each(flat)]
    else:  # the compiled pass cannot key these coordinates: its numpy specification
        rows = np.flatnonzero(np.all(np.isfinite(P), axis=1))
        if len(rows):
            keys = np.floor(P[rows] / voxel).astype(np.int64)
            keys -= keys.min(axis=0)
            dims = keys.max(axis=0) + 1
            if np.prod(dims.astype(float)) < 2**62:
                rows = rows[first_of_each((keys[:, 0] * dims[1] + keys[:, 1]) * dims[2] + keys[:, 2])]
            else:  # absurd extents: fall back to row-unique
                rows = rows[np.sort(np.unique(keys, axis=0, return_index=True)[1])]
    if len(rows) > max_points:
        rows = rows[np.linspace(0, len(rows) - 1, max_points).astype(np.int64)]
    return rows


def voxel_downsample(points: NDArray, voxel: float, max_points: int) -> NDArray[np.float64]:
    """One point per occupied voxel (the first, deterministic), then an even stride to the cap."""
    P = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    return P[voxel_sample_rows(P, voxel, max_points)]


@nb.njit(cache=True)
def _voxel_keys(P: NDArray[np.float64], voxel: float) -> tuple[bool, NDArray[np.int64], NDArray[np.int64]]:
    """(True, the rows of the finite points, their voxels' keys packed into one non-negative int64 each), or
    (False, _, _) when a voxel index or the voxel box is too large for int64 keys (then :func:`voxel_sample_rows`'
    numpy path answers). The first row of each key is what :func:`voxel_downsample` keeps."""
    n = P.shape[0]
    keys = np.empty((n, 3), np.int64)
    rows = np.empty(n, np.int64)
    m = 0
    lo = np.zeros(3, np.int64)
    hi = np.zeros(3, np.int64)
    for i in range(n):
        if not (np.isfinite(P[i, 0]) and np.isfinite(P[i, 1]) and np.isfinite(P[i, 2])):
            continue
        for j in range(3):
            f = np.floor(P[i, j] / voxel)
            if not abs(f) < 2.0**62:
                return False, rows[:0], rows[:0]
            k = int(f)
            keys[m, j] = k
            if m == 0 or k < lo[j]:
                lo[j] = k
            if m == 0 or k > hi[j]:
                hi[j] = k
        rows[m] = i
        m += 1
    if m == 0:
        return True, rows[:0], rows[:0]
    d0, d1, d2 = hi[0] - lo[0] + 1, hi[1] - lo[1] + 1, hi[2] - lo[2] + 1
    if not float(d0) * float(d1) * float(d2) < 2.0**62:
        return False, rows[:0], rows[:0]
    flat = np.empty(m, np.int64)
    for a in range(m):
        flat[a] = ((keys[a, 0] - lo[0]) * d1 + (keys[a, 1] - lo[1])) * d2 + (keys[a, 2] - lo[2])
    return True, rows[:m], flat


@nb.njit(cache=True)
def first_of_each(keys: NDArray[np.int64]) -> NDArray[np.bool_]:
    """Whether each entry of ``keys`` (non-negative) is the first with its value: what
    ``np.sort(np.unique(keys, return_index=True)[1])`` selects, in one pass over an
    open-addressing set instead of a sort."""
    n = keys.shape[0]
    cap = 8
    while cap < 4 * n:
        cap *= 2
    table = np.full(cap, -1, np.int64)
    mask = cap - 1
    out = np.zeros(n, np.bool_)
    for i in range(n):
        k = keys[i]
        s = _slot(k, mask)
        while True:
            t = table[s]
            if t == k:
                break
            if t == -1:
                table[s] = k
                out[i] = True
                break
            s = (s + 1) & mask
    return out


def non_ground_support(landmarks: LandmarkSet) -> NDArray[np.float32] | None:
    """Support points of every landmark except the ground plane, or None without points."""
    if landmarks.points is None or landmarks.point_offsets is None:
        return None
    g = landmarks.attributes.get("is_ground")
    if g is None:
        return landmarks.points
    keep = np.asarray(g, dtype=float).reshape(-1) < 0.5
    off = landmarks.point_offsets
    counts = np.diff(off)
    mask = np.repeat(keep, counts)
    return landmarks.points[mask]


def evidence_points(landmarks: LandmarkSet, voxel: float = 0.3, max_points: int = 1500) -> NDArray[np.float64] | None:
    """The points a set is verified on: its non-ground support voxelised (at most ``max_points``),
    or None when it carries fewer than 10 (too few to score a hypothesis). The loop database
    stores exactly these for landmark-poor scans."""
    pts = non_ground_support(landmarks)
    if pts is None:
        return None
    P = voxel_downsample(pts, voxel, max_points)
    return P if len(P) >= 10 else None


def support_cloud(landmarks: LandmarkSet, voxel: float = 0.3, max_points: int = 1500) -> SupportCloud | None:
    """Evidence points of one landmark set (None when it carries too few support points)."""
    P = evidence_points(landmarks, voxel, max_points)
    if P is None:
        return None
    pose = landmarks.sensor_pose
    free = None if pose is None else voxel_downsample(landmarks.points, voxel, 2 * max_points)  # type: ignore[arg-type]
    return SupportCloud(P, free_points=free, sensor_pose=None if pose is None else pose.copy(),
                        scan_ranges=None if pose is None else landmarks.scan_ranges)


class EvidenceCache:
    """Support clouds of recently matched landmark sets, so that a scan verified against k
    candidates (a loop detector's query, a map's keyframe) is downsampled and hashed once.

    Keyed by the *identity* of the set's support arrays (``points``, ``point_offsets``, the
    ``is_ground`` attribute and ``scan_ranges``), held by weak references: an entry lives no longer than those
    arrays, a new set (``ls[keep]``, a loaded file) never sees another's cloud, and the cache
    keeps no scan alive. A hit is also checked against copies of those arrays (a few tens of
    microseconds), so arrays changed in place are never served a stale cloud. At most
    ``max_entries`` clouds (least recently used dropped).
    """

    def __init__(self, max_entries: int = 64) -> None:
        self.max_entries = max_entries
        self._lock = threading.Lock()
        self._entries: OrderedDict[tuple, tuple] = OrderedDict()
        self.hits = 0
        self.misses = 0

    def support_cloud(self, landmarks: LandmarkSet, voxel: float = 0.3, max_points: int = 1500) -> SupportCloud | None:
        """:func:`support_cloud` of ``landmarks``, computed once per set of support arrays."""
        pts, off = landmarks.points, landmarks.point_offsets
        if pts is None or off is None or self.max_entries <= 0:
            return support_cloud(landmarks, voxel, max_points)
        ground = landmarks.attributes.get("is_ground")
        arrays = (pts, off, ground, landmarks.scan_ranges)
        if not all(a is None or isinstance(a, np.ndarray) for a in arrays):
            return support_cloud(landmarks, voxel, max_points)
        pose = None if landmarks.sensor_pose is None else landmarks.sensor_pose.tobytes()
        key = (id(pts), id(off), id(ground), id(landmarks.scan_ranges), float(voxel), int(max_points), pose)
        with self._lock:
            e = self._entries.get(key)
            if e is not None and all((r is None and a is None) or (r is not None and r() is a)
                                     for r, a in zip(e[0], arrays, strict=True)) and all(
                    (c is None and a is None) or (c is not None and np.array_equal(c, a))
                    for c, a in zip(e[2], arrays, strict=True)):
                if key in self._entries:  # (a GC callback may have dropped it meanwhile)
                    self._entries.move_to_end(key)
                self.hits += 1
                return e[1]
        cloud = support_cloud(landmarks, voxel, max_points)
        refs = tuple(None if a is None else weakref.ref(a, self._dropper(key)) for a in arrays)
        with self._lock:
            self.misses += 1
            self._entries.pop(key, None)
            self._entries[key] = (refs, cloud, tuple(None if a is None else a.copy() for a in arrays))
            while len(self._entries) > self.max_entries:
                self._entries.popitem(last=False)
        return cloud

    def _dropper(self, key: tuple):
        selfref = weakref.ref(self)

        def drop(_ref: weakref.ref) -> None:  # an array of the entry died: its id may be reused
            cache = selfref()
            if cache is not None:  # no lock: this may run inside a locked block (GC); pop is atomic
                cache._entries.pop(key, None)

        return drop

    def clear(self) -> None:
        with self._lock:
            self._entries.clear()

    def __len__(self) -> int:
        return len(self._entries)


evidence_cache = EvidenceCache()
"""The process-wide cache :func:`graffmatch.verification.verify.evidence_for` uses."""


def prepared_support(landmarks: LandmarkSet, voxel: float = 0.3, max_points: int = 1500) -> SupportCloud | None:
    """The evidence cloud of one landmark set from :data:`evidence_cache` (built on first use):
    what a loop detector calls once per scan before verifying it against its candidates."""
    return evidence_cache.support_cloud(landmarks, voxel, max_points)


def cloud_from_points(points: NDArray, voxel: float, max_points: int) -> SupportCloud | None:
    """Evidence points from a raw scan (already without its ground)."""
    P = voxel_downsample(points, voxel, max_points)
    if len(P) < 10:
        return None
    return SupportCloud(P)


def scan_cloud(points: NDArray, landmarks: LandmarkSet, voxel: float = 0.6,
               max_points: int = 2000) -> SupportCloud | None:
    """Evidence points from a scan's non-ground points (e.g. the extractor's voxel cloud,
    ``LandmarkExtractor.last_cloud.points``), re-voxelised at ``voxel`` and capped by an even
    stride, with the free-space inputs of the scan's ``landmarks`` (sensor pose, whole-scan
    ranges, support points with the ground): every surface of the scan can explain a hypothesis,
    not only the landmarks' support (where true poses explain as little as 0.06-0.18 of it,
    sim-downtown). None when fewer than 10 points remain."""
    P = voxel_downsample(points, voxel, max_points)
    if len(P) < 10:
        return None
    pose = landmarks.sensor_pose
    free = None
    if pose is not None and landmarks.points is not None:
        free = voxel_downsample(landmarks.points, voxel, 2 * max_points)
    return SupportCloud(P, free_points=free, sensor_pose=None if pose is None else pose.copy(),
                        scan_ranges=None if pose is None else landmarks.scan_ranges)


def score_on_points(hyps: list, source: SupportCloud, target: SupportCloud, inlier_m: float, exact: bool) -> None:
    """Fill each hypothesis' ``score_parts`` and ``score`` (the mean share of both clouds
    explained): exact neighbour counts (:func:`point_overlaps`) or the voxel first pass
    (:func:`occupancy_overlap`), all hypotheses in one call."""
    if not hyps:
        return
    Ts = np.stack([h.T_target_source for h in hyps])
    parts = (point_overlaps if exact else occupancy_overlap)(source, target, Ts, inlier_m)
    for h, (p0, p1) in zip(hyps, parts.tolist(), strict=True):
        h.score_parts = (p0, p1)
        h.score = 0.5 * (p0 + p1)


def point_overlaps(
    source: SupportCloud, target: SupportCloud, Ts: NDArray[np.float64], inlier_m: float
) -> NDArray[np.float64]:
    """(H, 2): :func:`point_overlap` of H stacked transforms, in two compiled calls (one per
    direction) when both clouds fit their cell hashes."""
    Ts = np.ascontiguousarray(Ts, dtype=np.float64).reshape(-1, 4, 4)
    h_t, h_s = target.cell_hash(inlier_m), source.cell_hash(inlier_m)
    if not (h_t.ok and h_s.ok):
        return np.array([_point_overlap_reference(source, target, T, inlier_m) for T in Ts]).reshape(-1, 2)
    out = np.empty((len(Ts), 2))
    out[:, 0] = h_t.hits(source.points, Ts) / len(source)
    out[:, 1] = h_s.hits(target.points, Ts, inverse=True) / len(target)
    return out


def point_overlap(
    source: SupportCloud, target: SupportCloud, T_target_source: NDArray[np.float64], inlier_m: float
) -> tuple[float, float]:
    """(source share explained by target, target share explained by source) under T (4x4)."""
    parts = point_overlaps(source, target, T_target_source, inlier_m)[0]
    return float(parts[0]), float(parts[1])


def reach_shares(source_points: NDArray, target_points: NDArray, Ts: NDArray, radius: float) -> NDArray[np.float64]:
    """(H,) share of the source points that each of the (H, 4, 4) ``Ts`` puts strictly within ``radius`` of a target
    point: ICP's fitness, counted the same way for any transform (a start and an ICP result compare like with like),
    in one compiled pass over a cell hash of the target (a KD-tree when the coordinates do not fit it)."""
    S = np.asarray(source_points, dtype=np.float64).reshape(-1, 3)
    G = np.asarray(target_points, dtype=np.float64).reshape(-1, 3)
    S = np.ascontiguousarray(S[np.all(np.isfinite(S), axis=1)])
    G = np.ascontiguousarray(G[np.all(np.isfinite(G), axis=1)])
    Ts = np.ascontiguousarray(Ts, dtype=np.float64).reshape(-1, 4, 4)
    if len(S) == 0 or len(G) == 0:
        return np.zeros(len(Ts))
    h = CellHash(G, float(radius))
    if h.ok:
        return h.hits(S, Ts) / len(S)
    tree = cKDTree(G)
    return np.array([np.mean(tree.query(S @ T[:3, :3].T + T[:3, 3], k=1)[0] < radius) for T in Ts])


def _point_overlap_reference(
    source: SupportCloud, target: SupportCloud, T_target_source: NDArray[np.float64], inlier_m: float
) -> tuple[float, float]:
    """numpy :func:`point_overlap` (moved points, then ``neighbours``): the path for clouds too
    far out for the cell hashes, and the specification of the compiled counts."""
    R, t = T_target_source[:3, :3], T_target_source[:3, 3]
    q = source.points @ R.T + t
    i_st = target.neighbours(q, inlier_m, nearest=False)
    p = (target.points - t) @ R  # R^T (p - t)
    i_ts = source.neighbours(p, inlier_m, nearest=False)
    return float(np.mean(i_st >= 0)), float(np.mean(i_ts >= 0))


def align_on_evidence(
    source: SupportCloud, target: SupportCloud, T_target_source: NDArray[np.float64],
    distances: tuple[float, ...] = (1.0, 0.6, 0.4, 0.3, 0.3),
) -> NDArray[np.float64]:
    """A few point-to-point alignment steps of the source evidence onto the target's, from a
    hypothesis (nearest neighbours within a shrinking distance, then the closed-form rigid fit).

    Landmark registration is only as good as the landmarks' fits; aligning the evidence points
    turns near misses (rotation right, translation off by a metre) into accurate transforms
    before they are scored. Deterministic (no threads).

    Each step is one compiled pass over the target's cell hash (:meth:`CellHash.align_step`:
    pairs, centroids, cross-covariance and the SVD fit without numpy overheads; verification
    runs about 45 steps per pair). It computes what :func:`_align_on_evidence_reference` (the
    numpy fit on KD-tree neighbours) computes, up to rounding in the sums; clouds too far out for
    the hashes use that reference."""
    T = np.array(T_target_source, dtype=np.float64)
    P = np.ascontiguousarray(source.points, dtype=np.float64)
    for d_max in distances:
        h = target.cell_hash(d_max)
        if not h.ok:
            return _align_on_evidence_reference(source, target, T_target_source, distances)
        if h.align_step(P, T) < 10:
            break
    return T


def _align_on_evidence_reference(
    source: SupportCloud, target: SupportCloud, T_target_source: NDArray[np.float64],
    distances: tuple[float, ...] = (1.0, 0.6, 0.4, 0.3, 0.3),
) -> NDArray[np.float64]:
    """numpy specification of :func:`align_on_evidence` (``target.neighbours``, mean, the
    ``(a - ca).T @ (b - cb)`` correlation, LAPACK SVD, ``V diag(1, 1, det) U^T``)."""
    T = np.array(T_target_source, dtype=np.float64)
    P = source.points
    for d_max in distances:
        q = P @ T[:3, :3].T + T[:3, 3]
        idx = target.neighbours(q, d_max)
        m = idx >= 0
        if int(np.count_nonzero(m)) < 10:
            break
        a, b = P[m], target.points[idx[m]]
        ca, cb = a.mean(axis=0), b.mean(axis=0)
        U, _, Vt = np.linalg.svd((a - ca).T @ (b - cb))
        D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0])
        R = Vt.T @ D @ U.T
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, cb - R @ ca
    return T


def landmark_overlap(
    source: LandmarkSet, target: LandmarkSet, T_target_source: NDArray[np.float64],
    max_deg: float = 5.0, max_m: float = 0.4, counts: list | None = None,
) -> NDArray[np.float64]:
    """Graded share of landmarks (ground plane excluded) with a same-type counterpart, both ways
    (each landmark counts 1 for an exact counterpart, falling linearly to 0 at the tolerances).
    ``counts`` (a list) receives the number of landmarks explained (the smaller direction).

    ``T_target_source`` is one (4, 4) transform -> (2,), or H stacked (H, 4, 4) -> (H, 2).
    Lines count when directions agree within ``max_deg`` and the axes pass within ``max_m``;
    planes when normals agree, the planes are within ``max_m`` and the anchors are closer than
    the supports' half sizes plus 2 m (a wall does not explain a wall 50 m along it).

    One compiled pass over (hypothesis, source, target) triples; the rotated directions and
    anchors and the final means are numpy's, so results equal :func:`_landmark_overlap_reference`
    up to the last bits of the per-pair angles and offsets (tested to 1e-12).
    """
    Ts = np.asarray(T_target_source, dtype=float)
    single = Ts.ndim == 2
    Ts = Ts[None] if single else Ts
    src, tgt = _ground_free(source), _ground_free(target)  # per set, once (set_cache)
    if src.n == 0 or tgt.n == 0:
        return _no_overlap(len(Ts), single, counts)
    t = Ts[:, :3, 3]
    Rt = np.swapaxes(Ts[:, :3, :3], 1, 2)
    ds = np.ascontiguousarray(src.directions @ Rt)  # (H, ns, 3)
    bs = np.ascontiguousarray(src.anchors @ Rt + t[:, None, :])
    H, ns, nt = len(Ts), src.n, tgt.n
    ws = np.zeros((H, ns))
    wt = np.zeros((H, nt))
    oks = np.zeros((H, ns), np.bool_)
    okt = np.zeros((H, nt), np.bool_)
    _landmark_pairs(ds, bs, tgt.directions, tgt.anchors, src.types, tgt.types, src.reach, tgt.reach,
                    float(max_deg), float(max_m), ws, wt, oks, okt)
    out = np.stack([ws.mean(axis=1), wt.mean(axis=1)], axis=1)
    if counts is not None:
        counts.append(np.minimum(oks.sum(axis=1), okt.sum(axis=1)))
    return out[0] if single else out


@nb.njit(cache=True)
def _landmark_pairs(ds, bs, dt, bt, ts, tt, reach_s, reach_t, max_deg, max_m, ws, wt, oks, okt):
    """Per hypothesis, each landmark's best graded counterpart weight (both ways) and whether it
    has any counterpart: the pair loop of :func:`_landmark_overlap_reference`."""
    H, ns, nt = ds.shape[0], ds.shape[1], dt.shape[0]
    for h in range(H):
        for s in range(ns):
            for u in range(nt):
                if ts[s] != tt[u]:
                    continue
                c = abs(ds[h, s, 0] * dt[u, 0] + ds[h, s, 1] * dt[u, 1] + ds[h, s, 2] * dt[u, 2])
                d0 = bt[u, 0] - bs[h, s, 0]
                d1 = bt[u, 1] - bs[h, s, 1]
                d2 = bt[u, 2] - bs[h, s, 2]
                along = d0 * dt[u, 0] + d1 * dt[u, 1] + d2 * dt[u, 2]
                dist = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
                if tt[u] == 2:  # plane
                    off = abs(along)
                elif tt[u] == 1:  # line
                    off = np.sqrt(max(dist * dist - along * along, 0.0))
                else:
                    off = dist
                if not off <= max_m:  # (NaN too)
                    continue
                if tt[u] >= 1 and not (dist <= reach_s[s] + reach_t[u] + 2.0):
                    continue
                w = 1.0 - off / max_m
                if ts[s] > 0:
                    ang = np.degrees(np.arccos(min(max(c, 0.0), 1.0)))
                    if not ang <= max_deg:
                        continue
                    w = (1.0 - ang / max_deg) * w
                oks[h, s] = True
                okt[h, u] = True
                if w > ws[h, s]:
                    ws[h, s] = w
                if w > wt[h, u]:
                    wt[h, u] = w


def _landmark_overlap_reference(
    source: LandmarkSet, target: LandmarkSet, T_target_source: NDArray[np.float64],
    max_deg: float = 5.0, max_m: float = 0.4, counts: list | None = None,
) -> NDArray[np.float64]:
    """numpy specification of :func:`landmark_overlap` (dense (H, ns, nt, 3) arrays).

    Graded share of landmarks (ground plane excluded) with a same-type counterpart, both ways
    (each landmark counts 1 for an exact counterpart, falling linearly to 0 at the tolerances).
    ``counts`` (a list) receives the number of landmarks explained (the smaller direction).

    ``T_target_source`` is one (4, 4) transform -> (2,), or H stacked (H, 4, 4) -> (H, 2).
    Lines count when directions agree within ``max_deg`` and the axes pass within ``max_m``;
    planes when normals agree, the planes are within ``max_m`` and the anchors are closer than
    the supports' half sizes plus 2 m (a wall does not explain a wall 50 m along it).
    """
    Ts, single, src, tgt = _overlap_inputs(source, target, T_target_source)
    if len(src) == 0 or len(tgt) == 0:
        return _no_overlap(len(Ts), single, counts)
    t = Ts[:, :3, 3]
    Rt = np.swapaxes(Ts[:, :3, :3], 1, 2)
    ds = src.directions @ Rt  # (H, ns, 3)
    bs = src.anchors @ Rt + t[:, None, :]
    dt, bt = tgt.directions, tgt.anchors
    same = (src.types[:, None] == tgt.types[None, :])[None]
    cosang = np.abs(np.einsum("hsi,ti->hst", ds, dt))
    diff = bt[None, None, :, :] - bs[:, :, None, :]  # (H, ns, nt, 3)
    along_t = np.einsum("hsti,ti->hst", diff, dt)
    is_plane = (tgt.types == LandmarkType.PLANE)[None, None, :]
    is_line = (tgt.types == LandmarkType.LINE)[None, None, :]
    dist = np.linalg.norm(diff, axis=3)
    dist_line = np.sqrt(np.maximum(dist**2 - along_t**2, 0.0))
    off = np.where(is_plane, np.abs(along_t), np.where(is_line, dist_line, dist))
    reach = (_reach(src)[:, None] + _reach(tgt)[None, :] + 2.0)[None]
    near = np.where(is_plane | is_line, dist <= reach, True)
    directional = (src.types[:, None] > 0)[None]
    ang = np.degrees(np.arccos(np.clip(cosang, 0.0, 1.0)))
    ok = same & np.where(directional, ang <= max_deg, True) & (off <= max_m) & near
    # graded: an exact counterpart counts 1, one at the tolerance 0 (tent kernels)
    w = np.where(ok, np.where(directional, 1.0 - ang / max_deg, 1.0) * (1.0 - off / max_m), 0.0)
    out = np.stack([w.max(axis=2).mean(axis=1), w.max(axis=1).mean(axis=1)], axis=1)
    if counts is not None:
        counts.append(np.minimum(ok.any(axis=2).sum(axis=1), ok.any(axis=1).sum(axis=1)))
    return out[0] if single else out



def _overlap_inputs(source: LandmarkSet, target: LandmarkSet, T_target_source: NDArray
                    ) -> tuple[NDArray[np.float64], bool, LandmarkSet, LandmarkSet]:
    """Stacked (H, 4, 4) transforms, whether one was given, and both sets without their ground."""
    Ts = np.asarray(T_target_source, dtype=float)
    single = Ts.ndim == 2
    return (Ts[None] if single else Ts), single, _without_ground(source), _without_ground(target)


def _no_overlap(n: int, single: bool, counts: list | None) -> NDArray[np.float64]:
    """Zero evidence for ``n`` hypotheses when one side has no landmark but ground."""
    out = np.zeros((n, 2))
    if counts is not None:
        counts.append(np.zeros(n, np.int64))
    return out[0] if single else out

@dataclass(frozen=True)
class _GroundFree:
    """What landmark-level evidence reads of one set without its ground plane (read-only)."""

    n: int
    types: NDArray[np.int64]
    directions: NDArray[np.float64]
    anchors: NDArray[np.float64]
    reach: NDArray[np.float64]


def _ground_free(ls: LandmarkSet) -> _GroundFree:
    """:func:`_without_ground` of ``ls`` reduced to the arrays :func:`landmark_overlap` reads,
    computed once per set of arrays (``derived_cache``): a scan scored against several
    candidates, and every call of one verification, reuse them."""
    def make() -> _GroundFree:
        g = _without_ground(ls)
        arrays = (g.types.astype(np.int64), np.ascontiguousarray(g.directions),
                  np.ascontiguousarray(g.anchors), _reach(g))
        for a in arrays:
            a.setflags(write=False)
        return _GroundFree(len(g), *arrays)

    a = ls.attributes
    return derived_cache.get("ground_free", (ls.types, ls.bases, ls.anchors, a.get("is_ground"), a.get("box"),
                                             a.get("extent")), make)


def _without_ground(ls: LandmarkSet) -> LandmarkSet:
    g = ls.attributes.get("is_ground")
    if g is None:
        return ls.without_points()
    keep = np.flatnonzero(np.asarray(g, dtype=float).reshape(-1) < 0.5)
    return ls.without_points()[keep]


def _reach(ls: LandmarkSet) -> NDArray[np.float64]:
    """Half the size of each landmark's support: plane box diagonal / 2, line length / 2 (inf if unknown)."""
    r = np.full(len(ls), np.inf)  # unknown size: no bound
    box = ls.attributes.get("box")
    ext = ls.attributes.get("extent")
    if box is not None:
        b = np.asarray(box, dtype=float).reshape(len(ls), -1)
        diag = np.sqrt(np.nansum(b**2, axis=1)) / 2
        r = np.where(np.isfinite(diag), diag, r)
    if ext is not None:
        e = np.asarray(ext, dtype=float).reshape(-1)
        r = np.where((ls.types == LandmarkType.LINE) & np.isfinite(e), e / 2, r)
        # planes without a box: the half diagonal of a square of that area
        r = np.where((ls.types == LandmarkType.PLANE) & ~np.isfinite(r) & np.isfinite(e) & (e > 0),
                     np.sqrt(np.maximum(e, 0) / 2), r)
    return r
