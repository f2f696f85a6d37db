"""Datasets: a ``Dataset`` protocol, loaders for KITTI / KITTI-360 / NCLT / KITTI-layout
folders, and an explicit registry (:func:`open_dataset`)."""

from graffmatch.datasets.base import Dataset, Scan, ScanSequence
from graffmatch.datasets.deskewed import Deskewed
from graffmatch.datasets.folder import KittiFolder
from graffmatch.datasets.kitti import KittiOdometry
from graffmatch.datasets.kitti360 import Kitti360
from graffmatch.datasets.nclt import NCLT
from graffmatch.datasets.registry import available, open_dataset, register

__all__ = [
    "NCLT",
    "Dataset",
    "Deskewed",
    "Kitti360",
    "KittiFolder",
    "KittiOdometry",
    "Scan",
    "ScanSequence",
    "available",
    "open_dataset",
    "register",
]
