"""``graffmatch``: global landmark matching and registration from the terminal.

Every command follows the same habits: results on stdout, progress (with an ETA) and errors on
stderr, errors as ONE line with a non-zero exit code (a traceback only with ``-v``), output
folders named by time with the exact configuration saved next to the results.
"""

from __future__ import annotations

import json
import time
from datetime import datetime, timezone
from enum import Enum
from importlib.metadata import PackageNotFoundError
from importlib.metadata import version as _pkg_version
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import typer
from rich.table import Table

from graffmatch.cli.common import (
    EXIT_NOT_VALID,
    STATE,
    cli_errors,
    debug,
    err,
    info,
    make_progress,
    out,
    reset_state,
    run_dir,
    stage,
    write_config_next_to,
)
from graffmatch.errors import GraffMatchError, InvalidInputError, MalformedFileError

try:
    __version__ = _pkg_version("graffmatch")
except PackageNotFoundError:  # running from a source tree without installation
    __version__ = "0.0.0+unknown"

EPILOG_MAIN = """\
[bold]Examples[/bold]

  graffmatch demo
  graffmatch extract data/kitti00/velodyne/000000.bin -o lm/
  graffmatch register scan0.bin scan5.bin --gt gt.txt --view match.html
  graffmatch register lm/000000.npz lm/000005.npz --refine icp -o result.json
  graffmatch view runs/2026-11-21_14-03-12_register/result.json -o match.html
  graffmatch config dump > my.yaml && graffmatch --config my.yaml register a.bin b.bin
  GRAFFMATCH_MATCHER__RHO=20 graffmatch register a.npz b.npz

[bold]Exit codes[/bold]: 0 ok, 1 error (one line on stderr), 2 bad usage,
3 the command ran but its result is not valid (no registration, demo bounds missed).
"""

app = typer.Typer(
    name="graffmatch",
    help="Global LiDAR landmark matching and registration on the affine Grassmannian (GraffMatch).",
    epilog=EPILOG_MAIN,
    rich_markup_mode="rich",
    no_args_is_help=True,
    add_completion=False,
    context_settings={"help_option_names": ["-h", "--help"]},
    pretty_exceptions_show_locals=False,
)
config_app = typer.Typer(help="Show or check the whole configuration (YAML).", no_args_is_help=True)
app.add_typer(config_app, name="config")


def _version_callback(value: bool) -> None:
    if value:
        out.print(f"graffmatch {__version__}")
        raise typer.Exit()


@app.callback()
def main(
    version: Annotated[
        bool,
        typer.Option(
            "--version", callback=_version_callback, is_eager=True, help="Print the version."
        ),
    ] = False,
    verbose: Annotated[
        int,
        typer.Option("--verbose", "-v", count=True, help="More output; -v also shows tracebacks."),
    ] = 0,
    quiet: Annotated[
        bool, typer.Option("--quiet", "-q", help="Only results and errors; no progress.")
    ] = False,
    runs_dir: Annotated[
        Path,
        typer.Option(
            "--runs-dir",
            help="Where commands without -o create their time-named output folders.",
            envvar="GRAFFMATCH_RUNS_DIR",
        ),
    ] = Path("runs"),
    config: Annotated[
        Path | None,
        typer.Option(
            "--config",
            "-c",
            help="YAML configuration (see 'graffmatch config dump'); env GRAFFMATCH_<SECTION>__"
            "<FIELD> overrides it.",
            envvar="GRAFFMATCH_CONFIG",
        ),
    ] = None,
) -> None:
    """Global LiDAR landmark matching and registration (GraffMatch)."""
    if verbose and quiet:
        raise typer.BadParameter("use either --verbose or --quiet")
    reset_state(-1 if quiet else verbose, config, runs_dir)


# ----------------------------------------------------------------------------------------------
# helpers shared by commands
# ----------------------------------------------------------------------------------------------
#: Tables print at most this many rows unless -v (the JSON files hold everything).
MAX_TABLE_ROWS = 40


def _fmt_ms(seconds: float) -> str:
    return f"{1e3 * seconds:.1f} ms"


def _jsonable(x: Any) -> Any:
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, np.generic):
        return _jsonable(x.item())
    if isinstance(x, float) and not np.isfinite(x):
        return None
    if isinstance(x, Path):
        return str(x)
    return x


def _write_json(path: Path, data: dict) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(_jsonable(data), indent=2) + "\n")
    return path


def _extractor():
    from graffmatch.lidar.extractor import LandmarkExtractor

    return LandmarkExtractor(STATE.settings.extractor)


def _load_input(path: Path, labels: Path | None, extractor_holder: list) -> Any:
    """A scan (extracted now) or a landmark file, as a LoadedInput."""
    from graffmatch.cli.inputs import LoadedInput, find_labels, is_landmark_file, read_scan
    from graffmatch.geometry.landmarks import LandmarkSet

    if not path.exists():
        raise MalformedFileError(f"{path}: input not found")
    if path.is_dir():
        raise MalformedFileError(f"{path}: input is a folder; give one scan or one landmark file")
    if is_landmark_file(path):
        return LoadedInput(path, "landmarks", LandmarkSet.load(path))
    label_path = find_labels(path, labels, STATE.settings.input.labels)
    pts, lab = read_scan(path, label_path)
    if not extractor_holder:
        extractor_holder.append(_extractor())
    ex = extractor_holder[0]
    t0 = time.perf_counter()
    ls = ex.extract(pts, lab)
    timings = dict(ex.last_timings)
    timings.setdefault("total", time.perf_counter() - t0)
    return LoadedInput(path, "scan", ls, pts, label_path, timings)


def _counts_text(ls) -> str:
    c = ls.counts()
    parts = [f"{c['lines']} poles", f"{c['planes']} planes"]
    if c["points"]:
        parts.append(f"{c['points']} points")
    return ", ".join(parts)


# ----------------------------------------------------------------------------------------------
# demo
# ----------------------------------------------------------------------------------------------
@app.command(
    epilog="[bold]Examples[/bold]\n\n  graffmatch demo\n\n  graffmatch demo --seed 3 "
    "--mode landmarks",
)
@cli_errors
def demo(
    seed: Annotated[int, typer.Option(help="Seed of the scene and the transform.")] = 0,
    mode: Annotated[
        str,
        typer.Option(
            help="'lidar': simulated street scans -> extraction -> match; 'landmarks': "
            "landmark sets directly; 'auto': lidar."
        ),
    ] = "auto",
) -> None:
    """Run the built-in demo: match two views 180° and 14 m apart, print errors and timings.

    Exits with code 3 when the recovered transform misses the demo's bounds.
    """
    from graffmatch.demo import run_demo

    t0 = time.perf_counter()
    with err.status("running the demo ...", spinner="dots") if not STATE.quiet else _null():
        report = run_demo(seed=seed, mode=mode, config=STATE.settings.matcher)
    debug(f"demo finished in {time.perf_counter() - t0:.2f} s")
    out.print(report)
    if not report.passed:
        err.print("[bold red]demo:[/bold red] the recovered transform misses its bounds")
        raise typer.Exit(EXIT_NOT_VALID)


class _null:
    """No spinner under -q (rich's status would still draw on stderr)."""

    def __enter__(self) -> None:
        return None

    def __exit__(self, *exc: object) -> None:
        return None


# ----------------------------------------------------------------------------------------------
# extract
# ----------------------------------------------------------------------------------------------
@app.command(
    epilog="[bold]Examples[/bold]\n\n  graffmatch extract scan.bin -o scan.npz\n\n"
    "  graffmatch extract kitti00/ --labels kitti00/labels -o landmarks/\n\n"
    "  graffmatch extract kitti00/velodyne   (writes runs/<time>_extract/)",
)
@cli_errors
def extract(
    scan: Annotated[Path, typer.Argument(help="A scan file (.bin/.pcd/.ply/.npy) or a folder.")],
    labels: Annotated[
        Path | None,
        typer.Option(
            "--labels", "-l", help="SemanticKITTI .label file, or a folder of them (folder input)."
        ),
    ] = None,
    output: Annotated[
        Path | None,
        typer.Option(
            "--output",
            "-o",
            help="Output .npz (one scan) or folder; default runs/<time>_extract/.",
        ),
    ] = None,
    with_points: Annotated[
        bool,
        typer.Option(
            "--with-points/--no-points",
            help="Also store the landmarks' support points (needed by --refine icp).",
        ),
    ] = False,
) -> None:
    """Extract pole (line) and plane landmarks from scans into compact .npz landmark files."""
    from graffmatch.cli.inputs import find_labels, list_scans, read_scan

    if not scan.exists():
        raise MalformedFileError(f"{scan}: scan not found")
    scans = list_scans(scan) if scan.is_dir() else [scan]
    if labels is not None and len(scans) > 1 and not labels.is_dir():
        raise InvalidInputError(f"{labels}: with a folder of scans, --labels must be a folder")
    single_file = len(scans) == 1 and output is not None and output.suffix.lower() == ".npz"
    if single_file:
        out_dir = output.parent if output.parent != Path("") else Path(".")
        out_dir.mkdir(parents=True, exist_ok=True)
    elif output is not None:
        out_dir = output
        out_dir.mkdir(parents=True, exist_ok=True)
    else:
        out_dir = run_dir(STATE.runs_dir, "extract")
    ex = _extractor()
    rows = []
    with make_progress() as progress:
        task = progress.add_task("extracting", total=len(scans))
        for path in scans:
            progress.update(task, description=f"extracting {path.name}")
            label_path = find_labels(path, labels, STATE.settings.input.labels)
            pts, lab = read_scan(path, label_path)
            t0 = time.perf_counter()
            ls = ex.extract(pts, lab)
            dt = time.perf_counter() - t0
            target = output if single_file else out_dir / f"{path.stem}.npz"
            ls.save(target, include_points=with_points)
            c = ls.counts()
            rows.append(
                {
                    "scan": str(path),
                    "labels": None if label_path is None else str(label_path),
                    "landmarks": str(target),
                    "n_points": len(pts),
                    "poles": c["lines"],
                    "planes": c["planes"],
                    "seconds": dt,
                    "bytes": target.stat().st_size,
                    "timings": dict(ex.last_timings),
                }
            )
            progress.advance(task)
    if single_file:
        _write_config_beside(output)
    else:
        write_config_next_to(out_dir)
    summary_path = (out_dir / "summary.json") if not single_file else output.with_suffix(".json")
    _write_json(summary_path, {"created": _now(), "scans": rows})
    table = Table(title=None, show_edge=False, header_style="bold")
    for col in ("scan", "points", "poles", "planes", "time", "file"):
        table.add_column(col, justify="left" if col in ("scan", "file") else "right")
    shown = rows if STATE.verbosity > 0 else rows[:MAX_TABLE_ROWS]
    for r in shown:
        table.add_row(
            Path(r["scan"]).name,
            f"{r['n_points']:,}",
            str(r["poles"]),
            str(r["planes"]),
            _fmt_ms(r["seconds"]),
            f"{r['bytes'] / 1024:.1f} kB",
        )
    if not STATE.quiet:
        out.print(table)
        if len(shown) < len(rows):
            out.print(f"... {len(rows) - len(shown)} more scan(s) in {summary_path} (-v: all)")
    tot = sum(r["seconds"] for r in rows)
    info(
        f"{len(rows)} scan(s): {sum(r['poles'] for r in rows)} poles, "
        f"{sum(r['planes'] for r in rows)} planes in {tot:.2f} s "
        f"({_fmt_ms(tot / max(len(rows), 1))}/scan) -> {out_dir if not single_file else output}"
    )


def _now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


# ----------------------------------------------------------------------------------------------
# register
# ----------------------------------------------------------------------------------------------
class PoseFormatChoice(str, Enum):
    kitti = "kitti"
    tum = "tum"


class RefineChoice(str, Enum):
    none = "none"
    icp = "icp"


@app.command(
    epilog="[bold]Examples[/bold]\n\n"
    "  graffmatch register kitti/velodyne/000000.bin kitti/velodyne/000005.bin\n\n"
    "  graffmatch register a.npz b.npz --gt T_b_a.txt --view match.html\n\n"
    "  graffmatch register seq/velodyne/000000.bin seq/velodyne/000005.bin --gt auto\n\n"
    "  graffmatch register a.bin b.bin --refine icp --pose-format kitti --pose-out T.txt\n\n"
    "Exit code 3 when no valid registration was found.",
)
@cli_errors
def register(
    source: Annotated[Path, typer.Argument(help="Source scan or landmark file (.npz).")],
    target: Annotated[Path, typer.Argument(help="Target scan or landmark file (.npz).")],
    gt: Annotated[
        str | None,
        typer.Option(
            help="Ground-truth T_target_source: a text file with a 4x4 or 3x4 matrix, the "
            "12/16 numbers inline, or 'auto' (from the poses of the KITTI-layout folder of "
            "both scans)."
        ),
    ] = None,
    output: Annotated[
        Path | None,
        typer.Option(
            "--output", "-o", help="Result JSON; default runs/<time>_register/result.json."
        ),
    ] = None,
    pose_format: Annotated[
        PoseFormatChoice | None,
        typer.Option(help="Also write T_target_source as a KITTI or TUM pose line."),
    ] = None,
    pose_out: Annotated[
        Path | None, typer.Option(help="Pose file (default: next to the result JSON).")
    ] = None,
    refine: Annotated[
        RefineChoice,
        typer.Option(help="Refine with ICP on the matched landmarks' support points."),
    ] = RefineChoice.none,
    view: Annotated[
        Path | None, typer.Option(help="Write the interactive 3D view (one HTML file).")
    ] = None,
    source_labels: Annotated[
        Path | None, typer.Option(help="SemanticKITTI labels of the source scan.")
    ] = None,
    target_labels: Annotated[
        Path | None, typer.Option(help="SemanticKITTI labels of the target scan.")
    ] = None,
) -> None:
    """Register SOURCE to TARGET: print T_target_source, inliers, score, κ and validity."""
    from graffmatch.cli.inputs import gt_from_dataset, path_record, read_transform, write_pose_file

    # Check the cheap things first: a typo must not cost an extraction.
    if gt == "auto":
        T_gt = gt_from_dataset(source, target)
    else:
        T_gt = read_transform(gt) if gt is not None else None
    for p in (source, target):
        if not p.exists():
            raise MalformedFileError(f"{p}: input not found")
    settings = STATE.settings
    if pose_out is not None and pose_format is None:
        pose_format = PoseFormatChoice.kitti if pose_out.suffix != ".tum" else PoseFormatChoice.tum
    holder: list = []
    steps = 3 + (refine == RefineChoice.icp)
    with make_progress() as progress:
        task = progress.add_task("registering", total=steps)
        with stage(progress, task, f"reading {source.name}"):
            src = _load_input(source, source_labels, holder)
        with stage(progress, task, f"reading {target.name}"):
            tgt = _load_input(target, target_labels, holder)
        with stage(progress, task, "matching"):
            from graffmatch.matcher import GraffMatcher

            result = GraffMatcher(settings.matcher).match(src.landmarks, tgt.landmarks)
        T_matcher = result.T_target_source
        T_est = None if T_matcher is None else np.asarray(T_matcher, float)
        assoc = np.asarray(result.associations, dtype=np.int64).reshape(-1, 2)
        refine_info = None
        if refine == RefineChoice.icp and T_est is not None:
            with stage(progress, task, "ICP refinement"):
                refine_info = _refine_icp(src.landmarks, tgt.landmarks, assoc, T_est, result)
                T_est = refine_info["T_target_source"]

    if output is None:
        folder = run_dir(STATE.runs_dir, "register")
        result_path = folder / "result.json"
    else:
        result_path = output
        folder = output.parent if str(output.parent) else Path(".")
        folder.mkdir(parents=True, exist_ok=True)
    # Landmark files next to the result so that `graffmatch view` can redraw it later.
    lm_paths = {}
    for name, item in (("source", src), ("target", tgt)):
        if item.kind == "landmarks":
            lm_paths[name] = item.path
        else:
            lm_paths[name] = item.landmarks.save(
                folder / f"{result_path.stem}_{name}_landmarks.npz", include_points=True
            )
    gt_info = None
    inlier_mask = None
    if T_gt is not None:
        gt_info, inlier_mask = _ground_truth_report(
            src.landmarks, tgt.landmarks, assoc, T_est, T_gt
        )
    valid = bool(result.valid)
    data = {
        "format": "graffmatch-register-result",
        "version": 1,
        "created": _now(),
        "graffmatch_version": __version__,
        "inputs": {
            "source": {**path_record(src.path, folder), "kind": src.kind},
            "target": {**path_record(tgt.path, folder), "kind": tgt.kind},
            "source_labels": path_record(src.labels_path, folder),
            "target_labels": path_record(tgt.labels_path, folder),
        },
        "landmarks": {k: path_record(v, folder) for k, v in lm_paths.items()},
        "counts": {"source": src.landmarks.counts(), "target": tgt.landmarks.counts()},
        "T_target_source": T_est,
        "T_target_source_matcher": T_matcher,
        "associations": assoc,
        "weights": np.asarray(result.weights, float),
        "score": float(result.score),
        "kappa": float(result.kappa),
        "degenerate": bool(result.degenerate),
        "valid": valid,
        "message": str(result.message),
        "n_putative": int(result.n_putative),
        "n_edges": int(result.n_edges),
        "timings": {
            "match": dict(result.timings),
            "extract_source": src.timings,
            "extract_target": tgt.timings,
        },
        "refine": refine_info,
        "ground_truth": gt_info,
        "config": STATE.settings.model_dump(mode="json"),
    }
    _write_json(result_path, data)
    if output is None:
        write_config_next_to(folder)
    else:
        _write_config_beside(result_path)
    pose_written = None
    if pose_format is not None and T_est is not None:
        suffix = ".kitti.txt" if pose_format == PoseFormatChoice.kitti else ".tum.txt"
        pose_written = write_pose_file(
            pose_out or result_path.with_suffix(suffix), T_est, pose_format.value
        )
    view_written = None
    if view is not None:
        from graffmatch.viz.match_view import write_match_view

        view_written = write_match_view(
            view,
            src.landmarks,
            tgt.landmarks,
            np.eye(4) if T_est is None else T_est,
            assoc,
            source_points=src.points,
            target_points=tgt.points,
            inlier_mask=inlier_mask,
            title=f"GraffMatch: {src.path.name} → {tgt.path.name}",
            info=_view_info(data),
            max_points=settings.view.max_points,
            initial=settings.view.initial,
        )
    _print_register(data, src, tgt, result_path, pose_written, view_written)
    if not valid:
        raise typer.Exit(EXIT_NOT_VALID)


def _write_config_beside(result_path: Path) -> Path:
    from graffmatch.cli.settings import save_settings

    return save_settings(STATE.settings, result_path.with_name(result_path.stem + ".config.yaml"))


def _view_info(data: dict) -> dict[str, str]:
    d = {
        "associations": str(len(data["associations"])),
        "score": f"{data['score']:.2f}" if data["score"] is not None else "-",
        "κ": f"{data['kappa']:.3g}" if data["kappa"] is not None else "-",
        "valid": "yes" if data["valid"] else "no",
    }
    gt = data.get("ground_truth")
    if gt:
        d["inliers"] = f"{gt['n_inliers']}/{len(data['associations'])}"
        d["error"] = f"{gt['rotation_error_deg']:.2f}° / {gt['translation_error_m']:.2f} m"
    return d


def _refine_icp(src, tgt, assoc: np.ndarray, T_init: np.ndarray, result) -> dict:
    """ICP on the support points of the matched landmarks only (the paper's GraffMatch+ICP).

    Like :func:`graffmatch.register_scans`, it uses the associations the registration kept
    (``result.info['registration_inliers']``) when the matcher reports them.
    """
    from graffmatch.registration.icp import matched_support_points, refine_icp

    keep = result.info.get("registration_inliers")
    used = assoc if keep is None else assoc[np.asarray(keep)]
    if len(used) == 0:
        raise InvalidInputError("--refine icp: the matcher selected no associations to refine")
    for name, ls in (("source", src), ("target", tgt)):
        if ls.points is None:
            raise InvalidInputError(
                f"--refine icp needs the {name} landmarks' support points: pass the scan, or "
                "extract with --with-points"
            )
    ps, pt = matched_support_points(src, tgt, used)
    if len(ps) < 3 or len(pt) < 3:
        raise InvalidInputError("--refine icp: the matched landmarks carry too few support points")
    icp = STATE.settings.icp
    T, fitness, rmse = refine_icp(
        ps,
        pt,
        T_init,
        max_correspondence_distance=icp.max_correspondence_distance,
        max_iterations=icp.max_iterations,
        point_to_plane=icp.point_to_plane,
        normal_radius=icp.normal_radius,
    )
    return {
        "method": "icp",
        "T_target_source": np.asarray(T, float),
        "T_init": T_init,
        "fitness": float(fitness),
        "inlier_rmse": float(rmse),
        "n_associations": len(used),
        "n_source_points": len(ps),
        "n_target_points": len(pt),
    }


def _ground_truth_report(src, tgt, assoc, T_est, T_gt) -> tuple[dict, np.ndarray]:
    from graffmatch.evaluation.metrics import association_distances_deg
    from graffmatch.geometry.transforms import transform_errors

    cfg = STATE.settings.ground_truth
    if T_est is None:  # no estimate: the pair fails, as in the evaluation
        rot, trans = float("inf"), float("inf")
    else:
        rot, trans = transform_errors(T_est, T_gt)
    d = association_distances_deg(src, tgt, assoc, T_gt) if len(assoc) else np.zeros(0)
    mask = d < cfg.tau_d_deg
    return (
        {
            "T_target_source": T_gt,
            "rotation_error_deg": float(rot),
            "translation_error_m": float(trans),
            "success": bool(rot <= cfg.max_rotation_deg and trans <= cfg.max_translation_m),
            "tau_d_deg": cfg.tau_d_deg,
            "association_distance_deg": d,
            "inlier_mask": mask,
            "n_inliers": int(mask.sum()),
        },
        mask,
    )


def _print_register(data, src, tgt, result_path, pose_written, view_written) -> None:
    if STATE.quiet:
        T = data["T_target_source"]
        out.print("none" if T is None else " ".join(f"{v:.9g}" for v in np.asarray(T)[:3].ravel()))
        return
    names = {0: "point", 1: "pole", 2: "plane"}
    out.print(
        f"[bold]source[/bold] {src.path.name} ({src.kind}): {_counts_text(src.landmarks)}   "
        f"[bold]target[/bold] {tgt.path.name} ({tgt.kind}): {_counts_text(tgt.landmarks)}"
    )
    assoc = np.asarray(data["associations"]).reshape(-1, 2)
    gt = data["ground_truth"]
    if len(assoc):
        table = Table(show_edge=False, header_style="bold", title="selected associations")
        for col in ("#", "source", "target", "type", "weight"):
            table.add_column(col, justify="right")
        if gt:
            table.add_column("d_Graff (GT)", justify="right")
            table.add_column("inlier", justify="center")
        w = np.asarray(data["weights"], float)
        n_rows = len(assoc) if STATE.verbosity > 0 else min(len(assoc), MAX_TABLE_ROWS)
        for k, (i, j) in enumerate(assoc[:n_rows]):
            row = [
                str(k),
                str(i),
                str(j),
                names.get(int(src.landmarks.types[i]), "?"),
                f"{w[k]:.3f}" if k < len(w) else "-",
            ]
            if gt:
                dk = gt["association_distance_deg"][k]
                ok = gt["inlier_mask"][k]
                row += [f"{dk:.2f}°", "[green]✓[/green]" if ok else "[red]✗[/red]"]
            table.add_row(*row)
        out.print(table)
        if n_rows < len(assoc):
            out.print(f"... {len(assoc) - n_rows} more association(s) in the result JSON (-v: all)")
    if data["T_target_source"] is None:
        out.print("[bold]T_target_source[/bold]: none (no estimate)")
    else:
        out.print("[bold]T_target_source[/bold]")
        for r in np.asarray(data["T_target_source"]):
            out.print("  " + " ".join(f"{v:+10.5f}" for v in r))
    verdict = "[green]valid[/green]" if data["valid"] else "[red]NOT valid[/red]"
    out.print(
        f"associations {len(assoc)}  score {data['score']:.3f}  κ {data['kappa']:.3g}  "
        f"degenerate {data['degenerate']}  {verdict}"
        + (f"  ({data['message']})" if data["message"] else "")
    )
    if data["refine"]:
        r = data["refine"]
        out.print(
            f"ICP on {r['n_source_points']}/{r['n_target_points']} landmark points: "
            f"fitness {r['fitness']:.3f}, inlier RMSE {r['inlier_rmse']:.3f} m"
        )
    if gt:
        ok = "[green]success[/green]" if gt["success"] else "[red]failure[/red]"
        out.print(
            f"vs ground truth: rotation error {gt['rotation_error_deg']:.3f}°, translation error "
            f"{gt['translation_error_m']:.3f} m ({ok}); inliers {gt['n_inliers']}/{len(assoc)} "
            f"at τ_d={gt['tau_d_deg']:g}°"
        )
    tm = data["timings"]["match"]
    if tm:
        out.print("timings: " + ", ".join(f"{k} {_fmt_ms(v)}" for k, v in tm.items()))
    out.print(f"result: {result_path}")
    if pose_written:
        out.print(f"pose: {pose_written}")
    if view_written:
        out.print(f"view: {view_written}")


# ----------------------------------------------------------------------------------------------
# view
# ----------------------------------------------------------------------------------------------
@app.command(
    epilog="[bold]Example[/bold]\n\n  graffmatch view runs/2026-11-21_14-03-12_register/"
    "result.json -o match.html",
)
@cli_errors
def view(
    result: Annotated[Path, typer.Argument(help="result.json written by 'graffmatch register'.")],
    output: Annotated[
        Path | None, typer.Option("--output", "-o", help="HTML file (default: next to result).")
    ] = None,
    no_points: Annotated[
        bool, typer.Option("--no-points", help="Do not re-read the scans; landmarks only.")
    ] = False,
    png: Annotated[
        Path | None,
        typer.Option(help="Also write a static bird's-eye PNG (matplotlib, for reports)."),
    ] = None,
    screenshot: Annotated[
        Path | None,
        typer.Option(help="Also screenshot the 3D view to this PNG (needs chromium)."),
    ] = None,
) -> None:
    """Write the interactive 3D view of a saved registration result (one HTML file).

    Example: graffmatch view result.json -o match.html --png match_topdown.png
    """
    from graffmatch.cli.inputs import is_landmark_file, load_result, read_scan, resolve_path_record
    from graffmatch.geometry.landmarks import LandmarkSet
    from graffmatch.viz.match_view import write_match_view

    data = load_result(result)
    base = result.parent
    lms = {}
    for name in ("source", "target"):
        p = resolve_path_record(data["landmarks"][name], base)
        if p is None or not p.exists():
            raise MalformedFileError(f"{result}: landmark file of the {name} is missing ({p})")
        lms[name] = LandmarkSet.load(p)
    points: dict[str, Any] = {"source": None, "target": None}
    if not no_points:
        for name in ("source", "target"):
            rec = data["inputs"][name]
            p = resolve_path_record(rec, base)
            if (
                rec.get("kind") == "scan"
                and p is not None
                and p.exists()
                and not is_landmark_file(p)
            ):
                points[name] = read_scan(p)[0]
            elif rec.get("kind") == "scan":
                err.print(f"[yellow]warning[/yellow]: scan {p} not found; drawing landmarks only")
    gt = data.get("ground_truth")
    mask = None if not gt else np.asarray(gt["inlier_mask"], bool)
    out_path = output or result.with_suffix(".html")
    T = np.eye(4) if data["T_target_source"] is None else np.asarray(data["T_target_source"])
    assoc = np.asarray(data["associations"], np.int64).reshape(-1, 2)
    written = write_match_view(
        out_path,
        lms["source"],
        lms["target"],
        T,
        assoc,
        source_points=points["source"],
        target_points=points["target"],
        inlier_mask=mask,
        title=f"GraffMatch: {Path(data['inputs']['source']['absolute']).name} → "
        f"{Path(data['inputs']['target']['absolute']).name}",
        info=_view_info(data),
        max_points=STATE.settings.view.max_points,
        initial=STATE.settings.view.initial,
    )
    info(f"view: {written}")
    if png is not None:
        from graffmatch.viz.plots import plot_match_topdown

        plot_match_topdown(
            lms["source"],
            lms["target"],
            T,
            assoc,
            points["source"],
            points["target"],
            mask,
            side_by_side=STATE.settings.view.initial == "side",
            path=png,
            max_points=STATE.settings.view.max_points,
        )
        info(f"png: {png}")
    if screenshot is not None:
        from graffmatch.viz.browser import render_html

        shot = render_html(written, screenshot=screenshot)
        if not shot.rendered or shot.errors:
            raise GraffMatchError(f"{written}: the browser did not render the view {shot.errors}")
        info(f"screenshot: {screenshot}")


# ----------------------------------------------------------------------------------------------
# config
# ----------------------------------------------------------------------------------------------
@config_app.command("dump")
@cli_errors
def config_dump(
    output: Annotated[
        Path | None, typer.Option("--output", "-o", help="Write to this file, not stdout.")
    ] = None,
) -> None:
    """Print the whole configuration (defaults + --config + environment) as commented YAML.

    Example: graffmatch config dump > my.yaml ; graffmatch --config my.yaml register a.bin b.bin
    """
    from graffmatch.cli.settings import dump_settings, missing_sections, save_settings

    for name in missing_sections():
        err.print(f"[yellow]warning[/yellow]: section {name!r} unavailable (module not importable)")
    if output is not None:
        save_settings(STATE.settings, output)
        info(f"configuration: {output}")
    else:
        # Plain print: YAML must not be wrapped or styled by rich.
        typer.echo(dump_settings(STATE.settings), nl=False)


@config_app.command("check")
@cli_errors
def config_check(
    file: Annotated[Path, typer.Argument(help="YAML configuration to validate.")],
) -> None:
    """Validate a YAML configuration file (exit code 1 with the first problems if invalid)."""
    from graffmatch.cli.settings import load_settings

    load_settings(file)
    info(f"{file}: valid")


# ----------------------------------------------------------------------------------------------
# wrappers over the datasets / evaluation / calibration layers
# ----------------------------------------------------------------------------------------------
class SensorChoice(str, Enum):
    hdl64 = "hdl64"
    vlp16 = "vlp16"
    os1_64 = "os1-64"


@app.command(
    epilog="[bold]Examples[/bold]\n\n  graffmatch simulate sim/ --style downtown --seed 0\n\n"
    "  graffmatch simulate sim/ --style suburban --scans 40 --sensor vlp16",
)
@cli_errors
def simulate(
    output: Annotated[Path, typer.Argument(help="Output KITTI-layout folder.")],
    style: Annotated[
        str, typer.Option(help="World style: downtown, suburban or open-road.")
    ] = "downtown",
    seed: Annotated[int, typer.Option(help="Seed of the world and the trajectory.")] = 0,
    scans: Annotated[
        int | None, typer.Option(min=1, help="Number of scans, ~1 m apart (default: 200).")
    ] = None,
    sensor: Annotated[SensorChoice, typer.Option(help="LiDAR profile.")] = SensorChoice.hdl64,
    overwrite: Annotated[
        bool, typer.Option(help="Replace the files of a non-empty output folder.")
    ] = False,
    reuse: Annotated[
        bool, typer.Option(help="Keep a folder that already holds this exact simulation.")
    ] = False,
) -> None:
    """Simulate a LiDAR drive through a procedural city; writes a KITTI-layout dataset.

    velodyne/*.bin, labels/*.label (SemanticKITTI classes), poses.txt (camera-0), calib.txt
    and the ground-truth landmarks; same seed -> identical bytes.
    """
    from graffmatch.datasets.simulator import STYLES, simulate_dataset

    if style not in STYLES:
        raise InvalidInputError(f"unknown style {style!r}; choose one of {', '.join(STYLES)}")
    t0 = time.perf_counter()
    with make_progress() as progress:
        task = progress.add_task(f"simulating {style}", total=scans)

        def tick(done: int, total: int) -> None:
            progress.update(task, completed=done, total=total)

        folder = simulate_dataset(
            output,
            style=style,
            seed=seed,
            n_scans=scans,
            sensor=sensor.value,
            overwrite=overwrite,
            reuse=reuse,
            progress=tick,
        )
    n = len(list((Path(folder) / "velodyne").glob("*.bin")))
    info(
        f"simulated {n} scans ({style}, {sensor.value}, seed {seed}) in "
        f"{time.perf_counter() - t0:.1f} s -> {folder}"
    )


@app.command(
    "build-dataset",
    epilog="[bold]Examples[/bold]\n\n  graffmatch build-dataset --list\n\n"
    "  graffmatch build-dataset sim-downtown --quick\n\n"
    "  graffmatch build-dataset balm_courtyard -o datasets/",
)
@cli_errors
def build_dataset(
    name: Annotated[
        str | None, typer.Argument(help="Suite name (see --list).", show_default=False)
    ] = None,
    output: Annotated[
        Path, typer.Option("--output", "-o", help="Root folder; the suite goes to <root>/<name>.")
    ] = Path("datasets"),
    quick: Annotated[bool, typer.Option(help="A small version (for tests and previews).")] = False,
    list_: Annotated[bool, typer.Option("--list", help="List the built-in suites.")] = False,
) -> None:
    """Build a loop-closure suite: places, revisits, landmarks, ground-truth matches, cases."""
    from graffmatch.evaluation.suites import SUITES, build_suite

    if list_ or name is None:
        for key in sorted(SUITES):
            out.print(f"{key:18s} {SUITES[key].description}")
        return
    from graffmatch.cli.settings import dump_model
    from graffmatch.evaluation.suites import suite_config

    summary = build_suite(name, output, quick=quick, progress=not STATE.quiet)
    folder = output / (f"{name}-quick" if quick else name)
    # The suite's own rules (and their extractor config) made this data, not the CLI settings.
    (folder / "config.yaml").write_text(
        dump_model(suite_config(name, quick), f"loop-closure rules of suite {name}")
    )
    info(_summary_line(summary, folder))


def _summary_line(summary: Any, folder: Path) -> str:
    if not isinstance(summary, dict):
        return f"built -> {folder}"
    keys = ("n_places", "n_pairs", "n_valid", "cases", "total_s")
    parts = [f"{k}={summary[k]}" for k in keys if k in summary]
    return f"built {summary.get('suite', '')} -> {folder}  " + " ".join(parts)


class ExecutorChoice(str, Enum):
    local = "local"
    serial = "serial"
    dask = "dask"
    ray = "ray"


@app.command(
    epilog="[bold]Examples[/bold]\n\n  graffmatch benchmark --quick\n\n"
    "  graffmatch benchmark sim-downtown balm_courtyard -o bench-out\n\n"
    "  graffmatch benchmark --executor dask --address tcp://10.0.0.2:8786",
)
@cli_errors
def benchmark(
    suites: Annotated[
        list[str] | None, typer.Argument(help="Suite names (default: the default suites).")
    ] = None,
    output: Annotated[
        Path | None,
        typer.Option("--output", "-o", help="Results folder; default runs/<time>_benchmark/."),
    ] = None,
    quick: Annotated[bool, typer.Option(help="The small (≤ 5 min) version.")] = False,
    executor: Annotated[
        ExecutorChoice, typer.Option(help="Where pairs run.")
    ] = ExecutorChoice.local,
    address: Annotated[
        str | None, typer.Option(help="Cluster scheduler address (dask/ray).")
    ] = None,
    workers: Annotated[int | None, typer.Option(min=1, help="Local worker processes.")] = None,
    methods: Annotated[
        list[str] | None, typer.Option("--method", "-m", help="Only these methods (repeatable).")
    ] = None,
    data_dir: Annotated[
        Path | None, typer.Option(help="Cache of built suites (share it between runs).")
    ] = None,
) -> None:
    """Run the paper's experiments (every method on every pair) in parallel; resumable.

    Writes <out>/results (one record per pair and method), <out>/report and the config. Rerun
    with the same -o to continue a killed run; 'graffmatch report <out>' rebuilds the report.
    """
    from graffmatch.evaluation.benchmark import run_benchmark

    out_dir = output or run_dir(STATE.runs_dir, "benchmark")
    out_dir.mkdir(parents=True, exist_ok=True)
    # run_benchmark writes the exact study configuration itself (results/config.json).
    res = run_benchmark(
        suites=list(suites or []) or None,
        out_dir=out_dir,
        quick=quick,
        executor=executor.value,
        address=address,
        workers=workers,
        methods=list(methods) if methods else None,
        data_dir=data_dir,
        progress=not STATE.quiet,
    )
    info(f"results -> {res}")


@app.command(
    epilog="[bold]Example[/bold]\n\n  graffmatch report runs/2026-11-21_14-03-12_benchmark "
    "-o report/",
)
@cli_errors
def report(
    results: Annotated[
        Path,
        typer.Argument(help="Folder written by 'graffmatch benchmark' (or its results/)."),
    ],
    output: Annotated[
        Path | None,
        typer.Option("--output", "-o", help="Report folder; default <benchmark>/report."),
    ] = None,
    views: Annotated[
        int,
        typer.Option(
            min=0,
            help="Interactive 3D views (and PNGs) of this many sample pairs per suite and case, "
            "linked from summary.md; 0 for none.",
        ),
    ] = 1,
) -> None:
    """Turn benchmark results into tables, figures, sample 3D views and a markdown summary."""
    from graffmatch.cli.report_views import benchmark_folder_of, write_report_views
    from graffmatch.evaluation.report import make_report

    if not results.is_dir():
        raise MalformedFileError(f"{results}: results folder not found")
    bench = benchmark_folder_of(results)
    if bench is not None and (results / "results").is_dir():
        # a 'graffmatch benchmark' output folder: its records live in results/
        output = output or results / "report"
        results = results / "results"
    with err.status("writing the report ...") if not STATE.quiet else _null():
        folder = Path(make_report(results, output))
    if views and bench is not None:
        with make_progress() as progress:
            task = progress.add_task("sample views", total=None)
            entries = write_report_views(
                bench,
                folder,
                per_case=views,
                matcher_config=STATE.settings.matcher,
                max_points=min(STATE.settings.view.max_points, 20_000),
                on_pair=lambda name: progress.update(task, description=f"view {name}"),
            )
        info(f"{len(entries)} sample view(s) -> {folder / 'views'}")
    info(f"report -> {folder}")


class CalibKind(str, Enum):
    lidar_lidar = "lidar-lidar"
    camera_depth = "camera-depth"
    both = "both"


@app.command(
    epilog="[bold]Examples[/bold]\n\n  graffmatch calibrate --demo\n\n"
    "  graffmatch calibrate --demo --kind camera-depth --seed 2\n\n"
    "  graffmatch calibrate lidar_a.pcd lidar_b.pcd -o extrinsic.json\n\n"
    "  graffmatch calibrate --image rgb.png --camera-k K.txt --depth depth.png "
    "--depth-k 525,525,319.5,239.5 --board 7x5x0.07",
)
@cli_errors
def calibrate(
    cloud_a: Annotated[Path | None, typer.Argument(help="Point cloud of LiDAR A.")] = None,
    cloud_b: Annotated[Path | None, typer.Argument(help="Point cloud of LiDAR B.")] = None,
    demo_: Annotated[bool, typer.Option("--demo", help="Run the simulated rig(s).")] = False,
    kind: Annotated[CalibKind, typer.Option(help="Which demo rig.")] = CalibKind.both,
    seed: Annotated[int, typer.Option(help="Seed of the simulated rig.")] = 0,
    output: Annotated[Path | None, typer.Option("--output", "-o", help="Result JSON.")] = None,
    image: Annotated[
        Path | None, typer.Option(help="Camera-depth: RGB image of the chessboards (png/jpg).")
    ] = None,
    camera_k: Annotated[
        str | None,
        typer.Option(help="Camera intrinsics: a 3x3 text file or 'fx,fy,cx,cy' [px]."),
    ] = None,
    depth: Annotated[
        Path | None,
        typer.Option(help="Camera-depth: depth image, .npy [m] or 16-bit .png (--depth-scale)."),
    ] = None,
    depth_k: Annotated[
        str | None, typer.Option(help="Depth intrinsics: a 3x3 text file or 'fx,fy,cx,cy' [px].")
    ] = None,
    depth_scale: Annotated[
        float, typer.Option(help="Metres per unit of an integer depth image.")
    ] = 0.001,
    board: Annotated[
        str | None,
        typer.Option(
            help="Chessboard: inner corners, square and optional margin [m], "
            "COLSxROWSxSQUARE[xMARGIN], e.g. 7x5x0.07."
        ),
    ] = None,
) -> None:
    """Extrinsic calibration from planar boards with GraffMatch (planes only, no initial guess).

    With two clouds: T_b_a (maps LiDAR A points into LiDAR B's frame), κ and plane residuals.
    With --demo: simulated rigs with known extrinsics; exit code 3 if a bound (1°, 5 cm) is missed.
    """
    from graffmatch import calibration

    cal = STATE.settings.calibration
    if demo_:
        kinds = ["lidar-lidar", "camera-depth"] if kind == CalibKind.both else [kind.value]
        reports = {}
        for k in kinds:
            config = cal.lidar_lidar if k == "lidar-lidar" else cal.camera_depth
            with (
                err.status(f"calibrating the simulated {k} rig ...") if not STATE.quiet else _null()
            ):
                rep = calibration.run_calibration_demo(kind=k, seed=seed, config=config)
            out.print(calibration.format_demo_report(rep))
            reports[k] = rep
        if output is not None:
            _write_json(output, reports)
        missed = [k for k, r in reports.items() if not r.get("within_bounds", False)]
        if missed:
            err.print(f"[bold red]calibrate:[/bold red] bounds missed for {', '.join(missed)}")
            raise typer.Exit(EXIT_NOT_VALID)
        return
    if image is not None or depth is not None:
        _calibrate_camera_depth(
            image, camera_k, depth, depth_k, depth_scale, board, cal.camera_depth, output
        )
        return
    if cloud_a is None or cloud_b is None:
        raise InvalidInputError(
            "give two point clouds (LiDAR A, LiDAR B), --image/--depth (camera-depth), or --demo"
        )
    from graffmatch.cli.inputs import read_scan

    a, _ = read_scan(cloud_a)
    b, _ = read_scan(cloud_b)
    res = calibration.calibrate_lidar_lidar(a[:, :3], b[:, :3], cal.lidar_lidar)
    out.print(repr(res))
    T = np.asarray(res.T_target_source)
    out.print("[bold]T_b_a[/bold] (LiDAR A -> LiDAR B)")
    for r in T:
        out.print("  " + " ".join(f"{v:+10.5f}" for v in r))
    if output is not None:
        _write_json(output, res.to_dict())
        info(f"result: {output}")
    if not res.valid:
        raise typer.Exit(EXIT_NOT_VALID)


def _calibrate_camera_depth(
    image: Path | None,
    camera_k: str | None,
    depth: Path | None,
    depth_k: str | None,
    depth_scale: float,
    board: str | None,
    config: Any,
    output: Path | None,
) -> None:
    """Camera-depth calibration from files: T_depth_camera, κ and plane residuals."""
    from graffmatch import calibration
    from graffmatch.cli.inputs import parse_board, read_depth_image, read_image, read_intrinsics

    missing = [
        name
        for name, v in (
            ("--image", image),
            ("--camera-k", camera_k),
            ("--depth", depth),
            ("--depth-k", depth_k),
            ("--board", board),
        )
        if v is None
    ]
    if missing:
        raise InvalidInputError(f"camera-depth calibration also needs {', '.join(missing)}")
    res = calibration.calibrate_camera_depth(
        read_image(image),
        read_intrinsics(camera_k, "--camera-k"),
        read_depth_image(depth, depth_scale),
        read_intrinsics(depth_k, "--depth-k"),
        parse_board(board),
        config,
    )
    out.print(repr(res))
    out.print("[bold]T_depth_camera[/bold] (camera -> depth)")
    for r in np.asarray(res.T_target_source):
        out.print("  " + " ".join(f"{v:+10.5f}" for v in r))
    if output is not None:
        _write_json(output, res.to_dict())
        info(f"result: {output}")
    if not res.valid:
        raise typer.Exit(EXIT_NOT_VALID)


if __name__ == "__main__":  # pragma: no cover
    app()
