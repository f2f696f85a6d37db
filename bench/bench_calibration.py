"""Benchmark: GraffMatch extrinsic calibration on the simulated rigs over many seeds.

Reports, per kind (LiDAR–LiDAR, camera–depth), the rotation / translation errors against the
known extrinsic and the time of each stage, next to the paper's real-rig numbers (1.1°/8 cm in
75 ms and 0.9°/5 cm in 23 ms; the paper's time is the matching of the planes).

    .venv/bin/python bench/bench_calibration.py --seeds 10 [--rho 4] [--json out.json]
    .venv/bin/python bench/bench_calibration.py --seeds 10 --rho-sweep   # ρ sensitivity

The ρ sweep extracts the planes once per seed and re-runs only GraffMatch + registration
(without the re-association step, so that the count is GraffMatch's own) for each ρ.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from graffmatch.calibration.camera_depth import CameraDepthConfig
from graffmatch.calibration.demo import PAPER_REFERENCE, run_calibration_demo
from graffmatch.calibration.lidar_lidar import LidarLidarConfig

KINDS = ("lidar-lidar", "camera-depth")


def _config(kind: str, rho: float | None):
    cfg = LidarLidarConfig() if kind == "lidar-lidar" else CameraDepthConfig()
    if rho is not None:
        cfg.calibration.matcher.rho = rho
    return cfg


def run(seeds: int, rho: float | None, kinds: tuple[str, ...]) -> dict:
    # Warm-up: the first call loads numba's cached kernels; it is not calibration time.
    run_calibration_demo("camera-depth", seed=10_000, config=_config("camera-depth", rho))
    rows: dict[str, list[dict]] = {k: [] for k in kinds}
    for kind in kinds:
        for seed in range(seeds):
            t0 = time.perf_counter()
            try:
                rep = run_calibration_demo(kind, seed=seed, config=_config(kind, rho))
            except Exception as exc:  # a failure is a data point of the benchmark
                rep = {"kind": kind, "seed": seed, "valid": False, "message": str(exc)}
            rep["wall_s"] = time.perf_counter() - t0
            rows[kind].append(rep)
            _print_row(rep)
    return rows


def _print_row(r: dict) -> None:
    if "rotation_error_deg" not in r:
        print(f"{r['kind']:<13} {r['seed']:>4}  FAILED: {r['message']}")
        return
    t = r["timings_s"]
    n_planes = "/".join(str(v) for v in r["n_planes"].values())
    print(
        f"{r['kind']:<13} {r['seed']:>4} {r['rotation_error_deg']:>8.3f} "
        f"{100 * r['translation_error_m']:>8.2f} {r['n_matched']:>3}/{n_planes:<6} "
        f"{r['kappa']:>6.2f} {1e3 * t['graffmatch']:>8.1f} {1e3 * t['total']:>8.0f} "
        f"{r['valid']!s:>6}"
    )


def summarise(rows: dict) -> dict:
    out = {}
    for kind, reps in rows.items():
        ok = [r for r in reps if "rotation_error_deg" in r]
        rot = np.array([r["rotation_error_deg"] for r in ok])
        tr = np.array([r["translation_error_m"] for r in ok])
        gm = np.array([r["timings_s"]["graffmatch"] for r in ok])
        tot = np.array([r["timings_s"]["total"] for r in ok])
        within = sum(bool(r.get("within_bounds")) for r in reps)
        out[kind] = {
            "runs": len(reps),
            "within_1deg_5cm": within,
            "valid": sum(bool(r.get("valid")) for r in reps),
            "rotation_deg": {"median": float(np.median(rot)), "max": float(rot.max())},
            "translation_m": {"median": float(np.median(tr)), "max": float(tr.max())},
            "graffmatch_ms": {"median": 1e3 * float(np.median(gm)), "max": 1e3 * float(gm.max())},
            "total_ms": {"median": 1e3 * float(np.median(tot)), "max": 1e3 * float(tot.max())},
            "matched_planes_median": float(np.median([r["n_matched"] for r in ok])),
            "paper": PAPER_REFERENCE[kind],
        }
    return out


RHO_SWEEP = (0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 40.0)


def _planes_for_seed(kind: str, seed: int):
    """(source planes, target planes, true extrinsic) of one simulated rig."""
    from graffmatch.calibration.camera_depth import calibrate_camera_depth
    from graffmatch.calibration.lidar_lidar import calibrate_lidar_lidar
    from graffmatch.calibration.rig import make_camera_depth_scenario, make_lidar_lidar_scenario

    if kind == "lidar-lidar":
        sc = make_lidar_lidar_scenario(seed)
        r = calibrate_lidar_lidar(sc.cloud_a, sc.cloud_b)
        return r.source_planes, r.target_planes, sc.T_b_a
    sc = make_camera_depth_scenario(seed)
    r = calibrate_camera_depth(sc.image, sc.camera.K, sc.depth, sc.depth_camera.K, sc.board)
    return r.source_planes, r.target_planes, sc.T_depth_camera


def rho_sweep(seeds: int, kinds: tuple[str, ...]) -> dict:
    from graffmatch.calibration.result import CalibrationConfig, calibrate_planes
    from graffmatch.geometry.transforms import transform_errors

    out: dict[str, dict[str, dict]] = {}
    for kind in kinds:
        planes = [_planes_for_seed(kind, seed) for seed in range(seeds)]
        out[kind] = {}
        for rho in RHO_SWEEP:
            ok = matched = 0
            rots = []
            for src, tgt, T_true in planes:
                cfg = CalibrationConfig(reassociate=False)
                cfg.matcher.rho = rho
                try:
                    r = calibrate_planes(src, tgt, cfg)
                except Exception:  # a failure counts as a miss
                    continue
                rot, tr = transform_errors(r.T_target_source, T_true)
                ok += int(r.valid and rot <= 1.0 and tr <= 0.05)
                matched += r.n_graffmatch
                rots.append(rot)
            out[kind][str(rho)] = {
                "within_bounds": ok,
                "runs": len(planes),
                "mean_graffmatch_associations": matched / max(len(planes), 1),
                "median_rotation_deg": float(np.median(rots)) if rots else float("nan"),
            }
            print(
                f"{kind:<13} rho={rho:>5}: {ok}/{len(planes)} within 1 deg/5 cm, "
                f"{matched / max(len(planes), 1):.1f} GraffMatch associations on average"
            )
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--seeds", type=int, default=10, help="seeds 0..N-1 per kind")
    ap.add_argument("--rho", type=float, default=None, help="override GraffMatch rho [m]")
    ap.add_argument("--kind", choices=(*KINDS, "both"), default="both")
    ap.add_argument("--json", type=Path, default=None, help="write rows + summary as JSON")
    ap.add_argument("--rho-sweep", action="store_true", help="only the ρ sensitivity sweep")
    args = ap.parse_args(argv)
    kinds = KINDS if args.kind == "both" else (args.kind,)
    if args.rho_sweep:
        sweep = rho_sweep(args.seeds, kinds)
        if args.json:
            args.json.parent.mkdir(parents=True, exist_ok=True)
            args.json.write_text(json.dumps({"rho_sweep": sweep}, indent=1))
            print(f"wrote {args.json}")
        return 0
    load = os.getloadavg()[0]
    print(f"machine: {os.cpu_count()} cpus, load average {load:.1f} at start")
    print(
        f"{'kind':<13} {'seed':>4} {'rot_deg':>8} {'trans_cm':>8} {'matched':<10} "
        f"{'kappa':>6} {'gm_ms':>8} {'tot_ms':>8} {'valid':>6}"
    )
    rows = run(args.seeds, args.rho, kinds)
    summary = summarise(rows)
    print()
    print(
        f"{'kind':<13} {'ok/runs':>8} {'rot med/max deg':>16} {'trans med/max cm':>17} "
        f"{'GraffMatch med ms':>18} {'total med ms':>13}   paper"
    )
    for kind, s in summary.items():
        p = s["paper"]
        print(
            f"{kind:<13} {s['within_1deg_5cm']:>3}/{s['runs']:<4} "
            f"{s['rotation_deg']['median']:>7.3f}/{s['rotation_deg']['max']:<8.3f} "
            f"{100 * s['translation_m']['median']:>8.2f}/{100 * s['translation_m']['max']:<8.2f} "
            f"{s['graffmatch_ms']['median']:>18.1f} {s['total_ms']['median']:>13.0f}   "
            f"{p['rotation_deg']} deg / {100 * p['translation_m']:.0f} cm / {p['time_ms']:.0f} ms"
        )
    print(f"load average at end {os.getloadavg()[0]:.1f}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(
            json.dumps(
                {"rows": rows, "summary": summary, "rho": args.rho, "load_start": load}, indent=1
            )
        )
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
