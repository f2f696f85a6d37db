"""Files of a loop-closure run: loops.csv, g2o pose graphs, KITTI and TUM trajectories.

* ``loops.csv``: one verified loop a row: query, match, the 12 values of the top 3x4 of
  ``T_match_query`` (row-major), confidence, overlap, association count, agreeing landmarks.
* g2o: ``VERTEX_SE3:QUAT id x y z qx qy qz qw`` and ``EDGE_SE3:QUAT i j x y z qx qy qz qw``
  followed by the 21 upper-triangular entries of the 6x6 information matrix, translation
  first (g2o's order). An edge i -> j holds ``T_i_j`` (pose of j in i's frame), so a loop edge
  is ``match query T_match_query``.
* Trajectories (KITTI, TUM): :mod:`graffmatch.geometry.pose_files`.
"""

from __future__ import annotations

import csv
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from graffmatch.atomic_files import write_text_atomic
from graffmatch.errors import InvalidInputError, MalformedFileError
from graffmatch.geometry.pose_files import pose_to_xyzq, xyzq_to_pose
from graffmatch.loops.verify import LoopClosure

Array = NDArray[np.float64]

LOOP_COLUMNS = (
    ["query", "match"]
    + [f"T{r}{c}" for r in range(3) for c in range(4)]
    + ["confidence", "overlap", "n_associations", "n_agreeing"]
)


def write_loops_csv(path: str | Path, loops: Iterable[LoopClosure]) -> Path:
    lines = [",".join(LOOP_COLUMNS)]
    for lc in loops:
        T = np.asarray(lc.T_match_query, float)[:3, :4].ravel()
        vals = [str(lc.query), str(lc.match)] + [f"{v:.9g}" for v in T]
        vals += [f"{lc.confidence:.6f}", f"{lc.overlap:.6f}", str(lc.n_associations), str(lc.n_agreeing)]
        lines.append(",".join(vals))
    return write_text_atomic(Path(path), "\n".join(lines) + "\n")


def read_loops_csv(path: str | Path) -> list[LoopClosure]:
    path = Path(path)
    if not path.is_file():
        raise InvalidInputError(f"loops file not found: {path}")
    out = []
    with path.open() as f:
        reader = csv.DictReader(f)
        if reader.fieldnames is None or list(reader.fieldnames[: len(LOOP_COLUMNS)]) != LOOP_COLUMNS:
            raise MalformedFileError(f"{path}: header must be {','.join(LOOP_COLUMNS)}")
        for lineno, row in enumerate(reader, start=2):
            try:
                T = np.eye(4)
                T[:3, :4] = np.array([float(row[f"T{r}{c}"]) for r in range(3) for c in range(4)]).reshape(3, 4)
                out.append(
                    LoopClosure(
                        query=int(row["query"]),
                        match=int(row["match"]),
                        T_match_query=T,
                        confidence=float(row["confidence"]),
                        overlap=float(row["overlap"]),
                        n_associations=int(row["n_associations"]),
                        n_agreeing=int(row["n_agreeing"]),
                        retrieval_rank=-1,
                        retrieval_distance=float("nan"),
                        valid=True,
                    )
                )
            except (KeyError, TypeError, ValueError) as exc:
                raise MalformedFileError(f"{path}:{lineno}: bad row ({exc})") from exc
    return out


def loop_information(lc: LoopClosure, min_sigma_m: float = 0.05, lever_m: float = 10.0) -> Array:
    """6x6 information (translation first) of a loop edge from its registration.

    sigma_t = max(rms offset residual, ``min_sigma_m``) / sqrt(associations); the rotation
    sigma is the translation sigma over a ``lever_m`` lever arm (landmarks ~10 m away).
    """
    rms = lc.info.get("rms_offset") if lc.info else None
    rms = float(rms) if rms is not None and np.isfinite(rms) else min_sigma_m
    n = max(int(lc.n_associations), 1)
    s_t = max(rms, min_sigma_m) / np.sqrt(n)
    s_r = s_t / lever_m
    return np.diag([1 / s_t**2] * 3 + [1 / s_r**2] * 3)


def _info_upper(info: Array) -> list[float]:
    iu = np.triu_indices(6)
    return np.asarray(info, float)[iu].tolist()


def _info_from_upper(vals: Sequence[float]) -> Array:
    M = np.zeros((6, 6))
    M[np.triu_indices(6)] = vals
    return M + np.triu(M, 1).T


def write_g2o(
    path: str | Path,
    edges: Iterable[tuple[int, int, Array, Array]],
    poses: Array | None = None,
) -> Path:
    """g2o file: optional vertices (poses[i] = T_world_i) and edges (i, j, T_i_j, info 6x6)."""
    lines = []
    if poses is not None:
        for i, T in enumerate(np.asarray(poses, float)):
            lines.append(f"VERTEX_SE3:QUAT {i} " + " ".join(f"{v:.9g}" for v in pose_to_xyzq(T)))
    for i, j, T, info in edges:
        vals = list(pose_to_xyzq(T)) + _info_upper(info)
        lines.append(f"EDGE_SE3:QUAT {int(i)} {int(j)} " + " ".join(f"{v:.9g}" for v in vals))
    return write_text_atomic(Path(path), "\n".join(lines) + "\n")


def loop_edges(loops: Iterable[LoopClosure]) -> list[tuple[int, int, Array, Array]]:
    return [(lc.match, lc.query, np.asarray(lc.T_match_query, float), loop_information(lc)) for lc in loops]


def read_g2o(path: str | Path) -> tuple[dict[int, Array], list[tuple[int, int, Array, Array]]]:
    """(vertices {id: T_world}, edges [(i, j, T_i_j, info)]) of a g2o SE3 file."""
    path = Path(path)
    if not path.is_file():
        raise InvalidInputError(f"g2o file not found: {path}")
    verts: dict[int, Array] = {}
    edges = []
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        parts = line.split()
        if not parts:
            continue
        try:
            if parts[0] == "VERTEX_SE3:QUAT":
                verts[int(parts[1])] = xyzq_to_pose([float(v) for v in parts[2:9]], f"{path}:{lineno}")
            elif parts[0] == "EDGE_SE3:QUAT":
                vals = [float(v) for v in parts[3:]]
                if len(vals) != 28:
                    raise ValueError(f"{len(vals)} values, expected 28")
                edges.append((int(parts[1]), int(parts[2]), xyzq_to_pose(vals[:7], f"{path}:{lineno}"), _info_from_upper(vals[7:])))
            else:
                raise ValueError(f"unknown tag {parts[0]!r}")
        except (ValueError, IndexError) as exc:
            raise MalformedFileError(f"{path}:{lineno}: {exc}") from exc
    return verts, edges
