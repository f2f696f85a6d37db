"""Moved to :mod:`graffmatch.viz.report_views` (it runs the matcher and draws: not CLI work)."""

from graffmatch.viz.report_views import (
    SECTION_TITLE,
    VIEWS_DIR,
    benchmark_folder_of,
    write_report_views,
)

__all__ = ["SECTION_TITLE", "VIEWS_DIR", "benchmark_folder_of", "write_report_views"]
