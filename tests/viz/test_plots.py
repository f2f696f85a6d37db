"""The static bird's-eye picture of a match (matplotlib, for reports)."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")

import matplotlib.image as mpimg
import numpy as np
import pytest

from graffmatch.errors import InvalidInputError
from graffmatch.viz.plots import plot_match_topdown


def test_topdown_png_after_and_side_by_side(scene, tmp_path):
    for side in (False, True):
        path = tmp_path / f"m_{side}.png"
        ax = plot_match_topdown(
            scene.source,
            scene.target,
            scene.T_target_source,
            scene.associations,
            scene.source_points,
            scene.target_points,
            scene.inlier_mask,
            side_by_side=side,
            path=path,
        )
        img = mpimg.imread(path)[..., :3]
        assert img.shape[0] > 500 and img.std() > 0.05
        labels = ax.get_legend_handles_labels()[1]
        assert "inliers (13)" in labels and "outliers (1)" in labels
        # after alignment the inlier lines have zero length; side by side they are long
        lines = [ln for ln in ax.get_lines() if ln.get_color() == "#2ca02c" and len(ln.get_xdata())]
        lengths = np.hypot(
            *(np.array([[np.ptp(ln.get_xdata()), np.ptp(ln.get_ydata())] for ln in lines]).T)
        )
        if side:
            assert lengths.min() > 5
        else:
            assert lengths.max() < 1e-6


def test_topdown_into_given_axes_and_bad_input(scene):
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots()
    out = plot_match_topdown(scene.source, scene.target, np.eye(4), scene.associations, ax=ax)
    assert out is ax and "correspondences (14)" in ax.get_legend_handles_labels()[1]
    with pytest.raises(InvalidInputError):
        plot_match_topdown(scene.source, scene.target, np.eye(4), [[0, 999]], ax=ax)
    with pytest.raises(InvalidInputError):
        plot_match_topdown(
            scene.source, scene.target, np.eye(4), scene.associations, inlier_mask=[True], ax=ax
        )
    plt.close(fig)
