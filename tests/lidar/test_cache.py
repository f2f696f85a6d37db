"""Landmark cache: hit, invalidation on scan change / config change, corrupt entries."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from graffmatch.lidar import LandmarkCache, LandmarkExtractor, LandmarkExtractorConfig, write_bin
from tests.lidar.scene import make_scene


def test_cache_hit_and_invalidation(tmp_path: Path) -> None:
    scene = make_scene(seed=3)
    scan = write_bin(tmp_path / "velodyne" / "000000.bin", scene.points)
    cache = LandmarkCache(tmp_path / "cache", LandmarkExtractor(), include_points=True)
    first = cache.get(scan)
    again = cache.get(scan)
    assert (cache.misses, cache.hits) == (1, 1)
    assert again.approx_equal(first, atol=1e-9)
    np.testing.assert_array_equal(again.points, first.points)
    # compact file: a few kB, a small fraction of the raw scan even with support points
    entry = cache.path_for(scan)
    assert entry.stat().st_size < 0.1 * scan.stat().st_size
    # a modified scan (new mtime/size) is re-extracted
    write_bin(scan, scene.points[:-1000])
    os.utime(scan, ns=(1, 1))
    cache.get(scan)
    assert cache.misses == 2
    # another config gets its own entry
    other = LandmarkCache(
        tmp_path / "cache", LandmarkExtractor(LandmarkExtractorConfig(min_range=1.0))
    )
    assert other.path_for(scan) != cache.path_for(scan)
    # a corrupt entry is recomputed instead of crashing
    cache.path_for(scan).write_bytes(b"not an npz")
    cache.get(scan)
    assert cache.misses == 3
