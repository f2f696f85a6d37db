"""Pictures of matches: the interactive 3D view (plotly, one offline HTML) and static PNGs."""

from graffmatch.viz.match_view import match_figure, write_match_view
from graffmatch.viz.plots import plot_match_topdown

__all__ = ["match_figure", "plot_match_topdown", "write_match_view"]
