"""Explicit registry of dataset loaders: ``open_dataset("kitti", root, sequence="00")``.

Loaders are registered by name in this file (no discovery by introspection), so the list of
supported datasets is readable in one place and a user can add their own with :func:`register`.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from graffmatch.datasets.base import Dataset
from graffmatch.datasets.folder import KittiFolder
from graffmatch.datasets.kitti import KittiOdometry
from graffmatch.datasets.kitti360 import Kitti360
from graffmatch.datasets.nclt import NCLT
from graffmatch.errors import InvalidInputError

LoaderFactory = Callable[..., Dataset]

_REGISTRY: dict[str, LoaderFactory] = {}


def register(kind: str, factory: LoaderFactory, overwrite: bool = False) -> None:
    """Register a loader: ``factory(root, **kwargs) -> Dataset``."""
    key = kind.strip().lower()
    if not key:
        raise InvalidInputError("dataset kind must be a non-empty name")
    if key in _REGISTRY and not overwrite:
        raise InvalidInputError(f"dataset kind {key!r} is already registered")
    _REGISTRY[key] = factory


def available() -> list[str]:
    """Names accepted by :func:`open_dataset`."""
    return sorted(_REGISTRY)


def open_dataset(kind: str, root: str | Path, **kwargs: Any) -> Dataset:
    """Open a dataset of a registered kind, e.g. ``open_dataset("nclt", root, date="2012-04-29")``."""
    key = kind.strip().lower()
    if key not in _REGISTRY:
        raise InvalidInputError(f"unknown dataset kind {kind!r}; available: {', '.join(available())}")
    return _REGISTRY[key](Path(root), **kwargs)


register("kitti", KittiOdometry)
register("kitti360", Kitti360)
register("nclt", NCLT)
register("folder", KittiFolder)
