"""Bit-level equality of the matcher's graph, solver and match() outputs between two code versions.

    python bench/selection_equality.py --save /tmp/eq_before.pkl      # on the old code
    python bench/selection_equality.py --compare /tmp/eq_before.pkl   # on the new code
    [--workloads REF,KITTI,W1,W2,W3] [--seeds 16]

For each case (the 4 reference graphs of ../shared/bench/clipper_graphs under the matcher's and
the paper's solver configs; KITTI 0->5 as in bench_matcher.py; W1/W2 seeds 0..seeds-1; W3 seeds
0-1) it records, for ``match()`` without verification: a hash of the consistency graph's CSR
arrays, the solver's selection, a hash of its u, score, mat-vecs, greedy work and which clique
won, and match()'s associations, transform bytes and valid flag. ``--compare`` prints every
field that differs. A change meant to be pure speed shows 0 differences; one that only rounds
differently shows which fields moved (u, score) and whether the selections stayed. Counts only,
no timing (runs anywhere, at any load).
"""

from __future__ import annotations

import argparse
import hashlib
import pickle
import sys
from pathlib import Path

import numpy as np
import scipy.sparse as sp

sys.path.insert(0, str(Path(__file__).resolve().parent))

import graffmatch.matcher as gm
from graffmatch.association.clipper import ClipperConfig, solve_clipper
from graffmatch.datasets.landmark_scene import make_scene_pair
from graffmatch.verification.config import VerificationConfig

GRAPHS = Path(__file__).resolve().parents[2] / "shared" / "bench" / "clipper_graphs"
WORKLOADS = {"W1": (15, 30), "W2": (30, 60), "W3": (60, 120)}


def _hash(*arrays: np.ndarray) -> str:
    h = hashlib.sha1()
    for a in arrays:
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()[:16]


def record(workloads: list[str], seeds: int) -> dict:
    """The outputs of every case, keyed by case."""
    out: dict = {}
    captured: list = []

    def spy(W, cfg=None, u0=None):
        s = solve_clipper(W, cfg, u0)
        captured.append((W, s))
        return s

    gm.solve_clipper = spy
    matcher = gm.GraffMatcher(gm.GraffMatchConfig(verification=VerificationConfig(enabled=False)))

    def match(key, sc) -> None:
        captured.clear()
        r = matcher.match(sc.source, sc.target)
        W, s = captured[0]
        out[key] = dict(graph=_hash(W.indptr, W.indices, W.data), selected=s.selected.tolist(), u=_hash(s.u),
                        score=s.score, matvecs=s.matvecs, chosen=s.info.get("chosen"),
                        greedy_work=s.info.get("greedy_work"), associations=r.associations.tolist(),
                        T=None if r.T_target_source is None else r.T_target_source.tobytes(), valid=r.valid)

    try:
        for wl in workloads:
            if wl == "REF":
                for f in sorted(GRAPHS.glob("*.npz")):
                    z = np.load(f)
                    W = sp.csr_matrix((z["M_data"], z["M_indices"], z["M_indptr"]),
                                      shape=tuple(z["M_shape"])).astype(np.float32)
                    for label, cfg in (("matcher", gm.GraffMatchConfig().solver), ("paper", ClipperConfig())):
                        s = solve_clipper(W, cfg)
                        out[(f.name, label)] = dict(selected=s.selected.tolist(), u=_hash(s.u), score=s.score,
                                                    matvecs=s.matvecs, chosen=s.info.get("chosen"))
            elif wl == "KITTI":
                from bench_matcher import kitti_case

                match("KITTI", kitti_case())
            else:
                for seed in range(2 if wl == "W3" else seeds):
                    match((wl, seed), make_scene_pair(*WORKLOADS[wl], seed=seed))
            print(wl, "done", flush=True)
    finally:
        gm.solve_clipper = solve_clipper
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--save", default=None, help="write the outputs to this file")
    ap.add_argument("--compare", default=None, help="compare the outputs with this saved file")
    ap.add_argument("--workloads", default="REF,KITTI,W1,W2,W3")
    ap.add_argument("--seeds", type=int, default=16)
    a = ap.parse_args()
    if (a.save is None) == (a.compare is None):
        ap.error("give one of --save, --compare")
    out = record(a.workloads.split(","), a.seeds)
    if a.save:
        Path(a.save).write_bytes(pickle.dumps(out))
        print(f"saved {len(out)} cases to {a.save}")
        return
    ref = pickle.loads(Path(a.compare).read_bytes())
    n_diff = n_sel = 0
    for key, v in out.items():
        r = ref.get(key)
        if r is None:
            print("not in the saved file:", key)
            continue
        diff = [f for f in v if v[f] != r.get(f)]
        if diff:
            n_diff += 1
            n_sel += v["selected"] != r["selected"]
            print("differs:", key, diff, "(same selection)" if v["selected"] == r["selected"] else "(OTHER SELECTION)")
    print(f"compared {len(out)} cases: {n_diff} differ, {n_sel} of them in the selection")


if __name__ == "__main__":
    main()
