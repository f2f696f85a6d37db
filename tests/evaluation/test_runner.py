"""The study runner: records, resumability after a killed worker or driver, Dask == local.

The pairs are synthetic (a random line/plane scene seen from two poses) and the methods are
scripted, picklable objects, so these tests do not depend on the dataset builder or on the
speed of the real methods; the evaluation itself (d_Graff inlier test, errors) is the real one.
"""

from __future__ import annotations

import json
import os
import sys
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from graffmatch.errors import InvalidInputError
from graffmatch.evaluation.executors import (
    ExecutorUnavailableError,
    LocalProcessExecutor,
    SerialExecutor,
    WorkerLostError,
    make_executor,
)
from graffmatch.evaluation.runner import (
    GT_METHOD,
    StudyConfig,
    compare_runs,
    format_comparison,
    load_records,
    parse_method_spec,
    record_path,
    record_without_timings,
    run_study,
)
from graffmatch.geometry.landmarks import LandmarkSet, LandmarkType
from graffmatch.geometry.transforms import invert, make_transform, rot_z

# ----------------------------------------------------------------------------------------------
# synthetic pairs and scripted methods (also used by test_report.py)
# ----------------------------------------------------------------------------------------------


@dataclass
class SynthPair:
    pair_id: str
    source: LandmarkSet
    target: LandmarkSet
    T_target_source: np.ndarray
    true_matches: np.ndarray
    case: int
    iir: float
    distance: float


def _scene(rng: np.random.Generator, n_lines: int, n_planes: int) -> LandmarkSet:
    n = n_lines + n_planes
    types = np.array([LandmarkType.LINE] * n_lines + [LandmarkType.PLANE] * n_planes)
    dirs = np.zeros((n, 3))
    dirs[:n_lines] = [0.0, 0.0, 1.0] + 0.05 * rng.normal(size=(n_lines, 3))  # poles
    dirs[n_lines:] = rng.normal(size=(n_planes, 3))
    anchors = np.column_stack(
        [rng.uniform(-30, 30, n), rng.uniform(-30, 30, n), rng.uniform(0, 4, n)]
    )
    return LandmarkSet.from_arrays(types, dirs, anchors)


def make_pairs(n: int, seed: int = 0, prefix: str = "p") -> list[SynthPair]:
    """n pairs; case cycles 1, 2, 3. Source landmarks are the target's, permuted."""
    rng = np.random.default_rng(seed)
    pairs = []
    for k in range(n):
        target = _scene(rng, 5, 7)
        T = make_transform(rot_z(rng.uniform(-np.pi, np.pi)), rng.uniform(-8, 8, 3) * [1, 1, 0.1])
        perm = rng.permutation(len(target))
        source = target.transform(invert(T))[perm]
        matches = np.column_stack([np.arange(len(target)), perm])
        possible = 5 * 5 + 7 * 7
        pairs.append(
            SynthPair(
                pair_id=f"{prefix}{k:03d}",
                source=source,
                target=target,
                T_target_source=T,
                true_matches=matches,
                case=k % 3 + 1,
                iir=len(matches) / possible,
                distance=float(np.linalg.norm(T[:3, 3])),
            )
        )
    return pairs


@dataclass
class Scripted:
    """A deterministic fake method with a known quality.

    Returns all true matches plus ``n_wrong`` wrong same-type associations, and the ground truth
    perturbed by ``rot_deg`` about z and ``trans_m`` along x; in ``fail_cases`` the estimate is
    30 deg / 10 m off. ``kill_on``: pair id on which a *worker* process dies (os._exit).
    """

    name: str = "Scripted"
    kind: str = "landmark"
    n_wrong: int = 2
    rot_deg: float = 0.5
    trans_m: float = 0.1
    fail_cases: tuple[int, ...] = ()
    kill_on: str | None = None
    bad_index: bool = False
    driver_pid: int = field(default_factory=os.getpid)

    def __call__(self, pair: SynthPair) -> SimpleNamespace:
        if self.kill_on == pair.pair_id and os.getpid() != self.driver_pid:
            os._exit(17)  # a worker killed mid-run
        m = np.asarray(pair.true_matches)
        # a wrong association pairs source i with the target partner of another source landmark
        # of the same type (deterministic: the next one in the list)
        wrong = []
        for a in range(min(self.n_wrong, len(m))):
            t = pair.source.types[m[a, 0]]
            same = [b for b in range(len(m)) if b != a and pair.source.types[m[b, 0]] == t]
            wrong.append([m[a, 0], m[same[0], 1]])
        assoc = np.vstack([m, np.asarray(wrong, dtype=int).reshape(-1, 2)])
        if self.bad_index:
            assoc[0, 1] = len(pair.target) + 5  # a buggy method: index out of range
        rot, trans = (30.0, 10.0) if pair.case in self.fail_cases else (self.rot_deg, self.trans_m)
        D = make_transform(rot_z(np.radians(rot)), [trans, 0.0, 0.0])
        h = zlib.crc32(f"{self.name}{pair.T_target_source[0, 3]:.9f}".encode()) % 1000
        return SimpleNamespace(
            T_target_source=pair.T_target_source @ D,
            associations=assoc,
            timings={"search": 1e-3 * (1 + h / 1000), "total": 2e-3 * (1 + h / 1000)},
            valid=True,
            info={"hash": h},
        )


def comparable(out_dir: Path) -> list[dict]:
    return [record_without_timings(r) for r in load_records(out_dir)]


# ----------------------------------------------------------------------------------------------
# tests
# ----------------------------------------------------------------------------------------------
def test_records_hold_the_evaluation(tmp_path: Path) -> None:
    pairs = make_pairs(3)
    out = run_study(
        {"synth": pairs},
        [Scripted(n_wrong=3, rot_deg=2.0, trans_m=0.5, fail_cases=(3,))],
        tmp_path / "r",
        executor="serial",
        progress=False,
    )
    recs = {(r["method"], r["pair_id"]): r for r in load_records(out)}
    assert {m for m, _ in recs} == {GT_METHOD, "Scripted"}
    for p in pairs:
        r = recs[("Scripted", p.pair_id)]
        k = len(p.true_matches)
        assert r["n_associations"] == k + 3
        # exactly the true matches are inliers (d_Graff ~ 0 after GT alignment)
        assert r["inlier_mask"] == [True] * k + [False] * 3
        assert r["oir"] == pytest.approx(k / (k + 3))
        if p.case == 3:
            assert r["rotation_error_deg"] == pytest.approx(30.0, abs=1e-6)
            assert not r["success"]
        else:
            assert r["rotation_error_deg"] == pytest.approx(2.0, abs=1e-6)
            assert r["translation_error_m"] == pytest.approx(0.5, abs=1e-6)
            assert r["success"]
        assert r["case"] == p.case and r["suite"] == "synth"
        assert r["timings"]["total"] > 0
    # the exact config is written next to the results
    cfg = json.loads((out / "config.json").read_text())
    assert cfg["study"]["methods"] == [GT_METHOD, "Scripted"]
    assert cfg["study"]["tau_d_deg"] == 6.0
    assert (out / "pairs" / "synth.json").is_file() and (out / "stats" / "synth.json").is_file()
    stats = json.loads((out / "stats" / "synth.json").read_text())
    assert stats["n_distances"] == 2 * 3 * (12 * 11 // 2)  # source + target of 3 pairs


def test_gt_matches_method_registers_exactly(tmp_path: Path) -> None:
    out = run_study({"s": make_pairs(2)}, [], tmp_path, executor="serial", progress=False)
    for r in load_records(out):
        assert r["method"] == GT_METHOD
        assert r["status"] == "ok", r["error"]
        # arccos near 1 resolves angles to ~2.6e-6 deg: one last-bit difference in R shows up there
        assert r["success"] and r["rotation_error_deg"] < 1e-5 and r["translation_error_m"] < 1e-6
        assert r["oir"] == 1.0


def test_resume_after_worker_kill_driver_kill_and_deleted_records(tmp_path: Path) -> None:
    pairs = make_pairs(6)
    cfg = StudyConfig(rho_values=[])
    ref = run_study(
        {"s": pairs}, [Scripted()], tmp_path / "ref", executor="serial", progress=False, config=cfg
    )
    expected = comparable(ref)
    assert len(expected) == 12

    # 1) a worker process dies on pair p003: finished records survive, the run raises
    run = tmp_path / "run"
    killer = Scripted(kill_on="p003")
    with pytest.raises(WorkerLostError):
        run_study(
            {"s": pairs},
            [killer],
            run,
            executor=LocalProcessExecutor(workers=2, max_in_flight=2),
            progress=False,
            config=cfg,
        )
    assert not record_path(run, "s", "Scripted", "p003").exists()
    n_after_kill = len(load_records(run))
    assert 0 < n_after_kill < 12
    # (the pool notices the dead worker with a delay, so how many others finished varies; make
    # sure the driver-kill step below has work left)
    for m in (GT_METHOD, "Scripted"):
        record_path(run, "s", m, "p000").unlink(missing_ok=True)
    n_after_kill = len(load_records(run))
    assert n_after_kill <= 9

    # 2) the driver dies (an exception in the driver loop) after two more records
    seen: list[str] = []

    def die_after_two(doc: dict) -> None:
        seen.append(doc["pair_id"])
        if len(seen) == 2:
            raise KeyboardInterrupt("driver killed")

    with pytest.raises(KeyboardInterrupt):
        run_study(
            {"s": pairs},
            [Scripted()],
            run,
            executor="serial",
            progress=False,
            config=cfg,
            on_record=die_after_two,
        )
    assert len(load_records(run)) == n_after_kill + 2

    # 3) some finished records are deleted; a stale temp file lies around
    record_path(run, "s", "Scripted", "p000").unlink(missing_ok=True)
    record_path(run, "s", GT_METHOD, "p005").unlink(missing_ok=True)
    (run / "records" / "s" / "Scripted" / ".p001.json.junk.tmp").write_text("{")

    # rerun: completes, computes only what is missing, identical to the clean run
    written: list[str] = []
    run_study(
        {"s": pairs},
        [Scripted()],
        run,
        executor="local",
        workers=2,
        progress=False,
        config=cfg,
        on_record=lambda d: written.append(d["pair_id"]),
    )
    assert comparable(run) == expected
    assert 2 <= len(written) < 12
    # a further rerun has nothing to do
    again: list[str] = []
    run_study(
        {"s": pairs},
        [Scripted()],
        run,
        executor="serial",
        progress=False,
        config=cfg,
        on_record=lambda d: again.append(d["pair_id"]),
    )
    assert again == []
    runs = [json.loads(x) for x in (run / "runs.jsonl").read_text().splitlines()]
    assert [r["complete"] for r in runs] == [False, False, True, True]
    assert runs[-1]["skipped_existing"] == 12


def test_dask_local_cluster_matches_local_run(tmp_path: Path) -> None:
    distributed = pytest.importorskip("distributed")
    from graffmatch.evaluation.executors import DaskExecutor

    pairs = make_pairs(4, seed=3)
    methods = [Scripted(n_wrong=1), Scripted(name="Other", n_wrong=4, fail_cases=(2,))]
    cfg = StudyConfig(rho_values=[])
    local = run_study(
        {"s": pairs},
        methods,
        tmp_path / "local",
        executor="local",
        workers=2,
        progress=False,
        config=cfg,
    )
    with (
        distributed.LocalCluster(
            n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None
        ) as cluster,
        distributed.Client(cluster) as client,
    ):
        ex = DaskExecutor(client=client)
        dask_dir = run_study(
            {"s": pairs}, methods, tmp_path / "dask", executor=ex, progress=False, config=cfg
        )
        # the tasks really ran on the cluster's worker processes
        assert len(client.nthreads()) == 2
    assert len(comparable(local)) == 12
    assert comparable(dask_dir) == comparable(local)
    assert json.loads((dask_dir / "config.json").read_text())["executor"] == "dask"


def test_method_errors_are_recorded_and_retried_on_request(tmp_path: Path) -> None:
    pairs = make_pairs(2)
    cfg = StudyConfig(rho_values=[])
    out = run_study(
        {"s": pairs},
        ["GraffMatch[rho=oops]"],
        tmp_path,
        executor="serial",
        progress=False,
        config=cfg,
    )
    recs = [r for r in load_records(out) if r["method"] != GT_METHOD]
    assert len(recs) == 2
    assert all(r["status"] == "error" and not r["success"] and r["oir"] == 0.0 for r in recs)
    assert all(r["error"] for r in recs)
    n = []
    run_study(
        {"s": pairs},
        ["GraffMatch[rho=oops]"],
        out,
        executor="serial",
        progress=False,
        config=cfg.model_copy(update={"retry_errors": True}),
        on_record=lambda d: n.append(1),
    )
    assert len(n) == 2  # only the failed ones were retried (GT records were fine)


def test_quick_subset_and_rho_study_selection(tmp_path: Path) -> None:
    pairs = make_pairs(15)  # 5 per case
    cfg = StudyConfig(max_pairs_per_case=2, rho_values=[10.0, 40.0], rho_pairs_per_suite=3)

    class _Stop(Exception):
        pass

    # Only the task list matters here: record what would run, without running GraffMatch.
    with pytest.raises(_Stop):

        def stop(doc: dict) -> None:
            raise _Stop

        run_study(
            {"s": pairs},
            [Scripted(name="GraffMatch")],
            tmp_path,
            executor="serial",
            progress=False,
            config=cfg,
            on_record=stop,
        )
    chosen = json.loads((tmp_path / "pairs" / "s.json").read_text())
    assert [c["case"] for c in chosen] == [1, 1, 2, 2, 3, 3]
    # evenly spaced within each case: first and last pair of the case
    assert [c["pair_id"] for c in chosen[:2]] == ["p000", "p012"]
    cfg_doc = json.loads((tmp_path / "config.json").read_text())
    assert cfg_doc["rho_study"]["specs"] == ["GraffMatch[rho=10]", "GraffMatch[rho=40]"]


def test_method_specs_and_bad_input(tmp_path: Path) -> None:
    assert parse_method_spec("GraffMatch[rho=20, variant=naive]") == (
        "GraffMatch",
        {"rho": 20, "variant": "naive"},
    )
    assert parse_method_spec("CLIPPER-Rn") == ("CLIPPER-Rn", {})
    with pytest.raises(InvalidInputError):
        parse_method_spec("GraffMatch[rho]")
    with pytest.raises(InvalidInputError):
        run_study({"s": make_pairs(1)}, ["NoSuchMethod"], tmp_path, progress=False)
    with pytest.raises(InvalidInputError):
        run_study([tmp_path / "missing"], [], tmp_path / "o", progress=False)
    with pytest.raises(InvalidInputError):
        make_executor("spark")
    with pytest.raises(InvalidInputError):
        make_executor("local", address="tcp://x:1")


def test_ray_adapter_reports_missing_ray(monkeypatch: pytest.MonkeyPatch) -> None:
    """Ray is an extra (make test installs it): hide it to see the message a user without it gets."""
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray -> ImportError
    with pytest.raises(ExecutorUnavailableError, match="pip install"):
        make_executor("ray")


def _square(x: int) -> int:
    return x * x


def test_executors_yield_every_result_once() -> None:
    for ex in (SerialExecutor(), LocalProcessExecutor(workers=2, max_in_flight=3)):
        with ex:
            got = dict(ex.imap_unordered(_square, range(20)))
        assert got == {i: i * i for i in range(20)}


def test_compare_runs(tmp_path: Path) -> None:
    pairs = make_pairs(6)
    cfg = StudyConfig(rho_values=[])
    a = run_study({"s": pairs}, [Scripted()], tmp_path / "a", "serial", progress=False, config=cfg)
    b = run_study(
        {"s": pairs},
        [Scripted(fail_cases=(1,))],
        tmp_path / "b",
        "serial",
        progress=False,
        config=cfg,
    )
    rows = compare_runs(a, b)
    by = {(r["case"], r["method"]): r for r in rows}
    assert by[(1, "Scripted")]["recall_delta"] == pytest.approx(-1.0)
    assert by[(2, "Scripted")]["recall_delta"] == 0.0
    assert by[("all", "Scripted")]["recall_delta"] == pytest.approx(-1 / 3)
    assert by[(1, "Scripted")]["n"] == 2
    assert "Δrecall" in format_comparison(rows)
    same = compare_runs(a, a)
    assert all(r["recall_delta"] == 0.0 and r["auc_delta"] == 0.0 for r in same)


def test_changed_pairs_are_recomputed_and_stale_records_not_reported(tmp_path: Path) -> None:
    cfg = StudyConfig(rho_values=[])
    pairs = make_pairs(3)
    out = run_study({"s": pairs}, [Scripted()], tmp_path, "serial", progress=False, config=cfg)
    # the dataset is rebuilt: same ids, but pair p001 now has other landmarks and case
    rebuilt = make_pairs(3)
    rebuilt[1] = make_pairs(2, seed=99)[1]
    rebuilt[1].pair_id, rebuilt[1].case = "p001", 3
    redone: list[str] = []
    run_study(
        {"s": rebuilt[:2]},
        [Scripted()],
        out,
        "serial",
        progress=False,
        config=cfg,
        on_record=lambda d: redone.append(d["pair_id"]),
    )
    assert redone == ["p001", "p001"]  # GT-matches and Scripted, only for the changed pair
    recs = load_records(out)
    # p002 is no longer selected: its records stay on disk but are not reported
    assert sorted({r["pair_id"] for r in recs}) == ["p000", "p001"]
    assert len(load_records(out, current_only=False)) == 6
    assert {r["case"] for r in recs if r["pair_id"] == "p001"} == {3}


def test_malformed_output_is_an_error_record_and_config_has_method_params(tmp_path: Path) -> None:
    cfg = StudyConfig(rho_values=[])
    out = run_study(
        {"s": make_pairs(2)},
        [Scripted(name="Buggy", bad_index=True), "CPMatch", "GraffMatch[epsilon=0.3]"],
        tmp_path,
        "serial",
        progress=False,
        config=cfg,
    )
    bad = [r for r in load_records(out) if r["method"] == "Buggy"]
    assert len(bad) == 2
    assert all(r["status"] == "error" and "out of range" in r["error"] for r in bad)
    assert all(r["n_associations"] == 0 and not r["success"] for r in bad)
    params = json.loads((out / "config.json").read_text())["method_params"]
    assert params["Buggy"]["bad_index"] is True
    assert params["CPMatch"]["max_cp_distance"] > 0
    assert params["GraffMatch[epsilon=0.3]"]["epsilon"] == 0.3
    assert params["GraffMatch[epsilon=0.3]"]["rho"] == 40.0
    ok = [r for r in load_records(out) if r["method"] in ("CPMatch", "GraffMatch[epsilon=0.3]")]
    assert len(ok) == 4 and all(r["status"] == "ok" for r in ok)


def write_dataset_folder(root: Path, pairs: list[SynthPair]) -> Path:
    """A loop-closure dataset folder in the builder's format (pairs.json + landmark files)."""
    from graffmatch.evaluation import loop_closures as lc

    (root / lc.LANDMARK_DIR).mkdir(parents=True, exist_ok=True)
    places, docs = [], []
    for k, p in enumerate(pairs):
        for scan, ls in ((2 * k, p.source), (2 * k + 1, p.target)):
            rel = f"{lc.LANDMARK_DIR}/{scan:06d}.npz"
            ls.save(root / rel)
            places.append({"scan": scan, "scan_path": str(root / f"{scan}.bin"), "landmarks": rel})
        docs.append(
            {
                "source_scan": 2 * k,
                "target_scan": 2 * k + 1,
                "T_target_source": p.T_target_source.tolist(),
                "true_matches": p.true_matches.tolist(),
                "n_possible": 74,
                "iir": p.iir,
                "case": p.case,
                "distance": p.distance,
                "rotation_deg": 0.0,
                "n_true_lines": 5,
                "n_true_planes": 7,
            }
        )
    doc = {
        "format": lc.FORMAT_NAME,
        "version": lc.FORMAT_VERSION,
        "config": lc.LoopClosureConfig().model_dump(mode="json"),
        "places": places,
        "pairs": docs,
    }
    (root / lc.PAIRS_FILE).write_text(json.dumps(doc))
    return root


def test_dataset_folders_are_loaded_by_the_workers(tmp_path: Path, monkeypatch) -> None:
    pairs = make_pairs(4, seed=5)
    folder = write_dataset_folder(tmp_path / "data" / "synth-suite", pairs)
    # the compact landmark file is not bit-exact: compare with the pairs as stored
    for k, p in enumerate(pairs):
        p.source = LandmarkSet.load(folder / "landmarks" / f"{2 * k:06d}.npz")
        p.target = LandmarkSet.load(folder / "landmarks" / f"{2 * k + 1:06d}.npz")
    cfg = StudyConfig(rho_values=[])
    mem = run_study(
        {"synth-suite": pairs}, [Scripted()], tmp_path / "mem", "serial", progress=False, config=cfg
    )
    disk = run_study(
        [folder], [Scripted()], tmp_path / "disk", "local", workers=2, progress=False, config=cfg
    )
    # same numbers whether the pairs travel in the task or are read from disk by the workers
    # (the ids differ: the dataset names pairs by scan indices)
    strip = [{k: v for k, v in r.items() if k != "pair_id"} for r in comparable(mem)]
    got = [{k: v for k, v in r.items() if k != "pair_id"} for r in comparable(disk)]
    key = lambda r: (r["method"], r["T_target_source_gt"])  # noqa: E731
    assert sorted(got, key=key) == sorted(strip, key=key)
    cfg_doc = json.loads((disk / "config.json").read_text())
    assert cfg_doc["suites"]["synth-suite"] == str(folder.resolve())

    # run_benchmark glue: build (stubbed: the folder exists), study, report
    from graffmatch.evaluation import benchmark, suites

    def fake_build(name, out_root, quick=False, data_root=None, progress=True):
        assert Path(out_root) == tmp_path / "data" and name == "synth-suite" and not quick
        return {"n_valid": len(pairs), "cases": {"1": {"pairs": 2}}}

    monkeypatch.setattr(suites, "build_suite", fake_build)
    out = benchmark.run_benchmark(
        ["synth-suite"],
        tmp_path / "bench",
        executor="serial",
        methods=["CPMatch"],
        data_dir=tmp_path / "data",
        progress=False,
    )
    log = json.loads((out / "benchmark.json").read_text())
    assert log["build"]["synth-suite"]["pairs"] == 4 and log["study_s"] > 0
    t1 = json.loads((out / "report" / "table1.json").read_text())
    assert t1["methods"] == ["CPMatch"]
    assert {r["case"] for r in t1["rows"]} == {1, 2, 3, "all"}
