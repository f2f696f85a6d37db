"""Byte-level equality of the extractor's landmark tables between two code versions.

    GRAFFMATCH_SHARED_DATA=... python bench/landmark_table_digests.py --json /tmp/a.json   # old code
    GRAFFMATCH_SHARED_DATA=... python bench/landmark_table_digests.py --json /tmp/b.json   # new code
    python bench/landmark_table_digests.py --compare /tmp/a.json /tmp/b.json

Extracts a fixed list of scans (every 4th courtyard scan, the six KITTI scans with and without
the whole-scan range image, every 25th scan of the three de-skewed simulated drives of
``bench/verification.py``, from its ``--out`` directory, read only) and records one SHA-1 per
table over every field's dtype, shape and bytes (types, bases, anchors, attributes, support
points, offsets, scan ranges, sensor pose). A change meant to be pure speed shows 0 differences.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from graffmatch.datasets.folder import KittiFolder
from graffmatch.evaluation.suites import SIM_EXTRACTORS, SUITES, shared_data_root, suite_config
from graffmatch.geometry.landmarks import LandmarkSet
from graffmatch.lidar.extractor import LandmarkExtractor, LandmarkExtractorConfig


def digest(ls: LandmarkSet) -> str:
    """SHA-1 over every field of a table (dtype, shape and bytes)."""
    h = hashlib.sha1()
    for name in LandmarkSet.__slots__:
        v = getattr(ls, name)
        items = sorted(v.items()) if name == "attributes" else [(name, v)]
        for key, x in items:
            h.update(key.encode())
            if x is None:
                h.update(b"None")
                continue
            a = np.asarray(x)
            h.update(f"{a.dtype}{a.shape}".encode())
            h.update(a.tobytes())
    return h.hexdigest()


def run(out: Path) -> dict[str, str]:
    from verification import Deskewed

    from graffmatch.loops.posegraph import OdometryDriftConfig, drifted_odometry

    root = shared_data_root()
    kitti = KittiFolder(root / "kitti00_first6")
    jobs = [("courtyard", KittiFolder(root / "balm_courtyard"), suite_config("balm_courtyard").extractor, 4),
            ("kitti", kitti, LandmarkExtractorConfig(), 1),
            ("kitti-no-ranges", kitti, LandmarkExtractorConfig(scan_ranges=False), 1)]
    for k, name in enumerate(("sim-downtown", "sim-suburban", "sim-openroad")):
        ds = SUITES[name].make_dataset(out / f"suite-{name}", False, None)
        jobs.append((f"{name}-deskew", Deskewed(ds, drifted_odometry(ds.poses, OdometryDriftConfig(seed=k))),
                     LandmarkExtractorConfig.model_validate(SIM_EXTRACTORS.get(name, {})), 25))
    res = {}
    for name, ds, cfg, step in jobs:
        ex = LandmarkExtractor(cfg)
        for i in range(0, len(ds), step):
            res[f"{name}:{i}"] = digest(ex.extract(ds[i].points, None))
        print(f"  {name}: {len(range(0, len(ds), step))} tables", flush=True)
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="/tmp/gm-verify", help="bench/verification.py's --out (simulated drives)")
    ap.add_argument("--json", default=None)
    ap.add_argument("--compare", nargs=2, default=None, metavar=("A", "B"))
    a = ap.parse_args()
    if a.compare:
        da, db = (json.loads(Path(f).read_text()) for f in a.compare)
        differ = sorted(k for k in da.keys() & db.keys() if da[k] != db[k])
        missing = sorted(da.keys() ^ db.keys())
        for k in differ:
            print(f"differs: {k}")
        print(f"{len(da.keys() & db.keys())} tables compared: {len(differ)} differ, {len(missing)} in one file only")
        raise SystemExit(1 if differ or missing else 0)
    res = run(Path(a.out))
    if a.json:
        Path(a.json).write_text(json.dumps(res, indent=0, sort_keys=True))
        print(f"wrote {a.json}: {len(res)} tables")


if __name__ == "__main__":
    main()
