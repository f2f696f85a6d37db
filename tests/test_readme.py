"""Every Python example in README.md runs (examples that are also tests)."""

from __future__ import annotations

import re

import numpy as np
import pytest

from tests.conftest import REPO_ROOT

BLOCKS = re.findall(r"```python\n(.*?)```", (REPO_ROOT / "README.md").read_text(), re.S)


def test_readme_has_three_examples():
    assert len(BLOCKS) >= 3


@pytest.mark.parametrize("code", BLOCKS, ids=[f"example{i}" for i in range(len(BLOCKS))])
def test_readme_example_runs(code, monkeypatch):
    if "../shared/data" in code and not (REPO_ROOT.parent / "shared" / "data").is_dir():
        pytest.skip("example reads ../shared/data, which is absent")
    monkeypatch.chdir(REPO_ROOT)
    ns: dict = {}
    exec(compile(code, "README.md", "exec"), ns)
    result = ns.get("result")
    if result is not None:
        assert result.valid, result
    if "landmarks" in ns:
        assert len(ns["landmarks"]) > 5
    if "loops" in ns:  # every reported loop closure is right (precision first), and there are many
        from graffmatch.geometry.transforms import transform_errors

        P = ns["drive"].poses
        assert len(ns["loops"]) >= 40
        for lc in ns["loops"]:
            rot, trans = transform_errors(lc.T_match_query, np.linalg.inv(P[lc.match]) @ P[lc.query])
            assert rot < 2.0 and trans < 1.0, (lc, rot, trans)
