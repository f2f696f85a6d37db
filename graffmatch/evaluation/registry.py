"""The method registry: every method of the evaluation by name, built lazily on request.

``get_method("GraffMatch", rho=20)`` builds a method; ``register_method`` adds a user's own.
Implementations are imported only when requested (Open3D and friends are heavy).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from graffmatch.errors import InvalidInputError
from graffmatch.evaluation.methods import Method, MethodKind

# ----------------------------------------------------------------------------------------------
# registry
# ----------------------------------------------------------------------------------------------
MethodFactory = Callable[..., Method]


@dataclass(frozen=True)
class _Entry:
    factory: MethodFactory
    kind: MethodKind
    description: str


METHODS: dict[str, _Entry] = {}


def register_method(
    name: str, factory: MethodFactory, kind: MethodKind, description: str = ""
) -> None:
    """Add a method to the registry (a user can register their own)."""
    if name in METHODS:
        raise InvalidInputError(f"method {name!r} is already registered")
    METHODS[name] = _Entry(factory, kind, description)


def _lazy(module: str, attr: str, **fixed: Any) -> MethodFactory:
    """Import the implementation only when the method is requested (Open3D etc. are heavy)."""

    def factory(**params: Any) -> Method:
        cls = getattr(importlib.import_module(module), attr)
        return cls(**{**fixed, **params})

    return factory


def get_method(name: str, **params: Any) -> Method:
    """Instantiate a registered method with optional parameters."""
    try:
        entry = METHODS[name]
    except KeyError:
        raise InvalidInputError(
            f"unknown method {name!r}; available: {', '.join(list_methods())}"
        ) from None
    return entry.factory(**params)


def list_methods(kind: MethodKind | None = None) -> list[str]:
    """Registered method names (optionally only landmark or point methods), in table order."""
    return [n for n, e in METHODS.items() if kind is None or e.kind == kind]


#: Local methods (need an initial guess) and the global baselines, in the paper's order.
LOCAL_METHODS = ("CPMatch", "BruteForceRMSE")
GLOBAL_BASELINES = ("ClusterMatch", "LiPMatch", "CLIPPER-Rn", "CLIPPER-CP")

_GM = "graffmatch.evaluation.methods"
_BL = "graffmatch.evaluation.baselines"
for _name, _factory, _kind, _desc in [
    ("GraffMatch", _lazy(_GM, "GraffMatchMethod"), "landmark", "the paper's method"),
    (
        "GraffMatch-Naive",
        _lazy(_GM, "GraffMatchMethod", name="GraffMatch-Naive", variant="naive"),
        "landmark",
        "d_Graff without the shift (not invariant)",
    ),
    (
        "GraffMatch-lines",
        _lazy(_GM, "GraffMatchMethod", name="GraffMatch-lines", landmark_types=("line",)),
        "landmark",
        "lines (poles) only",
    ),
    (
        "GraffMatch-planes",
        _lazy(_GM, "GraffMatchMethod", name="GraffMatch-planes", landmark_types=("plane",)),
        "landmark",
        "planes only",
    ),
    ("CPMatch", _lazy(f"{_BL}.cpmatch", "CPMatch"), "landmark", "Zhou et al. 2021 (pi-LSAM)"),
    (
        "BruteForceRMSE",
        _lazy(f"{_BL}.bruteforce_rmse", "BruteForceRMSE"),
        "landmark",
        "Zhou et al. 2022 (PLC-LiSLAM)",
    ),
    ("ClusterMatch", _lazy(f"{_BL}.clustermatch", "ClusterMatch"), "landmark", "Cao et al. 2020"),
    ("LiPMatch", _lazy(f"{_BL}.lipmatch", "LiPMatch"), "landmark", "Jiang et al. 2020"),
    (
        "CLIPPER-Rn",
        _lazy(f"{_BL}.clipper_variants", "ClipperCentroids"),
        "landmark",
        "CLIPPER, Euclidean centroid distances",
    ),
    (
        "CLIPPER-CP",
        _lazy(f"{_BL}.clipper_variants", "ClipperCP"),
        "landmark",
        "CLIPPER, Euclidean CP-vector distances",
    ),
    (
        "GraffMatch+ICP",
        _lazy(_GM, "GraffMatchICP"),
        "landmark",
        "GraffMatch then ICP on the matched landmarks' points",
    ),
    ("FPFH+RANSAC", _lazy(f"{_BL}.fpfh_ransac", "FpfhRansac"), "point", "Open3D FPFH + RANSAC"),
    ("ScanContext", _lazy(f"{_BL}.scan_context", "ScanContext"), "point", "Kim & Kim, yaw only"),
    (
        "ScanContext+ICP",
        _lazy(f"{_BL}.scan_context", "ScanContextICP"),
        "point",
        "Scan Context yaw, then ICP",
    ),
    (
        "KISS-Matcher",
        _lazy(f"{_BL}.kiss_matcher", "KissMatcher"),
        "point",
        "Lim et al. 2025, PyPI kiss-matcher",
    ),
]:
    register_method(_name, _factory, _kind, _desc)  # type: ignore[arg-type]

#: The paper's Table I methods in its column order (the report appends our variants).
TABLE_I_METHODS = [*LOCAL_METHODS, *GLOBAL_BASELINES, "GraffMatch"]
#: The paper's Table II methods.
TABLE_II_METHODS = ["GraffMatch+ICP", "FPFH+RANSAC", "ScanContext", "ScanContext+ICP"]
