"""Fuzz the trust of ``valid``: hypothesis-style random landmark pairs with known transforms
(degenerate geometry, outliers, low overlap, far coordinates, wrong units, unrelated scenes),
and count valid-and-wrong results (wrong: > 5 deg or > 1 m). Target: at most 0.1 % of valid.

    python bench/fuzz_validity.py --n 10000 --json bench/results/fuzz_validity.json

The landmark-only translation check's threshold (``min_translation_redundancy``) was chosen
on ``--seed 1 --min-translation-redundancy 0`` (the check off: the leave-one-out information
of every valid result, right and wrong) and is reported on seed 0.
"""

from __future__ import annotations

import argparse
import json
import time
from collections import Counter
from pathlib import Path

import numpy as np

from graffmatch.datasets.landmark_scene import make_scene_pair
from graffmatch.errors import GraffMatchError
from graffmatch.geometry.landmarks import LandmarkSet
from graffmatch.geometry.transforms import make_transform, transform_errors
from graffmatch.matcher import GraffMatchConfig, GraffMatcher


def case(rng: np.random.Generator):
    """One random pair: (source, target, T or None for unrelated, kind)."""
    seed = int(rng.integers(2**31 - 1))
    kind = str(rng.choice(["plain", "outliers", "degenerate", "low-overlap", "far", "wrong-unit", "unrelated"],
                          p=[0.2, 0.2, 0.15, 0.15, 0.1, 0.1, 0.1]))
    n_poles = int(rng.integers(0, 14))
    n_planes = int(rng.integers(2, 24))
    kw = dict(seed=seed, yaw_deg=float(rng.uniform(-180, 180)),
              translation=tuple(rng.uniform(-20, 20, 3) * [1, 1, 0.1]))
    if kind == "outliers":
        kw["n_outliers"] = int(rng.integers(2, 20))
    if kind == "degenerate":
        n_poles, n_planes = int(rng.integers(0, 4)), int(rng.integers(2, 5))
    if kind == "low-overlap":
        kw["overlap"] = float(rng.uniform(0.2, 0.5))
    sc = make_scene_pair(n_poles, n_planes, **kw)
    src, tgt, T = sc.source, sc.target, sc.T_target_source
    if kind == "far":
        shift = make_transform(np.eye(3), rng.uniform(-1e5, 1e5, 3) * [1, 1, 0])
        tgt, T = tgt.transform(shift), shift @ T
    if kind == "wrong-unit":
        s = float(rng.choice([2.0, 0.5, 0.01, 100.0]))
        src = LandmarkSet.from_arrays(src.types, src.directions, src.anchors * s, src.attributes)
        T = None
    if kind == "unrelated":
        other = make_scene_pair(n_poles, n_planes, seed=seed + 1)
        src, T = other.source, None
    return src, tgt, T, kind


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=10000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", default=None)
    ap.add_argument("--min-translation-redundancy", type=float, default=None,
                    help="override the landmark-only translation check (0: off)")
    a = ap.parse_args()
    rng = np.random.default_rng(a.seed)
    cfg = GraffMatchConfig()
    if a.min_translation_redundancy is not None:
        cfg.verification.min_translation_redundancy = a.min_translation_redundancy
    m = GraffMatcher(cfg)
    information = []  # (wrong, full, leave-one-out) of every valid result
    stats: dict[str, Counter] = {}
    examples = []
    t0 = time.perf_counter()
    for i in range(a.n):
        try:
            src, tgt, T, kind = case(rng)
        except GraffMatchError:  # the generator's own arguments rejected (e.g. no landmark)
            stats.setdefault("rejected-input", Counter())["inputs"] += 1
            continue
        c = stats.setdefault(kind, Counter())
        c["inputs"] += 1
        try:
            res = m.match(src, tgt)
        except GraffMatchError as exc:
            c[f"error:{type(exc).__name__}"] += 1
            continue
        if not res.valid:
            c["invalid"] += 1
            continue
        c["valid"] += 1
        wrong = T is None or any(e > lim for e, lim in zip(transform_errors(res.T_target_source, T), (5.0, 1.0),
                                                         strict=True))
        ti = next((h.info["translation_information"] for h in res.hypotheses
                   if "translation_information" in h.info), (np.nan, np.nan))
        information.append((bool(wrong), *ti))
        if wrong:
            c["valid_wrong"] += 1
            if len(examples) < 20:
                examples.append({"i": i, "kind": kind, "message": res.message, "confidence": res.confidence,
                                 "errors": None if T is None else transform_errors(res.T_target_source, T)})
        if (i + 1) % 1000 == 0:
            print(f"  {i + 1}/{a.n} in {time.perf_counter() - t0:.0f} s", flush=True)
    total = Counter()
    for c in stats.values():
        total.update(c)
    print(f"\n{'kind':<14}{'inputs':>8}{'valid':>8}{'invalid':>9}{'errors':>8}{'valid&wrong':>13}")
    for kind, c in [*sorted(stats.items()), ("ALL", total)]:
        err = sum(v for k, v in c.items() if k.startswith("error:"))
        print(f"{kind:<14}{c['inputs']:>8}{c['valid']:>8}{c['invalid']:>9}{err:>8}{c['valid_wrong']:>13}")
    rate = total["valid_wrong"] / max(total["valid"], 1)
    print(f"\nvalid-and-wrong: {total['valid_wrong']} of {total['valid']} valid ({100 * rate:.3f} %; target <= 0.1 %)"
          f" in {time.perf_counter() - t0:.0f} s")
    if a.json:
        Path(a.json).parent.mkdir(parents=True, exist_ok=True)
        thr = cfg.verification.min_translation_redundancy
        Path(a.json).write_text(json.dumps({
            "n": a.n, "seed": a.seed, "min_translation_redundancy": thr,
            "by_kind": {k: dict(v) for k, v in stats.items()}, "valid_wrong_rate": rate, "examples": examples,
            "translation_information_of_valid": sorted(information)}, indent=1, default=float))


if __name__ == "__main__":
    main()
