"""Matching landmark maps must not load Open3D: it costs ~100 MB of resident memory (issue 14's
W3 peak-memory target) and users who only match stored landmark maps never need it."""

from __future__ import annotations

import subprocess
import sys
import textwrap


def test_matching_landmark_sets_does_not_import_open3d() -> None:
    code = textwrap.dedent(
        """
        import sys
        from graffmatch import GraffMatcher, make_scene_pair
        pair = make_scene_pair(n_poles=8, n_planes=12, seed=0)
        result = GraffMatcher().match(pair.source, pair.target)
        assert result.valid, result.message
        print(sorted(m for m in sys.modules if m == "open3d" or m.startswith("open3d.")))
        """
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip().splitlines()[-1] == "[]"
