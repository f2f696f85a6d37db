"""A looser stopping rule on the first homotopy step only: does it save mat-vecs, and at what cost?

    python bench/first_step_tolerance.py [--seeds 24] [--json bench/results/first_step_tolerance.json]

The matcher's first homotopy step is the one ascent on the whole graph (~9 mat-vecs of ~1 ms at
W2). For each variant (tol_F, tol_u or the inner-iteration cap of that first ascent only; every
later step keeps the matcher's defaults) and W1 / W2 seeds 0..seeds-1, ``match()`` without
verification is compared with the default: on how many seeds the solver's selection differs,
the mean mat-vecs saved over the whole solve (negative: more), and on how many seeds the
returned transform's bytes differ (the registration weights are the solver's u). Counts only,
no timing. The first ascent is found by patching ``clipper._ascent_linear`` (the matcher's line
search) for the first call of each solve.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine, print_table, write_json

import graffmatch.association.clipper as cl
import graffmatch.matcher as gm
from graffmatch.datasets.landmark_scene import make_scene_pair
from graffmatch.verification.config import VerificationConfig

SIZES = {"W1": (15, 30), "W2": (30, 60)}
# (tol_u, tol_F, max_inner) of the first ascent; None keeps the default
VARIANTS: dict[str, tuple[float | None, float | None, int | None]] = {
    "tol_F 1e-3": (None, 1e-3, None), "tol_F 3e-3": (None, 3e-3, None), "tol_F 1e-2": (None, 1e-2, None),
    "tol_u 3e-3": (3e-3, None, None), "cap 6": (None, None, 6), "cap 4": (None, None, 4),
}


def _outputs(seeds: int, first: tuple | None) -> dict:
    """(selection, mat-vecs, transform bytes) of every case with ``first`` on the first ascent."""
    state = {"first": True}
    ascent, solve = cl._ascent_linear, gm.solve_clipper
    last: dict = {}

    def patched_ascent(indptr, indices, data, dense, u, rows, d, tol_u, tol_F, max_inner, *rest):
        if state["first"] and first is not None:
            tol_u, tol_F, max_inner = first[0] or tol_u, first[1] or tol_F, first[2] or max_inner
        state["first"] = False
        return ascent(indptr, indices, data, dense, u, rows, d, tol_u, tol_F, max_inner, *rest)

    def patched_solve(*a, **k):
        state["first"] = True
        last["s"] = solve(*a, **k)
        return last["s"]

    cl._ascent_linear, gm.solve_clipper = patched_ascent, patched_solve
    try:
        matcher = gm.GraffMatcher(gm.GraffMatchConfig(verification=VerificationConfig(enabled=False)))
        out = {}
        for wl, size in SIZES.items():
            for seed in range(seeds):
                sc = make_scene_pair(*size, seed=seed)
                r = matcher.match(sc.source, sc.target)
                s = last["s"]
                T = None if r.T_target_source is None else r.T_target_source.tobytes()
                out[(wl, seed)] = (s.selected.tolist(), s.matvecs, T)
        return out
    finally:
        cl._ascent_linear, gm.solve_clipper = ascent, solve


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=24)
    ap.add_argument("--json", default=None)
    a = ap.parse_args()
    base = _outputs(a.seeds, None)
    rows = []
    for name, first in VARIANTS.items():
        out = _outputs(a.seeds, first)
        for wl in SIZES:
            keys = [(wl, s) for s in range(a.seeds)]
            rows.append({
                "variant": name, "workload": wl, "seeds": a.seeds,
                "selection_differs_on_seeds": [k[1] for k in keys if out[k][0] != base[k][0]],
                "matvecs_saved_mean": round(float(np.mean([base[k][1] - out[k][1] for k in keys])), 2),
                "transforms_differ": sum(out[k][2] != base[k][2] for k in keys),
            })
    print_table(rows, ["variant", "workload", "seeds", "selection_differs_on_seeds", "matvecs_saved_mean",
                       "transforms_differ"])
    write_json(a.json, {"benchmark": "first_step_tolerance", "machine": machine(),
                        "default": "matcher's solver: tol_u 1e-3, tol_F 1e-4, max_inner_iterations 200",
                        "rows": rows})


if __name__ == "__main__":
    main()
