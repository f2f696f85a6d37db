"""Free-space evidence: a hypothesis is wrong when it puts one scan's structure where the other
scan's sensor saw through it.

Overlap counts the points a hypothesis explains; it cannot see an aliased alignment of
repetitive structure (tree rows along two different country roads, a 90 deg turn between two
similar streets) that explains a quarter of the points by chance. Such an alignment also puts
many of the source's points in front of what the target's beams reached: in space the target
observed as empty. The test is the classic visibility check of map merging: each scan's
support points, ground included (a ground return proves the beam travelled that far), form a
spherical range image around the sensor (the frame's origin) holding, per cell, the nearest
return of the cell and its neighbours. A point of the other scan mapped into a cell more than
``margin`` in front of that range conflicts.

The support points are a sparse sample of the scan: whatever the extractor did not turn into a
landmark (a trunk it missed, a parked car, a wall too small for a plane) is transparent in their
image, and a right match puts the other scan's view of it "in free space" (right sim-downtown
matches conflicted on up to 30 % of their points). So the extractor also stores the nearest
return of the *whole* scan per 1 deg cell (:func:`cell_minimum_ranges`, kept in
``LandmarkSet.scan_ranges``), and the check uses that image when a set carries it
(:meth:`RangeImage.from_cell_minima`); the support points' image remains for sets without it.

It assumes the landmarks are in their sensor's frame (one scan, origin = sensor), which is
what the extractor produces; maps in a world frame must switch it off
(``VerificationConfig.free_space``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import minimum_filter

from graffmatch.geometry.transforms import invert


@dataclass
class RangeImage:
    """Nearest return per (azimuth, elevation) cell around the sensor, min-filtered over the
    neighbouring cells (a thin pole seen by one beam still shadows its neighbours' beams);
    ``inf`` where nothing returned (unknown: no free space is claimed there)."""

    ranges: NDArray[np.float64]
    az_deg: float
    el_deg: float
    #: built from a whole scan's returns (:meth:`from_cell_minima`), not from support points
    whole_scan: bool = False

    @classmethod
    def from_points(cls, points: NDArray, az_deg: float = 1.0, el_deg: float = 1.0,
                    neighbours: int = 1) -> RangeImage:
        img, cells = _empty_image(points, az_deg, el_deg)
        if cells is not None:
            _spread_min(*cells, int(neighbours), img)
        return cls(img, az_deg, el_deg)

    @classmethod
    def _from_points_reference(cls, points: NDArray, az_deg: float = 1.0, el_deg: float = 1.0,
                               neighbours: int = 1) -> RangeImage:
        """numpy / scipy specification of :meth:`from_points` (per-cell minimum, then a
        minimum filter wrapping in azimuth and clamped in elevation)."""
        img, cells = _empty_image(points, az_deg, el_deg)
        if cells is not None:
            a, e, r = cells
            np.minimum.at(img, (a, e), r)
        if neighbours > 0:
            size = 2 * neighbours + 1
            img = minimum_filter(img, size=(size, size), mode=("wrap", "nearest"))
        return cls(img, az_deg, el_deg)

    @classmethod
    def from_cell_minima(cls, minima: NDArray, az_deg: float, el_deg: float, neighbours: int = 0
                         ) -> RangeImage | None:
        """The image of a whole scan's per-cell nearest returns (:func:`cell_minimum_ranges`),
        pooled to ``az_deg`` x ``el_deg`` cells (multiples of the stored cells; None if not)
        and min-filtered over ``neighbours`` cells."""
        na0, ne0 = minima.shape
        pa, pe = az_deg * na0 / 360.0, el_deg * ne0 / 180.0
        if abs(pa - round(pa)) > 1e-9 or abs(pe - round(pe)) > 1e-9 or round(pa) < 1 or round(pe) < 1:
            return None
        pa, pe = int(round(pa)), int(round(pe))
        if na0 % pa or ne0 % pe:
            return None
        img = np.asarray(minima, dtype=np.float64)
        if pa > 1 or pe > 1:
            # the minimum of the pa x pe strided views: 0.05 ms against numpy's 1.5 ms
            # reduction over two non-adjacent axes of a reshape (a cold match pools two images)
            pooled = img[0::pa, 0::pe]
            for i in range(pa):
                for j in range(pe):
                    if i or j:
                        pooled = np.minimum(pooled, img[i::pa, j::pe])
            img = pooled
        if neighbours > 0:
            size = 2 * int(neighbours) + 1
            img = minimum_filter(img, size=(size, size), mode=("wrap", "nearest"))
        return cls(np.ascontiguousarray(img), az_deg, el_deg, whole_scan=True)

    def conflicts(self, points: NDArray[np.float64], margin: float, margin_rel: float = 0.05,
                  min_range: float = 2.0) -> tuple[int, int]:
        """(points in front of the observed range R by more than max(``margin``,
        ``margin_rel`` R), points whose cell holds a return), for points in this image's
        sensor frame; points closer than ``min_range`` are not judged."""
        na, ne = self.ranges.shape
        a, e, r = _cells(points, self.az_deg, self.el_deg, na, ne)
        R = self.ranges[a, e]
        known = np.isfinite(R) & (r > min_range)
        with np.errstate(invalid="ignore"):
            bad = known & (r < R - np.maximum(margin, margin_rel * R))
        return int(bad.sum()), int(known.sum())


def cell_minimum_ranges(points: NDArray, az_deg: float = 1.0, el_deg: float = 1.0) -> NDArray[np.float32]:
    """Nearest horizontal range per (azimuth, elevation) cell of a whole scan in its sensor's
    frame (inf: no return): a few tens of kB that keep every beam's evidence of free space."""
    na, ne = int(round(360.0 / az_deg)), int(round(180.0 / el_deg))
    P = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 3))
    img = np.full((na, ne), np.inf, dtype=np.float32)
    # the azimuth cells as _cells computes them from numpy's (vectorised) arctan2, the rest of
    # the formula in the compiled pass; elevation cell e holds the angles in
    # [-90 + e el, -90 + (e+1) el): counting the boundaries a point lies on or above
    # (z >= r tan b) needs no arctan2
    with np.errstate(invalid="ignore"):
        ang = np.arctan2(P[:, 1], P[:, 0])
    tan_edges = np.tan(np.radians(-90.0 + np.arange(1, ne) * el_deg))
    _cell_minima(P, ang, float(az_deg), float(el_deg), tan_edges, img)
    return img


@nb.njit(cache=True)
def _cell_minima(P: NDArray[np.float64], ang: NDArray[np.float64], az_deg: float, el_deg: float,
                 tan_edges: NDArray[np.float64], img: NDArray[np.float32]) -> None:
    """The compiled part of :func:`cell_minimum_ranges`: the azimuth cells of :func:`_cells` from
    the angles ``ang`` (numpy's ``floor((degrees(ang) + 180) / az_deg)``, non-finite -> 0, modulo
    the cells), the elevation cells of :func:`_cells` (non-finite points skipped; the number of
    boundaries the point lies on or above, z >= r tan b, which holds for a prefix of the
    ascending boundaries: so the previous point's count, confirmed by its two neighbouring
    boundaries, is the count (consecutive returns of a ring share it), else a binary search;
    the angle itself straight up, straight down and at the sensor), each cell lowered to its
    nearest return."""
    na, ne = img.shape
    n_edges = tan_edges.shape[0]
    to_deg = 180.0 / np.pi
    e_prev = 0
    for p in range(P.shape[0]):
        x, y, z = P[p, 0], P[p, 1], P[p, 2]
        if not (np.isfinite(x) and np.isfinite(y) and np.isfinite(z)):
            continue
        af = np.floor((ang[p] * to_deg + 180.0) / az_deg)
        ai = int(af) if np.isfinite(af) else 0
        if ai < 0 or ai >= na:  # (an integer division only off the usual range)
            ai %= na
        r = np.sqrt(x * x + y * y)
        if not np.isfinite(r):  # |x|, |y| > 1e154: the squares overflow
            r = np.hypot(x, y)
        if r > 0.0:
            e = e_prev
            if not ((e == 0 or z >= r * tan_edges[e - 1]) and (e == n_edges or not z >= r * tan_edges[e])):
                lo, hi = 0, n_edges
                while lo < hi:
                    mid = (lo + hi) >> 1
                    if z >= r * tan_edges[mid]:
                        lo = mid + 1
                    else:
                        hi = mid
                e = lo
            e_prev = e
        else:
            e = min(max(int(np.floor((np.arctan2(z, r) * to_deg + 90.0) / el_deg)), 0), ne - 1)
        if r < img[ai, e]:
            img[ai, e] = r


def _empty_image(points: NDArray, az_deg: float, el_deg: float) -> tuple[NDArray[np.float64], tuple | None]:
    """An all-unknown (inf) image of the cell grid, and the cells of the finite points (None:
    no finite point); what the compiled image and its reference share."""
    na, ne = int(round(360.0 / az_deg)), int(round(180.0 / el_deg))
    img = np.full((na, ne), np.inf)
    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    P = P[np.isfinite(P).all(axis=1)]
    return img, (_cells(P, az_deg, el_deg, na, ne) if len(P) else None)


def _cells(P: NDArray[np.float64], az_deg: float, el_deg: float, na: int, ne: int
           ) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.float64]]:
    """Cell indices and horizontal range of points (sensor at the origin)."""
    r = np.hypot(P[:, 0], P[:, 1])
    a = (np.floor((np.degrees(np.arctan2(P[:, 1], P[:, 0])) + 180.0) / az_deg).astype(np.int64)) % na
    e = np.clip(np.floor((np.degrees(np.arctan2(P[:, 2], r)) + 90.0) / el_deg).astype(np.int64), 0, ne - 1)
    return a, e, r


@nb.njit(cache=True)
def _spread_min(a: NDArray[np.int64], e: NDArray[np.int64], r: NDArray[np.float64], k: int,
                img: NDArray[np.float64]) -> None:
    """Lower every cell within ``k`` cells of each point's (wrapping in azimuth, elevation cells
    inside the image) to the point's range: the per-cell minimum and the (2k+1)^2 minimum
    filter of :meth:`RangeImage._from_points_reference` in one pass over the points (a cell's
    filtered value is the minimum over the points whose cell lies within k of it; clamping the
    elevation at the border only repeats cells inside that window)."""
    na, ne = img.shape
    for p in range(a.shape[0]):
        for da in range(-k, k + 1):
            ai = (a[p] + da) % na
            for de in range(max(e[p] - k, 0), min(e[p] + k, ne - 1) + 1):
                if r[p] < img[ai, de]:
                    img[ai, de] = r[p]


def conflict_fraction(
    source_points: NDArray[np.float64], target_points: NDArray[np.float64],
    source_image: RangeImage, target_image: RangeImage, T_target_source: NDArray[np.float64],
    margin: float, margin_rel: float = 0.05,
    source_pose: NDArray[np.float64] | None = None, target_pose: NDArray[np.float64] | None = None,
) -> tuple[float, float]:
    """Share of each scan's points that the hypothesis puts in the other's observed free space
    (source -> target, target -> source); 0 where no point falls in an observed cell. Each
    image is in its sensor's frame (``*_pose``: the sensor in the set's frame; None: identity)."""
    Ts = np.eye(4) if source_pose is None else source_pose
    Tt = np.eye(4) if target_pose is None else target_pose
    M_st = invert(Tt) @ T_target_source  # source set frame -> target sensor frame
    M_ts = invert(Ts) @ invert(T_target_source)  # target set frame -> source sensor frame
    q_st = source_points @ M_st[:3, :3].T + M_st[:3, 3]
    q_ts = target_points @ M_ts[:3, :3].T + M_ts[:3, 3]
    b1, k1 = target_image.conflicts(q_st, margin, margin_rel)
    b2, k2 = source_image.conflicts(q_ts, margin, margin_rel)
    return (b1 / k1 if k1 else 0.0), (b2 / k2 if k2 else 0.0)
