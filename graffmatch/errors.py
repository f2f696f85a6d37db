"""Exceptions raised by graffmatch.

They all derive from :class:`GraffMatchError` so that callers (and the CLI) can catch the
library's own failures in one place and show them as one clear line.
"""

from __future__ import annotations


class GraffMatchError(Exception):
    """Base class of every error graffmatch raises on purpose."""


class InvalidInputError(GraffMatchError, ValueError):
    """Input arrays have NaN/Inf, wrong shapes, non-orthonormal bases or are empty."""


class MissingPosesError(InvalidInputError):
    """A dataset without ground-truth poses was asked for them (an evaluation, simulated drift); the message names
    the file that was looked for and what runs without it."""


class DegenerateGeometryError(GraffMatchError):
    """The geometry does not determine the requested quantity (e.g. only parallel planes)."""


class MalformedFileError(GraffMatchError, OSError):
    """A file could not be parsed; the message names the file."""


class PrecisionLossWarning(UserWarning):
    """Casting coordinates to float32 moved points by more than the tolerance (far/UTM
    coordinates read without recentring); read them with ``graffmatch.lidar.io.read_scan``."""
