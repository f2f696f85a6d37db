"""KITTI odometry (optionally with SemanticKITTI labels).

Layout (as downloaded; SemanticKITTI adds ``labels/`` and its own ``poses.txt``)::

    <root>/sequences/XX/velodyne/NNNNNN.bin
    <root>/sequences/XX/labels/NNNNNN.label     optional
    <root>/sequences/XX/calib.txt               'Tr:' velodyne -> camera-0 (required)
    <root>/sequences/XX/times.txt               optional
    <root>/poses/XX.txt  or  <root>/sequences/XX/poses.txt   optional (the test sequences 11-21 have none)

The poses are camera-0 poses; the LiDAR pose of frame i is ``inv(Tr) @ P_i @ Tr``.
"""

from __future__ import annotations

from pathlib import Path

from graffmatch.datasets.folder import KittiLayoutSequence
from graffmatch.errors import InvalidInputError


def _sequence_name(sequence: str | int) -> str:
    if isinstance(sequence, int):
        return f"{sequence:02d}"
    s = str(sequence).strip()
    return f"{int(s):02d}" if s.isdigit() else s


class KittiOdometry(KittiLayoutSequence):
    """One sequence of KITTI odometry / SemanticKITTI, LiDAR-frame ground truth."""

    motion_compensated = True  # KITTI odometry ships its scans de-skewed

    def __init__(self, root: str | Path, sequence: str | int = "00") -> None:
        root = Path(root)
        seq = _sequence_name(sequence)
        seq_dir = root / "sequences" / seq
        if not seq_dir.is_dir():
            raise InvalidInputError(
                f"KITTI sequence folder not found: {seq_dir} (expected <root>/sequences/{seq})"
            )
        candidates = [root / "poses" / f"{seq}.txt", seq_dir / "poses.txt"]
        # the test sequences 11-21 ship without poses: their scans still load (has_poses False)
        pose_file = next((p for p in candidates if p.is_file()), None)
        self._pose_source = " or ".join(str(c) for c in candidates)
        calib = seq_dir / "calib.txt"
        if not calib.is_file():
            raise InvalidInputError(f"KITTI sequence {seq}: calibration not found: {calib}")
        super().__init__(
            scan_dir=seq_dir / "velodyne",
            pose_file=pose_file,
            calib_file=calib,
            times_file=seq_dir / "times.txt",
            label_dir=seq_dir / "labels",
            name=f"kitti-{seq}",
            require_tr=True,
        )
        self.root = root
        self.sequence = seq
