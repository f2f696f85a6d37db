"""Decision equality of two code versions: the verified matcher (default config) on the pairs of
``bench/verification.py`` (same datasets, same cache, same pairs), one row per pair with the
transform, ``valid``, overlap, rival ratio, free-space conflict, confidence and message.
``--compare A B`` reports which rows differ (bit-exact transforms, equal decisions), so a change
meant to be pure speed can show that it decides exactly as before.

    python bench/verification_rows.py --out /tmp/gm-verify --json /tmp/rows_before.json
    python bench/verification_rows.py --compare /tmp/rows_before.json /tmp/rows_after.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from verification import ROT_OK, TRANS_OK, load_sources, make_pairs

from graffmatch.errors import InvalidInputError
from graffmatch.geometry.transforms import invert, transform_errors
from graffmatch.matcher import GraffMatcher


def run(out: Path, every: int, sims: bool) -> list[dict]:
    src = load_sources(out, sims)
    pairs = make_pairs(src, 120, 180)[::every]
    matcher = GraffMatcher()
    rows = []
    t_start = time.perf_counter()
    for n, p in enumerate(pairs):
        T, S = src[p["ds"]]["lms"][p["i"]], src[p["ds2"]]["lms"][p["j"]]
        row = dict(p)
        if len(S) < 2 or len(T) < 2:
            rows.append({**row, "message": "too few landmarks"})
            continue
        try:
            r = matcher.match(S, T)
        except InvalidInputError as exc:
            rows.append({**row, "message": str(exc)})
            continue
        row.update(valid=bool(r.valid), overlap=float(r.overlap), confidence=float(r.confidence),
                   ratio=float(r.info.get("rival_ratio", 1.0)) if r.runner_up is not None else 0.0,
                   conflict=[float(c) for c in r.info.get("free_space_conflict", (0.0, 0.0))],
                   message=r.message, n_hyp=len(r.hypotheses),
                   T=None if r.T_target_source is None else np.asarray(r.T_target_source).tolist(),
                   runner_up_T=None if r.runner_up is None else np.asarray(r.runner_up.T_target_source).tolist())
        row["correct"] = False
        if p["ds"] == p["ds2"] and r.T_target_source is not None:
            T_gt = invert(src[p["ds"]]["poses"][p["i"]]) @ src[p["ds"]]["poses"][p["j"]]
            rot, tr = transform_errors(r.T_target_source, T_gt)
            row["correct"] = bool(rot <= ROT_OK and tr <= TRANS_OK)
        rows.append(row)
        if (n + 1) % 200 == 0:
            print(f"  {n + 1}/{len(pairs)} pairs, {time.perf_counter() - t_start:.0f} s", flush=True)
    return rows


def compare(a: list[dict], b: list[dict]) -> int:
    """Print the rows that differ; returns how many differ in the decision (valid or correct).
    ``b`` may hold a subset of ``a``'s pairs (``--every``): rows are matched by pair."""
    by_pair = {(r["ds"], r["i"], r["ds2"], r["j"]): r for r in a}
    a = [by_pair[(r["ds"], r["i"], r["ds2"], r["j"])] for r in b]
    keys = ("valid", "correct", "overlap", "ratio", "conflict", "confidence", "message", "n_hyp")
    n_T = n_other = n_dec = 0
    max_dT = 0.0
    pose = {"all": (0.0, 0.0), "valid": (0.0, 0.0)}  # largest rotation [deg] / translation [m] change
    for ra, rb in zip(a, b, strict=True):
        assert (ra["ds"], ra["i"], ra["ds2"], ra["j"]) == (rb["ds"], rb["i"], rb["ds2"], rb["j"])
        Ta, Tb = ra.get("T"), rb.get("T")
        dT = 0.0 if Ta is None and Tb is None else (
            np.inf if (Ta is None) != (Tb is None) else float(np.abs(np.subtract(Ta, Tb)).max()))
        diff = [k for k in keys if ra.get(k) != rb.get(k)]
        n_T += dT != 0.0
        max_dT = max(max_dT, dT)
        n_other += bool(diff)
        if ra.get("valid") != rb.get("valid") or ra.get("correct") != rb.get("correct"):
            n_dec += 1
        moved = ""
        if Ta is not None and Tb is not None and dT != 0.0:
            rot, tr = transform_errors(np.array(Tb), np.array(Ta))
            moved = f" ({rot:.3g} deg / {tr:.3g} m)"
            for k in ("all", "valid") if ra.get("valid") or rb.get("valid") else ("all",):
                pose[k] = (max(pose[k][0], rot), max(pose[k][1], tr))
        if diff or dT != 0.0:
            print(f"{ra['ds']}:{ra['i']} <- {ra['ds2']}:{ra['j']}: max |dT| {dT:.3g}{moved}; "
                  + ", ".join(f"{k} {ra.get(k)!r} -> {rb.get(k)!r}" for k in diff))
    n_valid = sum(bool(r.get("valid")) for r in a)
    print(f"{len(a)} pairs ({n_valid} valid): transforms differ on {n_T} (max |dT| {max_dT:.3g}), other fields on "
          f"{n_other}, decisions (valid / correct) on {n_dec}; largest pose change {pose['all'][0]:.3g} deg / "
          f"{pose['all'][1]:.3g} m, on valid rows {pose['valid'][0]:.3g} deg / {pose['valid'][1]:.3g} m")
    return n_dec


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="/tmp/gm-verify", help="bench/verification.py's --out (its dataset cache)")
    ap.add_argument("--every", type=int, default=1, help="every k-th pair only")
    ap.add_argument("--no-sim", action="store_true")
    ap.add_argument("--json", default=None)
    ap.add_argument("--compare", nargs=2, default=None, metavar=("A", "B"))
    a = ap.parse_args()
    if a.compare:
        ra, rb = (json.loads(Path(f).read_text())["rows"] for f in a.compare)
        raise SystemExit(1 if compare(ra, rb) else 0)
    rows = run(Path(a.out), a.every, not a.no_sim)
    if a.json:
        Path(a.json).parent.mkdir(parents=True, exist_ok=True)
        Path(a.json).write_text(json.dumps({"rows": rows}, indent=0, default=float))
        print(f"wrote {a.json}: {len(rows)} rows")


if __name__ == "__main__":
    main()
