"""The whole configuration of the ``graffmatch`` tool as ONE pydantic model, after kiss-icp.

``Settings`` aggregates the library's own configs (matcher, extractor, ...) plus the tool's
(view, ICP). It round-trips through YAML (``graffmatch config dump`` -> edit ->
``graffmatch --config FILE.yaml``) and takes environment overrides of the form
``GRAFFMATCH_<SECTION>__<FIELD>[__<SUBFIELD>]=value`` (the value is parsed as YAML, so
``GRAFFMATCH_MATCHER__RHO=20`` is the float 20 and ``GRAFFMATCH_MATCHER__LANDMARK_TYPES=[line]``
is a list). Overrides apply after the file, so the environment wins, as in pydantic-settings.

The library configs are imported defensively: the tool must still start (and say which part is
missing) when one sub-package fails to import, instead of dying on ``graffmatch --help``.
"""

from __future__ import annotations

import importlib
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from graffmatch.errors import InvalidInputError, MalformedFileError

ENV_PREFIX = "GRAFFMATCH_"
ENV_SEPARATOR = "__"


class _Unavailable(BaseModel):
    """Stand-in for a library config whose module failed to import (keeps the tool usable)."""

    model_config = ConfigDict(extra="allow")


def _optional_model(module: str, name: str) -> type[BaseModel]:
    try:
        cls = getattr(importlib.import_module(module), name)
    except (ImportError, AttributeError):
        return _Unavailable
    return cls if isinstance(cls, type) and issubclass(cls, BaseModel) else _Unavailable


MatcherConfig = _optional_model("graffmatch.matcher", "GraffMatchConfig")
ExtractorConfig = _optional_model("graffmatch.lidar.extractor", "LandmarkExtractorConfig")
LidarLidarConfig = _optional_model("graffmatch.calibration.lidar_lidar", "LidarLidarConfig")
CameraDepthConfig = _optional_model("graffmatch.calibration.camera_depth", "CameraDepthConfig")


class IcpConfig(BaseModel):
    """ICP refinement on the support points of the matched landmarks (``--refine icp``)."""

    model_config = ConfigDict(extra="forbid")

    max_correspondence_distance: float = Field(
        0.5,
        gt=0,
        description="Largest point-pair distance ICP accepts as a match [m] (as "
        "graffmatch.register_scans).",
    )
    max_iterations: int = Field(30, ge=1, description="ICP iterations at most.")
    point_to_plane: bool = Field(
        True, description="Point-to-plane ICP (normals on the target); else point-to-point."
    )
    normal_radius: float = Field(
        1.0, gt=0, description="Radius of the target normal estimation (point-to-plane) [m]."
    )


class GroundTruthConfig(BaseModel):
    """How associations are judged against a ground-truth transform (``--gt``)."""

    model_config = ConfigDict(extra="forbid")

    tau_d_deg: float = Field(
        6.0,
        gt=0,
        description="An association is an inlier if its GT-aligned d_Graff < tau_d [deg].",
    )
    max_rotation_deg: float = Field(
        5.0, gt=0, description="A registration succeeds within this rotation error [deg]."
    )
    max_translation_m: float = Field(
        1.0, gt=0, description="A registration succeeds within this translation error [m]."
    )


class ViewConfig(BaseModel):
    """The interactive HTML view (``--view``, ``graffmatch view``)."""

    model_config = ConfigDict(extra="forbid")

    max_points: int = Field(
        25_000, ge=0, description="Points drawn per scan at most (uniform, seeded subset)."
    )
    initial: Literal["after", "raw", "side"] = Field(
        "after",
        description="State shown when the page opens: 'after' alignment, 'raw' frames (before) "
        "or 'side' by side (before, with the correspondences readable).",
    )


class InputConfig(BaseModel):
    """How scans given on the command line are read."""

    model_config = ConfigDict(extra="forbid")

    labels: Literal["auto", "never"] = Field(
        "auto",
        description="'auto' uses SemanticKITTI labels found next to a scan "
        "(velodyne/NNNNNN.bin -> labels/NNNNNN.label); 'never' ignores them.",
    )


class CalibrationSettings(BaseModel):
    """Extrinsic calibration from planar boards (``graffmatch calibrate``)."""

    model_config = ConfigDict(extra="forbid")

    lidar_lidar: LidarLidarConfig = Field(  # type: ignore[valid-type]
        default_factory=LidarLidarConfig, description="LiDAR-LiDAR: board planes + GraffMatch."
    )
    camera_depth: CameraDepthConfig = Field(  # type: ignore[valid-type]
        default_factory=CameraDepthConfig,
        description="Camera-depth: chessboard PnP planes, depth planes + GraffMatch.",
    )


class Settings(BaseModel):
    """Every setting of the tool; ``graffmatch config dump`` prints it with the defaults."""

    model_config = ConfigDict(extra="forbid")

    matcher: MatcherConfig = Field(  # type: ignore[valid-type]
        default_factory=MatcherConfig, description="GraffMatch matcher (paper defaults)."
    )
    extractor: ExtractorConfig = Field(  # type: ignore[valid-type]
        default_factory=ExtractorConfig, description="LiDAR landmark extraction (poles, planes)."
    )
    input: InputConfig = Field(default_factory=InputConfig, description="Reading scans.")
    icp: IcpConfig = Field(default_factory=IcpConfig, description="ICP refinement.")
    ground_truth: GroundTruthConfig = Field(
        default_factory=GroundTruthConfig, description="Judging results against ground truth."
    )
    view: ViewConfig = Field(default_factory=ViewConfig, description="Interactive 3D view.")
    calibration: CalibrationSettings = Field(
        default_factory=CalibrationSettings, description="Extrinsic calibration."
    )


def missing_sections() -> list[str]:
    """Names of sections whose library module could not be imported."""
    return [
        name for name, info in Settings.model_fields.items() if info.default_factory is _Unavailable
    ]


# ----------------------------------------------------------------------------------------------
# environment overrides
# ----------------------------------------------------------------------------------------------
def _field_model(model: type[BaseModel], key: str) -> type[BaseModel] | None:
    info = model.model_fields.get(key)
    if info is None:
        return None
    ann = info.annotation
    return ann if isinstance(ann, type) and issubclass(ann, BaseModel) else None


def env_overrides(environ: Mapping[str, str] | None = None) -> dict[str, Any]:
    """Nested dict of ``GRAFFMATCH_SECTION__FIELD=value`` overrides (values parsed as YAML).

    Variables whose first segment is not a section (e.g. ``GRAFFMATCH_SHARED_DATA``) are not
    overrides and are ignored; a known section with an unknown field is an error, so a typo
    does not pass silently.
    """
    environ = os.environ if environ is None else environ
    out: dict[str, Any] = {}
    for name in sorted(environ):
        if not name.startswith(ENV_PREFIX) or ENV_SEPARATOR not in name:
            continue
        path = name[len(ENV_PREFIX) :].lower().split(ENV_SEPARATOR)
        if path[0] not in Settings.model_fields or any(not p for p in path):
            continue
        model: type[BaseModel] | None = Settings
        for depth, key in enumerate(path):
            if model is None or (
                key not in model.model_fields and not model.model_config.get("extra") == "allow"
            ):
                raise InvalidInputError(
                    f"environment override {name}: unknown setting {'.'.join(path[: depth + 1])!r}"
                )
            model = _field_model(model, key) if model is not None else None
        try:
            value = yaml.safe_load(environ[name])
        except yaml.YAMLError as exc:
            raise InvalidInputError(f"environment override {name}: not valid YAML ({exc})") from exc
        node = out
        for key in path[:-1]:
            node = node.setdefault(key, {})
        node[path[-1]] = value
    return out


def _deep_merge(base: dict[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in over.items():
        if isinstance(v, Mapping) and isinstance(out.get(k), dict):
            out[k] = _deep_merge(out[k], v)
        else:
            out[k] = v
    return out


# ----------------------------------------------------------------------------------------------
# loading and dumping
# ----------------------------------------------------------------------------------------------
def _format_validation_error(exc: ValidationError, source: str) -> str:
    parts = []
    for err in exc.errors()[:3]:
        loc = ".".join(str(x) for x in err["loc"])
        parts.append(f"{loc}: {err['msg']}")
    more = f" (+{len(exc.errors()) - 3} more)" if len(exc.errors()) > 3 else ""
    return f"invalid configuration in {source}: " + "; ".join(parts) + more


def load_settings(
    path: str | Path | None = None, environ: Mapping[str, str] | None = None
) -> Settings:
    """Defaults, then the YAML file (if any), then environment overrides."""
    data: dict[str, Any] = {}
    source = "defaults"
    if path is not None:
        path = Path(path)
        source = str(path)
        try:
            text = path.read_text()
        except FileNotFoundError as exc:
            raise MalformedFileError(f"{path}: configuration file not found") from exc
        try:
            loaded = yaml.safe_load(text)
        except yaml.YAMLError as exc:
            raise MalformedFileError(f"{path}: not valid YAML ({exc})") from exc
        if loaded is None:
            loaded = {}
        if not isinstance(loaded, dict):
            raise MalformedFileError(f"{path}: expected a mapping at the top level")
        data = loaded
    env = env_overrides(environ)
    if env:
        data = _deep_merge(data, env)
        source += " + environment"
    try:
        return Settings.model_validate(data)
    except ValidationError as exc:
        raise InvalidInputError(_format_validation_error(exc, source)) from exc


def _scalar_yaml(value: Any) -> str:
    text = yaml.safe_dump(value, default_flow_style=True, sort_keys=False, width=10_000).strip()
    return text.removesuffix("\n...").removesuffix("...").strip()


def _dump_model(model: BaseModel, indent: int, lines: list[str]) -> None:
    pad = "  " * indent
    data = model.model_dump(mode="json")
    fields = type(model).model_fields
    for key, value in data.items():
        info = fields.get(key)
        if info is not None and info.description:
            lines.append(f"{pad}# {' '.join(info.description.split())}")
        child = getattr(model, key, None)
        if isinstance(child, BaseModel):
            lines.append(f"{pad}{key}:")
            before = len(lines)
            _dump_model(child, indent + 1, lines)
            if len(lines) == before:
                lines[-1] = f"{pad}{key}: {{}}"
        else:
            lines.append(f"{pad}{key}: {_scalar_yaml(value)}")


def dump_settings(settings: Settings) -> str:
    """YAML of every setting, each preceded by its description as a comment."""
    lines = [
        "# graffmatch configuration: every setting with its value.",
        "# Use with: graffmatch --config THIS_FILE.yaml <command> ...",
        f"# Environment overrides: {ENV_PREFIX}<SECTION>{ENV_SEPARATOR}<FIELD>=value",
    ]
    _dump_model(settings, 0, lines)
    return "\n".join(lines) + "\n"


def dump_model(model: BaseModel, header: str = "") -> str:
    """Commented YAML of any pydantic config (e.g. a suite's LoopClosureConfig)."""
    lines = [f"# {ln}" for ln in header.splitlines()]
    _dump_model(model, 0, lines)
    return "\n".join(lines) + "\n"


def save_settings(settings: Settings, path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(dump_settings(settings))
    return path
