"""Commands on scans: ``extract`` landmarks, ``register`` two scans, ``view`` a result.

Each parses its arguments, calls the library and prints; results on stdout, progress on stderr.
The module runs past 500 lines while ``register`` still refines with ICP itself and assembles
its result document; both move to :mod:`graffmatch.pipeline` (``ScanMatcher``) next.
"""

from __future__ import annotations

import time
from enum import Enum
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import typer
from rich.table import Table

from graffmatch.cli.common import (
    EXIT_NOT_VALID,
    MAX_TABLE_ROWS,
    STATE,
    ScaleOption,
    __version__,
    cli_errors,
    err,
    fmt_ms,
    info,
    make_progress,
    now,
    out,
    parse_scale,
    print_matrix,
    run_dir,
    stage,
    write_config_beside,
    write_config_next_to,
    write_json,
)
from graffmatch.cli.inputs import LazyExtractor, counts_text, load_input
from graffmatch.errors import GraffMatchError, InvalidInputError, MalformedFileError
from graffmatch.geometry.transforms import restore_offsets

commands = typer.Typer()


# ----------------------------------------------------------------------------------------------
# extract
# ----------------------------------------------------------------------------------------------
@commands.command(
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
    scale: ScaleOption = "1",
) -> None:
    """Extract pole (line) and plane landmarks from scans into compact .npz landmark files."""
    from graffmatch.cli.inputs import find_labels, list_scans, read_cloud

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
    ex = LazyExtractor(STATE.settings.extractor).get()
    rows = []
    with make_progress() as progress:
        task = progress.add_task("extracting", total=len(scans))
        for path in scans:
            progress.update(task, description=f"extracting {path.name}")
            label_path = find_labels(path, labels, STATE.settings.input.labels)
            cloud = read_cloud(path, label_path, scale)
            pts = cloud.points
            t0 = time.perf_counter()
            ls = ex.extract(pts, cloud.labels)
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
                    # landmarks are relative to this (zero unless the file held far coordinates)
                    "origin": cloud.origin,
                    "poles": c["lines"],
                    "planes": c["planes"],
                    "seconds": dt,
                    "bytes": target.stat().st_size,
                    "timings": dict(ex.last_timings),
                }
            )
            progress.advance(task)
    if single_file:
        write_config_beside(output)
    else:
        write_config_next_to(out_dir)
    summary_path = (out_dir / "summary.json") if not single_file else output.with_suffix(".json")
    write_json(summary_path, {"created": now(), "scans": rows})
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
            fmt_ms(r["seconds"]),
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
        f"({fmt_ms(tot / max(len(rows), 1))}/scan) -> {out_dir if not single_file else output}"
    )


# ----------------------------------------------------------------------------------------------
# register
# ----------------------------------------------------------------------------------------------
class PoseFormatChoice(str, Enum):
    kitti = "kitti"
    tum = "tum"


class RefineChoice(str, Enum):
    none = "none"
    icp = "icp"


@commands.command(
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
    scan_realign: Annotated[
        bool,
        typer.Option(help="With both scans read: re-align a valid support-point answer by ICP on the scans "
                     "(1 m correspondences; kept when it reaches at least as many points)."),
    ] = True,
    view: Annotated[
        Path | None, typer.Option(help="Write the interactive 3D view (one HTML file).")
    ] = None,
    source_labels: Annotated[
        Path | None, typer.Option(help="SemanticKITTI labels of the source scan.")
    ] = None,
    target_labels: Annotated[
        Path | None, typer.Option(help="SemanticKITTI labels of the target scan.")
    ] = None,
    scale: ScaleOption = "1",
    allow_invalid: Annotated[
        bool,
        typer.Option(help="Write --pose-out (and print the pose with -q) even when the result is not valid."),
    ] = False,
) -> None:
    """Register SOURCE to TARGET: print T_target_source, confidence, inliers, κ and validity.

    An invalid result prints INVALID: <reason> on stderr, no pose on stdout, writes no pose file
    (unless --allow-invalid) and exits with 3."""
    from graffmatch.cli.inputs import path_record, read_transform
    from graffmatch.datasets.folder import ground_truth_between
    from graffmatch.geometry.pose_files import write_poses

    # Check the cheap things first: a typo must not cost an extraction.
    if gt == "auto":
        T_gt = ground_truth_between(source, target)
    else:
        T_gt = read_transform(gt) if gt is not None else None
    for p in (source, target):
        if not p.exists():
            raise MalformedFileError(f"{p}: input not found")
    settings = STATE.settings
    if pose_out is not None and pose_format is None:
        pose_format = PoseFormatChoice.kitti if pose_out.suffix != ".tum" else PoseFormatChoice.tum
    extractor = LazyExtractor(settings.extractor)
    label_mode = settings.input.labels
    steps = 3 + (refine == RefineChoice.icp)
    with make_progress() as progress:
        task = progress.add_task("registering", total=steps)
        with stage(progress, task, f"reading {source.name}"):
            src = load_input(source, source_labels, label_mode, extractor, scale)
        with stage(progress, task, f"reading {target.name}"):
            tgt = load_input(target, target_labels, label_mode, extractor, scale)
        from graffmatch.pipeline import RefinementConfig, ScanMatcher, ScanMatcherConfig

        both_scans = src.points is not None and tgt.points is not None
        scan_matcher = ScanMatcher(ScanMatcherConfig(
            extractor=settings.extractor, matcher=settings.matcher,
            refinement=RefinementConfig(
                method=refine.value, points="scans" if both_scans else "landmarks",
                **settings.icp.model_dump(),
            ),
            **({} if scan_realign else {"scan_realign_m": None}),
        ))
        with stage(progress, task, "matching and verifying"):
            result = scan_matcher.match_scans(src.landmarks, tgt.landmarks, src.points, tgt.points,
                                              src.cloud, tgt.cloud)
        T_matcher = None if result.T_target_source is None else result.T_target_source.copy()
        refine_info = None
        if refine == RefineChoice.icp and T_matcher is not None:
            with stage(progress, task, "ICP refinement"):
                scan_matcher.refine(result, src.landmarks, tgt.landmarks, src.points, tgt.points)
                i = result.info
                refine_info = {
                    "method": "icp", "points": i["icp_points"],
                    "T_target_source": np.asarray(result.T_target_source, float), "T_init": T_matcher,
                    "fitness": float(i["icp_fitness"]), "inlier_rmse": float(i["icp_rmse"]),
                    "n_source_points": int(i["icp_n_source"]), "n_target_points": int(i["icp_n_target"]),
                    "correction_deg": float(i["icp_correction_deg"]), "correction_m": float(i["icp_correction_m"]),
                }
        T_est = None if result.T_target_source is None else np.asarray(result.T_target_source, float)
        assoc = np.asarray(result.associations, dtype=np.int64).reshape(-1, 2)
    # Far (UTM) clouds were registered around their origins; give the transform of the files.
    T_local = T_est
    if T_est is not None:
        T_est = restore_offsets(T_est, src.origin, tgt.origin)
        T_matcher = restore_offsets(T_matcher, src.origin, tgt.origin)
        if refine_info is not None:
            refine_info["T_target_source"] = T_est
            refine_info["T_init"] = T_matcher

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
        from graffmatch.evaluation.metrics import ground_truth_report

        g = settings.ground_truth
        # judged around the origins, where the landmarks are (the same frames when they are 0)
        gt_info = ground_truth_report(
            src.landmarks,
            tgt.landmarks,
            assoc,
            T_local,
            restore_offsets(T_gt, -src.origin, -tgt.origin),
            tau_d_deg=g.tau_d_deg,
            max_rotation_deg=g.max_rotation_deg,
            max_translation_m=g.max_translation_m,
        )
        inlier_mask = gt_info["inlier_mask"]
    valid = bool(result.valid)
    data = {
        "format": "graffmatch-register-result",
        "version": 1,
        "created": now(),
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
        "origins": {"source": src.origin, "target": tgt.origin, "scale": str(scale)},
        "T_target_source_local": T_local,
        "associations": assoc,
        "weights": np.asarray(result.weights, float),
        "score": float(result.score),
        "kappa": float(result.kappa),
        "degenerate": bool(result.degenerate),
        "valid": valid,
        "confidence": float(result.confidence),
        "overlap": float(result.overlap),
        "margin": float(result.margin),
        "runner_up": None if result.runner_up is None else result.runner_up.to_dict(),
        "hypotheses": [h.to_dict() for h in result.hypotheses],
        "message": str(result.message),
        "n_putative": int(result.n_putative),
        "n_edges": int(result.n_edges),
        "timings": {
            "match": dict(result.timings),
            "extract_source": src.timings,
            "extract_target": tgt.timings,
        },
        "refine": refine_info,
        "scan_realign": None if "scan_realign" not in result.info else {
            **result.info["scan_realign"], "T_support": result.info.get("T_support"),
            "enabled": scan_realign},
        "ground_truth": gt_info,
        "config": STATE.settings.model_dump(mode="json"),
    }
    write_json(result_path, data)
    if output is None:
        write_config_next_to(folder)
    else:
        write_config_beside(result_path)
    pose_written = None
    if pose_format is not None and T_est is not None and (valid or allow_invalid):
        suffix = ".kitti.txt" if pose_format == PoseFormatChoice.kitti else ".tum.txt"
        pose_written = write_poses(
            pose_out or result_path.with_suffix(suffix), T_est, pose_format.value
        )
    view_written = None
    if view is not None:
        from graffmatch.viz.match_view import result_view_info, write_match_view

        view_written = write_match_view(
            view,
            src.landmarks,
            tgt.landmarks,
            np.eye(4) if T_local is None else T_local,
            assoc,
            source_points=src.points,
            target_points=tgt.points,
            inlier_mask=inlier_mask,
            title=f"GraffMatch: {src.path.name} → {tgt.path.name}",
            info=result_view_info(data),
            max_points=settings.view.max_points,
            initial=settings.view.initial,
        )
    _print_register(data, src, tgt, result_path, pose_written, view_written, allow_invalid)
    if not valid:
        err.print(f"INVALID: {result.message}", markup=False, highlight=False)
        raise typer.Exit(EXIT_NOT_VALID)


def _print_register(data, src, tgt, result_path, pose_written, view_written,
                    allow_invalid: bool = False) -> None:
    if STATE.quiet:
        if not data["valid"] and not allow_invalid:
            return  # no pose on stdout for an invalid result
        T = data["T_target_source"]
        out.print("none" if T is None else " ".join(f"{v:.9g}" for v in np.asarray(T)[:3].ravel()))
        return
    names = {0: "point", 1: "pole", 2: "plane"}
    out.print(
        f"[bold]source[/bold] {src.path.name} ({src.kind}): {counts_text(src.landmarks)}   "
        f"[bold]target[/bold] {tgt.path.name} ({tgt.kind}): {counts_text(tgt.landmarks)}"
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
    elif data["valid"] or allow_invalid:
        print_matrix(data["T_target_source"], "T_target_source")
    else:
        out.print("[bold]T_target_source[/bold]: withheld (not valid; --allow-invalid shows it)")
    verdict = "[green]valid[/green]" if data["valid"] else "[red]NOT valid[/red]"
    out.print(
        f"confidence {data['confidence']:.3f}  overlap {data['overlap']:.3f}  margin {data['margin']:.3f}  "
        f"associations {len(assoc)}  κ {data['kappa']:.3g}  {verdict}"
        + (f"  ({data['message']})" if data["message"] else "")
    )
    if data["runner_up"]:
        ru = data["runner_up"]
        out.print(f"runner-up: {ru['origin']}, {ru['n_associations']} associations, score {ru['score']:.3f}")
    if data["refine"]:
        r = data["refine"]
        out.print(
            f"ICP on {r['n_source_points']}/{r['n_target_points']} {r['points']} points: "
            f"fitness {r['fitness']:.3f}, inlier RMSE {r['inlier_rmse']:.3f} m, correction "
            f"{r['correction_deg']:.2f}° / {r['correction_m']:.3f} m"
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
        out.print("timings: " + ", ".join(f"{k} {fmt_ms(v)}" for k, v in tm.items()))
    out.print(f"result: {result_path}")
    if pose_written:
        out.print(f"pose: {pose_written}")
    if view_written:
        out.print(f"view: {view_written}")


# ----------------------------------------------------------------------------------------------
# view
# ----------------------------------------------------------------------------------------------
@commands.command(
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
    from graffmatch.cli.inputs import is_landmark_file, load_result, read_cloud, resolve_path_record
    from graffmatch.geometry.landmarks import LandmarkSet
    from graffmatch.viz.match_view import result_view_info, write_match_view

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
                scale = data.get("origins", {}).get("scale", "1")
                points[name] = read_cloud(p, scale=parse_scale(scale)).points
            elif rec.get("kind") == "scan":
                err.print(f"[yellow]warning[/yellow]: scan {p} not found; drawing landmarks only")
    gt = data.get("ground_truth")
    mask = None if not gt else np.asarray(gt["inlier_mask"], bool)
    out_path = output or result.with_suffix(".html")
    # the landmark files and the re-read points are around the origins (see register)
    T_saved = data.get("T_target_source_local", data["T_target_source"])
    T = np.eye(4) if T_saved is None else np.asarray(T_saved)
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
        info=result_view_info(data),
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
