"""Raw-scan registration with and without the scan re-alignment of valid support-point answers
(``ScanMatcherConfig.scan_realign_m``, session 22), on the product path (``ScanMatcher.match_scans`` with the
extractor's clouds, as ``register`` calls it).

Two data sets, nothing chosen on either (the re-alignment's distance is the rival distance, 1 m, and its rule, "keep
the ICP pose when it reaches at least as many source points", has no threshold):
* ``courtyard``: every pair of ``balm_courtyard``'s 89 scans (3,916), as ``bench/verification_bare_real.py``;
* ``heldout``: the test split of ``bench/verification.py`` (second halves of the courtyard and the three simulated
  drives, de-skewed; KITTI's six scans; negatives > 60 m apart and across data sets), built by its own loaders.

A valid result is wrong when it is more than 5 deg or 1 m off the ground truth (negatives across data sets have
none: any valid one is wrong). Prints and writes JSON::

    python bench/verification_scan_realign.py --out /tmp/gm-verify --json bench/results/verification_scan_realign_session22.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine
from verification import load_sources, make_pairs

from graffmatch.datasets.deskewed import Deskewed
from graffmatch.datasets.folder import KittiFolder
from graffmatch.evaluation.suites import SIM_EXTRACTORS, SUITES, shared_data_root, suite_config
from graffmatch.geometry.transforms import transform_errors
from graffmatch.lidar.extractor import LandmarkExtractorConfig
from graffmatch.loops.posegraph import OdometryDriftConfig, drifted_odometry
from graffmatch.pipeline import ScanMatcher, ScanMatcherConfig

ROT_OK, TRANS_OK = 5.0, 1.0
SIMS = ("sim-downtown", "sim-suburban", "sim-openroad")


def datasets(out: Path) -> dict[str, tuple]:
    """name -> (dataset of raw scans as the verification bench reads them, extractor config)."""
    root = shared_data_root()
    d = {"courtyard": (KittiFolder(root / "balm_courtyard"), suite_config("balm_courtyard").extractor),
         "kitti": (KittiFolder(root / "kitti00_first6"), LandmarkExtractorConfig())}
    for k, name in enumerate(SIMS):
        ds = SUITES[name].make_dataset(out / f"suite-{name}", False, None)
        odometry = drifted_odometry(ds.poses, OdometryDriftConfig(seed=k))
        d[name] = (Deskewed(ds, odometry), LandmarkExtractorConfig.model_validate(SIM_EXTRACTORS.get(name, {})))
    return d


class Scans:
    """Each scan extracted once (landmarks with points, the extractor's voxel cloud), on first use."""

    def __init__(self, data: dict[str, tuple]) -> None:
        self.data = data
        self.cache: dict[tuple[str, int], tuple] = {}
        self.extractors = {name: ScanMatcher(ScanMatcherConfig(extractor=cfg)) for name, (_ds, cfg) in data.items()}

    def get(self, name: str, i: int) -> tuple:
        if (name, i) not in self.cache:
            sm = self.extractors[name]
            ls = sm.extract(self.data[name][0][i].points)
            self.cache[name, i] = (ls, sm.extractor.last_cloud)
        return self.cache[name, i]


def run(pairs: list[dict], scans: Scans, poses: dict[str, np.ndarray]) -> dict:
    """Both settings on every pair: counts of valid, valid-and-wrong, fixed and broken, and the times."""
    on, off = ScanMatcher(ScanMatcherConfig()), ScanMatcher(ScanMatcherConfig(scan_realign_m=None))
    rows = []
    for p in pairs:
        S, Sc = scans.get(p["ds2"], p["j"])  # source: scan j of ds2, target: scan i of ds (bench/verification.py)
        T, Tc = scans.get(p["ds"], p["i"])
        if len(S) < 2 or len(T) < 2:
            continue
        row = dict(p)
        gt = None
        if p["ds"] == p["ds2"]:
            P = poses[p["ds"]]
            gt = np.linalg.solve(P[p["i"]], P[p["j"]])
        for tag, sm in (("off", off), ("on", on)):
            t0 = time.perf_counter()
            r = sm.match_scans(S, T, None, None, Sc, Tc)
            row[f"t_{tag}"] = time.perf_counter() - t0
            row[f"valid_{tag}"] = bool(r.valid)
            err = None if (gt is None or r.T_target_source is None) else list(map(float, transform_errors(r.T_target_source, gt)))
            row[f"err_{tag}"] = err
            row[f"wrong_{tag}"] = bool(r.valid and (err is None or err[0] > ROT_OK or err[1] > TRANS_OK))
            if tag == "on":
                row["realign"] = r.info.get("scan_realign")
        rows.append(row)
    return summarise(rows)


def summarise(rows: list[dict]) -> dict:
    out: dict = {"pairs": len(rows)}
    for tag in ("off", "on"):
        v = [r for r in rows if r[f"valid_{tag}"]]
        w = [r for r in v if r[f"wrong_{tag}"]]
        neg = [r for r in rows if not r.get("positive", True)]
        out[tag] = {"valid": len(v), "valid_wrong": len(w), "precision": 1 - len(w) / max(len(v), 1),
                    "negatives": len(neg), "negatives_valid_wrong": sum(r[f"wrong_{tag}"] for r in neg),
                    "ms_median": 1e3 * float(np.median([r[f"t_{tag}"] for r in rows])) if rows else 0.0,
                    "ms_p95": 1e3 * float(np.percentile([r[f"t_{tag}"] for r in rows], 95)) if rows else 0.0}
        errs = np.array([r[f"err_{tag}"] for r in v if r[f"err_{tag}"] is not None and not r[f"wrong_{tag}"]])
        if len(errs):
            out[tag]["right_rot_deg_median_p95"] = np.percentile(errs[:, 0], [50, 95]).round(3).tolist()
            out[tag]["right_trans_m_median_p95"] = np.percentile(errs[:, 1], [50, 95]).round(3).tolist()
    both = [r for r in rows if r["valid_off"] and r["valid_on"]]
    out["fixed"] = [(r["ds"], r["i"], r["j"]) for r in both if r["wrong_off"] and not r["wrong_on"]]
    out["broken"] = [(r["ds"], r["i"], r["j"]) for r in both if not r["wrong_off"] and r["wrong_on"]]
    out["still_wrong"] = [(r["ds"], r["i"], r["j"], r["err_on"]) for r in both if r["wrong_on"]]
    out["applied"] = sum(1 for r in rows if r.get("realign") and r["realign"]["applied"])
    out["moved_beyond_1m"] = sum(1 for r in rows if r.get("realign") and r["realign"]["applied"]
                                 and r["realign"]["moved_m"] > 1.0)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="/tmp/gm-verify", help="the verification bench's data folder (built if absent)")
    ap.add_argument("--only", choices=("courtyard", "heldout"), default=None)
    ap.add_argument("--json", default=None)
    a = ap.parse_args()
    warnings.simplefilter("ignore")
    out = Path(a.out)
    data = datasets(out)
    scans = Scans(data)
    poses = {name: np.asarray(ds.poses) for name, (ds, _cfg) in data.items()}
    res: dict = {"machine": machine()}
    if a.only in (None, "courtyard"):
        n = len(data["courtyard"][0])
        t0 = time.perf_counter()
        pairs = [dict(ds="courtyard", i=m, j=q, ds2="courtyard", positive=True) for q in range(n) for m in range(q)]
        res["courtyard"] = run(pairs, scans, poses)
        res["courtyard"]["seconds"] = time.perf_counter() - t0
        print("courtyard, every pair:", json.dumps({k: v for k, v in res["courtyard"].items() if k != "fixed"}))
    if a.only in (None, "heldout"):
        t0 = time.perf_counter()
        src = load_sources(out, sims=True)
        pairs = [p for p in make_pairs(src, 120, 180) if p["split"] == "test"]
        res["heldout"] = run(pairs, scans, poses)
        res["heldout"]["seconds"] = time.perf_counter() - t0
        print("held-out test split:", json.dumps({k: v for k, v in res["heldout"].items() if k != "fixed"}))
    if a.json:
        Path(a.json).write_text(json.dumps(res, indent=1, default=float))


if __name__ == "__main__":
    main()
