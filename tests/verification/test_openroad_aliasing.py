"""Open road, the aliasing case: two different tree-lined roads 60-80 m apart look alike, and
overlap alone accepted a 90 or 180 deg wrong match of them with confidence 0.98-1.00
(docs/report, sim-openroad negatives). The free-space check must reject them, and keep real
revisits of the same drive valid and right.

Fixtures: landmark sets with support points of the sim-openroad suite's drive (seed 1,
400 scans), see ``tests/data/openroad_aliasing/pairs.json``. They were saved before the
extractor kept each scan's whole range image, so they exercise the support points' image and
its own threshold (``max_conflict_support_points``)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from graffmatch.geometry.landmarks import LandmarkSet
from graffmatch.geometry.transforms import transform_errors
from graffmatch.matcher import GraffMatchConfig, GraffMatcher
from graffmatch.verification.config import VerificationConfig

DATA = Path(__file__).resolve().parents[1] / "data" / "openroad_aliasing"
PAIRS = json.loads((DATA / "pairs.json").read_text())["pairs"]


def _load(i: int) -> LandmarkSet:
    return LandmarkSet.load(DATA / f"scan_{i:06d}.npz")


def _match(p: dict, cfg: GraffMatchConfig | None = None):
    r = GraffMatcher(cfg or GraffMatchConfig()).match(_load(p["source"]), _load(p["target"]))
    rot, tr = transform_errors(r.T_target_source, np.array(p["T_target_source"]))
    return r, rot, tr


@pytest.mark.parametrize("p", [p for p in PAIRS if p["kind"] == "aliased"], ids=lambda p: f"{p['source']}-{p['target']}")
def test_aliased_roads_are_not_valid(p: dict) -> None:
    r, rot, tr = _match(p)
    assert rot > 5.0 or tr > 1.0  # the best hypothesis is wrong: the decision must catch it
    assert not r.valid
    assert "free-space conflict" in r.message or "ambiguous" in r.message or "overlap" in r.message
    assert r.confidence <= 0.5


@pytest.mark.parametrize("p", [p for p in PAIRS if p["kind"] == "aliased"], ids=lambda p: f"{p['source']}-{p['target']}")
def test_without_the_free_space_check_they_were_valid(p: dict) -> None:
    """The regression this guards: overlap and margin alone (without the free-space check and
    without the translation votes, whose slid rivals catch some of them) accept these wrong
    matches."""
    cfg = GraffMatchConfig(verification=VerificationConfig(free_space=False, vote_rotations=0))
    r, rot, tr = _match(p, cfg)
    assert r.valid and (rot > 5.0 or tr > 1.0)


def test_translation_votes_find_the_aliases_slid_rivals() -> None:
    """Without the free-space check, the winner's translation re-voted along the road finds a
    twin a few metres away that explains the points about as well: 2 of the 3 aliases are
    ambiguous on the evidence points alone."""
    cfg = GraffMatchConfig(verification=VerificationConfig(free_space=False))
    msgs = [_match(p, cfg)[0] for p in PAIRS if p["kind"] == "aliased"]
    ambiguous = [r for r in msgs if not r.valid and "ambiguous" in r.message and "+vote" in r.message]
    assert len(ambiguous) >= 2


@pytest.mark.parametrize("p", [p for p in PAIRS if p["kind"] == "revisits"], ids=lambda p: f"{p['source']}-{p['target']}")
def test_revisits_stay_valid_and_right(p: dict) -> None:
    r, rot, tr = _match(p)
    assert r.valid, r.message
    assert rot <= 2.0 and tr <= 0.5
    cfg = VerificationConfig()
    assert r.info["free_space_image"] == "support points"  # these files carry no whole-scan image
    assert max(r.info["free_space_conflict"]) < min(cfg.max_conflict, cfg.max_conflict_support_points)
