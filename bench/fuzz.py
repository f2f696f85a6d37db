"""Fuzz the public API with random and adversarial inputs; count what escapes.

Five kinds of input, each generated from its own reproducible seed (``--replay KIND:I`` re-runs
one input and shows its traceback):

* ``landmarks``  LandmarkSet / Landmark constructors, load() of corrupt files, then a few methods
* ``match``      GraffMatcher().match on random landmark sets (a fifth with ``associations=``,
                 many of them with bad indices; those are counted as their own kind ``match-assoc``)
* ``extract``    LandmarkExtractor().extract on random clouds (shapes, dtypes, NaN, degenerate,
                 far, tiny, centimetre integers) and labels
* ``read``       read_points / read_scan on random or mutated bytes, one fifth per suffix
* ``register``   register_scans on small random clouds (random boxes, rooms with poles)

An input is ``ok`` (finite result), a ``graffmatch`` error (by class), or ``foreign`` (any other
exception: a bug). Inputs that print to the C-level stderr (e.g. Qhull) and inputs slower than
``--slow`` seconds are counted too. Prints a table; ``--json`` writes it with the foreign cases.

    PYTHONPATH=. python bench/fuzz.py --n 10000 --json bench/results/fuzz.json
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
import traceback
import warnings
from collections import Counter
from collections.abc import Callable
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine, print_table, write_json

from graffmatch.errors import GraffMatchError

KINDS = ("landmarks", "match", "extract", "read", "register")
SUFFIXES = (".bin", ".pcd", ".ply", ".npy", ".npz")


# ----------------------------------------------------------------------------------------------
# value palettes
# ----------------------------------------------------------------------------------------------
def _floats(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    """Floats that are usually ordinary and sometimes the worst values there are."""
    x = rng.normal(scale=float(rng.choice([1e-9, 1e-3, 1.0, 20.0, 1e4, 1e7])), size=shape)
    if x.size and rng.random() < 0.35:
        special = np.array([np.nan, np.inf, -np.inf, 0.0, -0.0, 1e300, -1e300, 5e-324, 1e-310,
                            3.5e38, 1.0, 2.0**53])  # fmt: skip
        mask = rng.random(shape) < rng.choice([0.01, 0.2, 1.0])
        x[mask] = rng.choice(special, size=int(mask.sum()))
    if x.size and rng.random() < 0.1:
        x += rng.choice([4.6e6, 1e12, -1e5])  # far away
    return x


def _types(rng: np.random.Generator, n: int) -> object:
    r = rng.random()
    if r < 0.6:
        return rng.integers(0, 3, n)
    if r < 0.7:
        return rng.choice(["point", "line", "plane", "PLANE", " line "], n).tolist()
    palette: list[object] = [0, 1, 2, 1.0, 1.7, 2.2, 257, -1, 3, 2**70, True, "cylinder", None,
                             float("nan"), b"line", 1 + 1j, "2", [1]]  # fmt: skip
    return [palette[int(i)] for i in rng.integers(0, len(palette), n)]


def _maybe_bad_shape(rng: np.random.Generator, arr: np.ndarray) -> object:
    r = rng.random()
    if r < 0.8:
        return arr
    if r < 0.85:
        return arr.reshape(-1)
    if r < 0.9:
        return arr[: max(0, len(arr) - 1)]
    if r < 0.93:
        return arr.astype(str)
    if r < 0.96:
        return [np.atleast_1d(row).tolist()[: int(rng.integers(1, 4))] for row in arr]  # ragged
    return arr[..., :2] if arr.ndim > 1 else arr


# ----------------------------------------------------------------------------------------------
# landmarks
# ----------------------------------------------------------------------------------------------
def _random_set_args(rng: np.random.Generator, valid: bool) -> tuple:
    n = int(rng.integers(0, 10))
    if valid:
        types = rng.integers(0, 3, n)
        dirs = rng.normal(size=(n, 3))
        anchors = rng.uniform(-50, 50, (n, 3))
        if rng.random() < 0.2:
            anchors += rng.choice([4.6e6, 1e-6, 1e9])
        if rng.random() < 0.15:  # degenerate: all parallel
            dirs[:] = [0, 0, 1]
        if rng.random() < 0.1:  # duplicates
            anchors[:] = anchors[:1] if n else anchors
        return types, dirs, anchors
    return (_types(rng, n), _maybe_bad_shape(rng, _floats(rng, (n, 3))),
            _maybe_bad_shape(rng, _floats(rng, (n, 3))))  # fmt: skip


def _check_set(ls: object) -> None:
    from graffmatch.geometry.landmarks import LandmarkSet

    assert isinstance(ls, LandmarkSet), type(ls)
    assert ls.bases.shape == (len(ls), 3, 2) and ls.anchors.shape == (len(ls), 3)
    assert np.isfinite(ls.bases).all() and np.isfinite(ls.anchors).all(), "non-finite landmarks"
    assert set(np.unique(ls.types).tolist()) <= {0, 1, 2}


def gen_landmarks(rng: np.random.Generator) -> Callable[[], object]:
    from graffmatch.geometry.landmarks import Landmark, LandmarkSet
    from graffmatch.geometry.transforms import random_transform

    valid = rng.random() < 0.3
    types, dirs, anchors = _random_set_args(rng, valid)
    n = len(types) if hasattr(types, "__len__") else 0
    attrs: object = None
    r = rng.random()
    if r < 0.3:
        attrs = {"support": rng.integers(0, 100, n).astype(float), "rms": _floats(rng, (n,))}
    elif r < 0.4:
        attrs = {"bad": _floats(rng, (n + 1,))}
    elif r < 0.45:
        attrs = [1, 2, 3]
    points = offsets = None
    if rng.random() < 0.3:
        counts = rng.integers(0, 5, n)
        points = _floats(rng, (int(counts.sum()), 3)) if rng.random() < 0.5 else rng.normal(
            size=(int(counts.sum()), 3)
        )
        offsets = np.concatenate([[0], np.cumsum(counts)])
        if rng.random() < 0.3:
            offsets = _maybe_bad_shape(rng, offsets.astype(float) + rng.choice([0, 0.5, -3]))
    which = int(rng.integers(0, 7))

    def call() -> object:
        if which == 0:
            ls = LandmarkSet.from_arrays(types, dirs, anchors, attrs, points, offsets)
        elif which == 1:
            bases = _maybe_bad_shape(rng, _floats(rng, (n, 3, 2)))
            ls = LandmarkSet(types, bases, anchors, attrs, points, offsets)
        elif which == 2:
            j = int(rng.integers(0, 3))
            k = [Landmark.point, Landmark.line, Landmark.plane][j]
            args = [_floats(rng, (3,))] + ([] if j == 0 else [_floats(rng, (3,))])
            if j and rng.random() < 0.5:
                args[1] = rng.normal(size=3)  # a usable direction, so the anchor gets tested
            if rng.random() < 0.2:
                args[0] = args[0][:2]
            ls = LandmarkSet.from_landmarks([k(*args)])
        elif which == 3:
            kind = _types(rng, 1)
            kind = kind[0] if isinstance(kind, list) else int(np.asarray(kind)[0])
            ls = LandmarkSet.from_landmarks([Landmark(kind, _floats(rng, (3, 1)), _floats(rng, (3,)))])
        elif which == 4:
            a = LandmarkSet.from_arrays(*_random_set_args(rng, True))
            b = LandmarkSet.from_arrays(types, dirs, anchors)
            ls = LandmarkSet.concatenate([a, b])
        elif which == 5:
            good = LandmarkSet.from_arrays(*_random_set_args(rng, True))
            data = bytearray(good.to_bytes(include_points=False))
            for _ in range(int(rng.integers(0, 6))):
                if data:
                    data[int(rng.integers(0, len(data)))] = int(rng.integers(0, 256))
            if rng.random() < 0.3:
                data = data[: int(rng.integers(0, len(data) + 1))]
            with tempfile.TemporaryDirectory() as d:
                p = Path(d) / "lm.npz"
                p.write_bytes(bytes(data))
                ls = LandmarkSet.load(p)
        else:
            ls = LandmarkSet.from_arrays(types, dirs, anchors)
            ls = ls.transform(random_transform(rng))[rng.integers(0, max(1, len(ls)), 2) % max(1, len(ls))] if len(ls) else ls  # fmt: skip
        _check_set(ls)
        ls.cp_vectors()
        return ls

    return call


# ----------------------------------------------------------------------------------------------
# match
# ----------------------------------------------------------------------------------------------
def _valid_set(rng: np.random.Generator, n: int | None = None):
    from graffmatch.geometry.landmarks import LandmarkSet

    n = int(rng.integers(0, 14)) if n is None else n
    types = rng.integers(0, 3, n) if rng.random() < 0.7 else rng.integers(1, 3, n)
    dirs = rng.normal(size=(n, 3))
    anchors = rng.uniform(-40, 40, (n, 3))
    r = rng.random()
    if r < 0.1:
        dirs[:] = [0, 0, 1]  # all parallel
    elif r < 0.2:
        anchors[:] = 0.0  # all through one point
    elif r < 0.3:
        anchors += 4.6e6
    elif r < 0.35:
        anchors *= 1e-9
    elif r < 0.4:
        anchors *= 1e6
    return LandmarkSet.from_arrays(types, dirs, anchors)


def _bad_associations(rng: np.random.Generator, ns: int, nt: int) -> object:
    r = int(rng.integers(0, 9))
    return [
        [[0, 999]],
        [[-1, 0]],
        [[ns, 0]],
        [[0, nt + 5], [1, 1]],
        [[0.5, 1.0]],
        [["a", 0]],
        [0, 1, 2],
        np.zeros((0, 2)),
        [[2**40, 0]],
    ][r]


def gen_match(rng: np.random.Generator) -> tuple[str, Callable[[], object]]:
    from graffmatch.geometry.landmarks import LandmarkSet
    from graffmatch.geometry.transforms import random_transform
    from graffmatch.matcher import GraffMatcher, MatchResult

    src = _valid_set(rng)
    if rng.random() < 0.5 and len(src):
        tgt = src.transform(random_transform(rng, 20.0))
        if rng.random() < 0.5:
            tgt = LandmarkSet.concatenate([tgt, _valid_set(rng)])
    else:
        tgt = _valid_set(rng)
    kind = "match"
    assoc: object = None
    if rng.random() < 0.2:
        kind = "match-assoc"
        if rng.random() < 0.4 and len(src) and len(tgt):
            k = int(rng.integers(1, 6))
            assoc = np.c_[rng.integers(0, len(src), k), rng.integers(0, len(tgt), k)]
        else:
            assoc = _bad_associations(rng, len(src), len(tgt))

    def call() -> object:
        res = GraffMatcher().match(src, tgt, associations=assoc)
        assert isinstance(res, MatchResult)
        if res.T_target_source is not None:
            assert np.isfinite(res.T_target_source).all(), "non-finite transform"
        assert np.isfinite(res.score), "non-finite score"
        A = np.asarray(res.associations)
        if A.size:
            assert A[:, 0].max() < len(src) and A[:, 1].max() < len(tgt) and A.min() >= 0
        return res

    return kind, call


# ----------------------------------------------------------------------------------------------
# clouds: extract, register
# ----------------------------------------------------------------------------------------------
def _room(rng: np.random.Generator, n: int) -> np.ndarray:
    """Ground + up to 3 walls + up to 3 poles around the sensor, noisy; cheap and structured."""
    parts = [np.c_[rng.uniform(-25, 25, (n // 2, 2)), np.full(n // 2, -1.7)]]
    for _ in range(int(rng.integers(0, 4))):
        a, b = rng.uniform(-20, 20, 2), rng.uniform(-20, 20, 2)
        s = rng.random(n // 8)
        parts.append(np.c_[a + s[:, None] * (b - a), rng.uniform(-1.7, 3, n // 8)])
    for _ in range(int(rng.integers(0, 4))):
        c = rng.uniform(-15, 15, 2)
        m = n // 20
        parts.append(np.c_[c + rng.normal(scale=0.05, size=(m, 2)), rng.uniform(-1.7, 2.5, m)])
    P = np.concatenate(parts)
    return P + rng.normal(scale=rng.choice([0.0, 0.01, 0.05]), size=P.shape)


def _cloud(rng: np.random.Generator, valid_shape: bool = False) -> object:
    n = int(rng.choice([0, 1, 2, 3, 4, 10, 60, 300, 1500, 3000]))
    r = rng.random()
    t = np.linspace(0, 10, n)
    if r < 0.25:
        P = _room(rng, max(n, 8))
    elif r < 0.4:
        P = rng.normal(scale=rng.choice([1e-3, 1.0, 10.0]), size=(n, 3))
    elif r < 0.5:
        P = np.c_[t, np.zeros(n), np.zeros(n)] + rng.choice([0, 1e-6]) * rng.random((n, 3))
    elif r < 0.55:
        P = np.c_[rng.uniform(-20, 20, (n, 2)), np.zeros(n)]
    elif r < 0.6:
        P = np.tile(rng.normal(size=(1, 3)), (n, 1))
    elif r < 0.7:
        P = _room(rng, max(n, 8)) * rng.choice([100.0, 1000.0])  # cm / mm
        P = np.round(P).astype(rng.choice([np.int32, np.int64]))
    else:
        P = _floats(rng, (n, 3))
    if rng.random() < 0.3:
        P = np.c_[P, rng.random(len(P))]
    if rng.random() < 0.1 and len(P):
        P = np.asarray(P, dtype=float) + rng.choice([4.6e6, 1e12, 1e-12])
    if valid_shape:
        return np.asarray(P, dtype=np.float64)
    r = rng.random()
    if r < 0.05:
        return np.asarray(P).reshape(-1)
    if r < 0.08:
        return np.asarray(P)[:, :2]
    if r < 0.1:
        return np.asarray(P).astype(str)
    if r < 0.12:
        return np.asarray(P).astype(np.float32)
    if r < 0.14:
        return np.asarray(P) > 0
    return P


def _labels(rng: np.random.Generator, n: int) -> object:
    r = rng.random()
    if r < 0.7:
        return None
    if r < 0.85:
        return rng.choice(np.array([0, 40, 71, 80, 81, 80 | (3 << 16)], np.uint32), n)
    return [rng.integers(0, 100, n + 1), rng.normal(size=n), -np.ones(n, int), ["a"] * n][
        int(rng.integers(0, 4))
    ]


def gen_extract(rng: np.random.Generator) -> Callable[[], object]:
    from graffmatch.lidar.extractor import LandmarkExtractor

    P = _cloud(rng)
    n = len(P) if hasattr(P, "__len__") else 0
    labels = _labels(rng, n)

    def call() -> object:
        out = LandmarkExtractor().extract(P, labels)
        _check_set(out)
        return out

    return call


def gen_register(rng: np.random.Generator) -> Callable[[], object]:
    from graffmatch.geometry.transforms import random_transform, transform_points
    from graffmatch.pipeline import register_scans

    A = (_room(rng, int(rng.choice([1000, 3000, 6000]))) if rng.random() < 0.7
         else _cloud(rng, valid_shape=True))  # fmt: skip
    if rng.random() < 0.5 and len(A):
        B = transform_points(random_transform(rng, 5.0), A[:, :3])
        B = B + rng.normal(scale=0.02, size=B.shape)
    else:
        B = _room(rng, 3000) if rng.random() < 0.5 else _cloud(rng, valid_shape=True)

    def call() -> object:
        res = register_scans(A, B)
        if res.T_target_source is not None:
            assert np.isfinite(res.T_target_source).all(), "non-finite transform"
        return res

    return call


# ----------------------------------------------------------------------------------------------
# files
# ----------------------------------------------------------------------------------------------
def _valid_file_bytes(rng: np.random.Generator, suffix: str, d: Path) -> bytes:
    from graffmatch.lidar.io import write_pcd, write_ply

    n = int(rng.integers(0, 50))
    pts = _floats(rng, (n, 4)) if rng.random() < 0.5 else rng.normal(scale=20, size=(n, 4))
    p = d / f"v{suffix}"
    if suffix == ".bin":
        p.write_bytes(pts.astype("<f4" if rng.random() < 0.8 else "<f8").tobytes())
    elif suffix == ".pcd":
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            write_pcd(p, np.nan_to_num(pts.astype(np.float32)), binary=bool(rng.random() < 0.6))
    elif suffix == ".ply":
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            write_ply(p, np.nan_to_num(pts.astype(np.float32)), binary=bool(rng.random() < 0.6))
    elif suffix == ".npy":
        dt = rng.choice(["<f4", "<f8", "<f8", "<i4", "<u2", "|b1", "<c8", "<U3"])
        shape = [(n, 3), (n, 4), (n, 4), (n,), (n, 2), (2, n, 3)][int(rng.integers(0, 6))]
        np.save(p, np.resize(pts, shape).astype(dt) if dt != "<U3" else np.full(shape, "ab"))
    else:
        keys = rng.choice(["points", "a", "b", "xyz"], int(rng.integers(1, 3)), replace=False)
        np.savez(p, **{str(k): np.resize(pts, (n, 3)) for k in keys})
    return p.read_bytes()


def gen_read(rng: np.random.Generator, suffix: str) -> Callable[[], object]:
    from graffmatch.lidar.io import read_points, read_scan

    d = Path(tempfile.mkdtemp(prefix="gmfuzz"))
    r = rng.random()
    if r < 0.3:
        size = int(rng.choice([0, 1, 15, 16, 64, 160, 1600, 16000]))
        data = rng.bytes(size)
    elif r < 0.4:
        data = "\n".join(f"{x:.3f} {y:.3f} {z:.3f} 0.5"
                         for x, y, z in rng.normal(scale=20, size=(int(rng.integers(1, 200)), 3))).encode()  # fmt: skip
        if rng.random() < 0.5:
            data = data[: len(data) // 16 * 16]
    else:
        data = bytearray(_valid_file_bytes(rng, suffix, d))
        for _ in range(int(rng.choice([0, 1, 3, 20]))):
            if data:
                data[int(rng.integers(0, len(data)))] = int(rng.integers(0, 256))
        if rng.random() < 0.3:
            data = data[: int(rng.integers(0, len(data) + 1))]
        if rng.random() < 0.1:
            data = bytes(data).replace(b"POINTS", b"POINTS 99999999999999999999 ", 1)
        data = bytes(data)
    path = d / f"scan{suffix}"
    path.write_bytes(data)
    use_scan = rng.random() < 0.5
    scale: object = [1.0, 0.01, "mm", 0, -1, "furlong", float("nan")][int(rng.integers(0, 7))]
    scale = 1.0 if rng.random() < 0.7 else scale

    def call() -> object:
        try:
            if use_scan:
                s = read_scan(path, scale=scale)
                out = s.points
                assert s.origin.shape == (3,) and np.isfinite(s.origin).all()
            else:
                out = read_points(path, scale=scale)
            assert out.dtype == np.float32 and out.ndim == 2 and out.shape[1] == 4
            return out
        finally:
            path.unlink(missing_ok=True)
            for f in d.iterdir():
                f.unlink()
            d.rmdir()

    return call


# ----------------------------------------------------------------------------------------------
# runner
# ----------------------------------------------------------------------------------------------
def make_input(kind: str, seed: int, i: int) -> tuple[str, Callable[[], object]]:
    """The i-th input of a kind: (label it is counted under, the call)."""
    rng = np.random.default_rng([seed, KINDS.index(kind), i])
    if kind == "landmarks":
        return kind, gen_landmarks(rng)
    if kind == "match":
        return gen_match(rng)
    if kind == "extract":
        return kind, gen_extract(rng)
    if kind == "register":
        return kind, gen_register(rng)
    suffix = SUFFIXES[i % len(SUFFIXES)]
    return f"read{suffix}", gen_read(rng, suffix)


class _StderrWatch:
    """Redirect the C-level stderr to a file so that Qhull-like chatter can be counted."""

    def __enter__(self) -> _StderrWatch:
        sys.stderr.flush()
        self.saved = os.dup(2)
        self.file = tempfile.TemporaryFile()
        os.dup2(self.file.fileno(), 2)
        return self

    def size(self) -> int:
        return os.fstat(self.file.fileno()).st_size

    def text(self, start: int) -> str:
        self.file.seek(start)
        return self.file.read(400).decode(errors="replace")

    def __exit__(self, *exc: object) -> None:
        sys.stderr.flush()
        os.dup2(self.saved, 2)
        os.close(self.saved)
        self.file.close()


def run(kinds: list[str], n: dict[str, int], seed: int, slow: float, quiet: bool) -> dict:
    stats: dict[str, dict] = {}
    foreign: list[dict] = []
    warnings.simplefilter("ignore")
    with _StderrWatch() as err:
        for kind in kinds:
            t_kind = time.perf_counter()
            for i in range(n[kind]):
                label, call = make_input(kind, seed, i)
                st = stats.setdefault(label, {"inputs": 0, "ok": 0, "errors": Counter(),
                                              "foreign": 0, "stderr": 0, "slow": 0, "max_s": 0.0,
                                              "total_s": 0.0})  # fmt: skip
                st["inputs"] += 1
                before = err.size()
                t = time.perf_counter()
                try:
                    call()
                    st["ok"] += 1
                except GraffMatchError as exc:
                    st["errors"][type(exc).__name__] += 1
                except BaseException as exc:  # counting every escape is the point
                    if isinstance(exc, KeyboardInterrupt):
                        raise
                    st["foreign"] += 1
                    if sum(f["label"] == label for f in foreign) < 20:
                        foreign.append({"label": label, "kind": kind, "i": i,
                                        "type": type(exc).__name__, "message": str(exc)[:300],
                                        "where": traceback.format_exc().splitlines()[-3][:200]})  # fmt: skip
                dt = time.perf_counter() - t
                st["max_s"] = max(st["max_s"], dt)
                st["total_s"] += dt
                if dt > slow:
                    st["slow"] += 1
                    foreign.append({"label": label, "kind": kind, "i": i, "type": "slow",
                                    "message": f"{dt:.1f} s", "where": ""})  # fmt: skip
                if err.size() > before:
                    st["stderr"] += 1
                    if st["stderr"] <= 3:
                        foreign.append({"label": label, "kind": kind, "i": i, "type": "stderr",
                                        "message": err.text(before)[:300], "where": ""})  # fmt: skip
            if not quiet:
                print(f"{kind}: {n[kind]} inputs in {time.perf_counter() - t_kind:.1f} s",
                      file=sys.__stdout__, flush=True)  # fmt: skip
    return {"stats": stats, "foreign": foreign}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=10000, help="inputs per kind")
    ap.add_argument("--n-register", type=int, default=None, help="inputs for 'register' (default --n)")
    ap.add_argument("--kinds", default=",".join(KINDS), help=f"comma-separated subset of {KINDS}")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--slow", type=float, default=10.0, help="an input slower than this [s] counts as slow")
    ap.add_argument("--json", default=None, help="write the counts and foreign cases here")
    ap.add_argument("--replay", default=None, help="KIND:I - run one input and show its traceback")
    ap.add_argument("--quiet", action="store_true")
    args = ap.parse_args()
    if args.replay:
        kind, i = args.replay.split(":")
        label, call = make_input(kind, args.seed, int(i))
        print(f"replaying {label} #{i}")
        print(call())
        return
    kinds = [k.strip() for k in args.kinds.split(",") if k.strip()]
    for k in kinds:
        if k not in KINDS:
            ap.error(f"unknown kind {k!r}; known: {', '.join(KINDS)}")
    n = {k: args.n for k in kinds}
    if "register" in n and args.n_register is not None:
        n["register"] = args.n_register
    t0 = time.perf_counter()
    out = run(kinds, n, args.seed, args.slow, args.quiet)
    rows = []
    for label, st in sorted(out["stats"].items()):
        rows.append({"input": label, "inputs": st["inputs"], "ok": st["ok"],
                     "graffmatch_errors": sum(st["errors"].values()),
                     "by_class": ", ".join(f"{k} {v}" for k, v in sorted(st["errors"].items())),
                     "foreign": st["foreign"], "stderr": st["stderr"], "slow": st["slow"],
                     "max_s": f"{st['max_s']:.2f}", "total_s": f"{st['total_s']:.0f}"})  # fmt: skip
    total = {"input": "TOTAL", **{c: sum(r[c] for r in rows) for c in
                                  ("inputs", "ok", "graffmatch_errors", "foreign", "stderr", "slow")}}  # fmt: skip
    print_table([*rows, total], ["input", "inputs", "ok", "graffmatch_errors", "by_class", "foreign",
                                 "stderr", "slow", "max_s", "total_s"])  # fmt: skip
    for f in out["foreign"]:
        print(f"  {f['type']} in {f['label']} #{f['i']} (replay: --replay {f['kind']}:{f['i']}"
              f"{'' if args.seed == 0 else f' --seed {args.seed}'}): {f['message'][:160]!r} {f['where']}")  # fmt: skip
    write_json(args.json, {
        "command": " ".join(sys.argv), "seed": args.seed, "n": n, "machine": machine(),
        "wall_s": time.perf_counter() - t0,
        "stats": {k: {**v, "errors": dict(v["errors"])} for k, v in out["stats"].items()},
        "foreign": out["foreign"],
    })  # fmt: skip


if __name__ == "__main__":
    main()
