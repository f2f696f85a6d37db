"""Interactive 3D views and static plots of matches (tools layer)."""

from graffmatch.viz.match_view import match_figure, write_match_view

__all__ = ["match_figure", "write_match_view"]
