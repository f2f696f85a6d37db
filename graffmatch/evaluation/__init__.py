"""Evaluation: the loop-closure dataset, metrics, methods and the experiment runner.

The names below are loaded on first use (PEP 562) so that ``import graffmatch.evaluation.x``
does not pull in the LiDAR front end (Open3D) when ``x`` does not need it. To export a new
name, add it to ``_EXPORTS`` as ``name: module``.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS: dict[str, str] = {
    "LoopClosureConfig": "graffmatch.evaluation.loop_closures",
    "LoopClosureDataset": "graffmatch.evaluation.loop_closures",
    "LoopClosurePair": "graffmatch.evaluation.loop_closures",
    "build_loop_closure_dataset": "graffmatch.evaluation.loop_closures",
    "SUITES": "graffmatch.evaluation.suites",
    "build_suite": "graffmatch.evaluation.suites",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'graffmatch.evaluation' has no attribute {name!r}")
    return getattr(importlib.import_module(module), name)


def __dir__() -> list[str]:
    return sorted([*globals(), *_EXPORTS])
