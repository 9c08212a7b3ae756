"""Pydantic v2 models of every ``wire-v1`` message (see ``docs/wire.md``).

Field names, types and defaults are those of the contract; the optional project additions are
marked as such. Validation is strict and precise:

* numbers: ``int`` or ``float`` (numpy scalars too when built in Python); a ``bool`` or a string
  is never a number, and a float is never an integer (``seq``, counters);
* every float is finite, except the values inside ``Scan.ranges`` (there NaN, inf or anything
  outside ``[range_min, range_max]`` means "no return");
* identifiers are 1-64 characters of ``[A-Za-z0-9_.-]``;
* pose angles are normalised to (-pi, pi] on input;
* unknown keys are ignored (forward compatibility with later optional fields).

Array-valued fields are exposed as read-only float64 numpy arrays: poses ``(3,)``, ranges
``(n,)``, polylines a tuple of ``(k, 2)`` arrays, covariance ``(3, 3)``.

Every validation failure raises :class:`service.errors.InvalidMessage` (also when a model is
built directly in Python); the text is ``<field path>: <reason>``, e.g. ``pose[2]: must be
finite``. ``model_copy(update=...)`` does not validate: build a new model instead.
"""

from __future__ import annotations

from typing import Annotated, Any, ClassVar, Literal, Self, get_args

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator
from pydantic.functional_validators import PlainValidator
from pydantic.json_schema import WithJsonSchema

from schemas.fields import (
    ID_PATTERN,
    NUM_SCHEMA,
    Count,
    CountDict,
    FieldError,
    FiniteFloat,
    Ident,
    OptIdent,
    OptPose3,
    Pose3,
    UnitFloat,
    as_validator,
    check_candidates,
    check_count,
    check_covariance,
    check_finite,
    check_ident,
    check_polylines,
    check_ranges,
    custom_error,
    format_validation_error,
    nullable_schema,
    optional_check,
    text_check,
    type_name,
    wire_type_name,
    wrap_pi,
)
from schemas.limits import (
    MAX_BEAMS,
    MAX_CANDIDATES,
    MAX_FOV,
    MAX_KEY_LEN,
    MAX_MAP_POINTS,
    MAX_POLYLINES,
    MAX_TEXT_LEN,
    MAX_UINT,
)
from service.errors import InvalidMessage

__all__ = [
    "MESSAGES",
    "METHODS",
    "ErrorNotice",
    "Health",
    "Map",
    "Method",
    "PoseMsg",
    "RobotConfig",
    "Scan",
    "Truth",
    "WireModel",
    "format_validation_error",
    "wire_type_name",
    "wrap_pi",
]

#: The localisation methods a robot may be configured with (``RobotConfig.method``). The wire
#: owns these names; ``service.core.types.METHODS`` is the core's equal copy (a test checks).
Method = Literal["shape", "icp", "lines"]
METHODS: tuple[str, ...] = get_args(Method)


class WireModel(BaseModel):
    """Base of every wire message: strict, immutable, unknown keys ignored.

    Construction (``Model(**fields)`` or :meth:`parse`) raises ``InvalidMessage`` on any
    violation. Equality compares array fields element-wise (NaN equals NaN).
    """

    model_config = ConfigDict(
        extra="ignore",
        frozen=True,
        arbitrary_types_allowed=True,
        hide_input_in_errors=True,
        revalidate_instances="never",
    )

    #: Key of the file in ``schemas/json/`` (``<schema_name>.schema.json``).
    schema_name: ClassVar[str] = ""

    def __init__(self, /, **data: Any) -> None:
        try:
            super().__init__(**data)
        except ValidationError as e:
            raise InvalidMessage(format_validation_error(e)) from None

    @classmethod
    def parse(cls, obj: object) -> Self:
        """Validate a decoded payload (a dict with string keys) into this model."""
        if not isinstance(obj, dict):
            raise InvalidMessage(f"message: must be a map, got {type_name(obj)}")
        if not all(isinstance(k, str) for k in obj):
            raise InvalidMessage("message: keys must be strings")
        # Going through __init__ (not model_validate) keeps the error text free of pydantic's
        # "Value error" wrapping: a custom __init__ is what model_validate calls anyway.
        return cls(**obj)

    @classmethod
    def model_validate(cls, obj: Any, *args: Any, **kwargs: Any) -> Self:
        """As pydantic's, but failures raise ``InvalidMessage`` (prefer :meth:`parse`)."""
        try:
            return super().model_validate(obj, *args, **kwargs)
        except ValidationError as e:
            raise InvalidMessage(format_validation_error(e)) from None

    def __eq__(self, other: object) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        for name in type(self).model_fields:
            a, b = getattr(self, name), getattr(other, name)
            if isinstance(a, tuple) and isinstance(b, tuple):
                if len(a) != len(b) or not all(_same(x, y) for x, y in zip(a, b, strict=True)):
                    return False
            elif not _same(a, b):
                return False
        return True

    __hash__ = None  # type: ignore[assignment]

    def to_wire(self, ranges_as_bytes: bool = False) -> dict[str, Any]:
        """Plain dict of wire types (lists of floats, no numpy); ``None`` fields are left out."""
        out: dict[str, Any] = {}
        for name in type(self).model_fields:
            value = getattr(self, name)
            if value is None:
                continue
            out[name] = _plain(value)
        return out


def _zero_pose() -> np.ndarray:
    z = np.zeros(3, dtype=np.float64)
    z.setflags(write=False)
    return z


def _same(a: object, b: object) -> bool:
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return (
            isinstance(a, np.ndarray)
            and isinstance(b, np.ndarray)
            and a.shape == b.shape
            and bool(np.array_equal(a, b, equal_nan=True))
        )
    return a == b


def _plain(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.reshape(-1).tolist() if value.shape == (3, 3) else value.tolist()
    if isinstance(value, tuple):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return dict(value)
    return value


# --------------------------------------------------------------------------- messages


class Map(WireModel):
    """A map: ``put <prefix>/maps/<map_id>``. Coordinates in metres, map frame.

    ``polylines``: each at least 2 points; a closed ring repeats its first point last.
    Exposed as a tuple of read-only ``(k, 2)`` float64 arrays.
    """

    schema_name: ClassVar[str] = "map"

    map_id: Ident = Field(description="Must equal the <map_id> of the key.")
    kind: Literal["metric", "schematic"] = Field(
        description="metric: exact map; schematic: room outlines only (no furniture)."
    )
    polylines: Annotated[
        tuple[np.ndarray, ...],
        PlainValidator(as_validator(check_polylines)),
        WithJsonSchema(
            {
                "type": "array",
                "minItems": 1,
                "maxItems": MAX_POLYLINES,
                "items": {
                    "type": "array",
                    "minItems": 2,
                    "items": {
                        "type": "array",
                        "items": {"type": "number"},
                        "minItems": 2,
                        "maxItems": 2,
                    },
                },
                "description": (
                    f"Polylines of [x, y] points in metres (map frame); at most "
                    f"{MAX_MAP_POINTS} points in total; a closed ring repeats its first point."
                ),
            }
        ),
    ]
    name: Annotated[
        str | None,
        PlainValidator(as_validator(optional_check(text_check(MAX_TEXT_LEN, allow_empty=True)))),
        WithJsonSchema(nullable_schema({"type": "string", "maxLength": MAX_TEXT_LEN})),
    ] = Field(default=None, description="Optional human-readable name.")


class RobotConfig(WireModel):
    """Robot configuration: ``put <prefix>/robots/<robot_id>/config`` (resets its localiser)."""

    schema_name: ClassVar[str] = "robot_config"

    map_id: Ident = Field(description="Id of the map to localise against.")
    method: Method = Field(default="shape", description="Localisation method.")
    initial_pose: OptPose3 = Field(
        default=None,
        description="Initial pose of the robot base in the map frame; null: global localisation.",
    )
    laser_offset: Pose3 = Field(
        default_factory=lambda: _zero_pose(),
        description="Project addition: pose [x, y, theta] of the laser on the robot base "
        "(base frame, REP 103: x forward, y left; metres, radians). Scans are in the laser's "
        "frame; odometry, initial_pose and the published poses are the base's. Absent: "
        "[0, 0, 0], the laser at the base's origin facing forward.",
        json_schema_extra={"default": [0.0, 0.0, 0.0]},
    )

    def to_wire(self, ranges_as_bytes: bool = False) -> dict[str, Any]:
        """As :meth:`WireModel.to_wire`; a zero ``laser_offset`` is left out (absent means
        zero, so the payload stays what a service without the field expects)."""
        out = super().to_wire()
        if not np.any(self.laser_offset):
            out.pop("laser_offset", None)
        return out


class Scan(WireModel):
    """One laser scan: ``put <prefix>/robots/<robot_id>/scan``.

    Beam ``i`` points at ``angle_min + i * angle_increment`` (radians, robot frame, REP 103);
    the laser sits at the robot origin. ``ranges`` (metres) is a read-only float64 array of
    the raw values; NaN, inf or anything outside ``[range_min, range_max]`` means "no return"
    (``schemas.codec.scan_arrays`` maps all of them to NaN).
    """

    schema_name: ClassVar[str] = "scan"

    seq: Count = Field(description="Sequence number, >= 0.")
    stamp: FiniteFloat = Field(description="Acquisition time, seconds.")
    angle_min: FiniteFloat = Field(description="Angle of beam 0, radians, robot frame.")
    angle_increment: Annotated[
        float,
        PlainValidator(as_validator(check_finite)),
        WithJsonSchema({"type": "number", "exclusiveMinimum": 0}),
    ] = Field(description="Angle between consecutive beams, radians, > 0.")
    range_min: Annotated[
        float,
        PlainValidator(as_validator(check_finite)),
        WithJsonSchema({"type": "number", "minimum": 0}),
    ] = Field(description="Shortest valid range, metres, >= 0.")
    range_max: FiniteFloat = Field(description="Longest valid range, metres, > range_min.")
    ranges: Annotated[
        np.ndarray,
        PlainValidator(as_validator(check_ranges)),
        WithJsonSchema(
            {
                "type": "array",
                "items": {"anyOf": [{"type": "number"}, {"type": "null"}]},
                "minItems": 1,
                "maxItems": MAX_BEAMS,
                "description": (
                    "Ranges in metres, one per beam. In msgpack this may instead be a binary "
                    "string of little-endian float32 values. NaN, inf, null or a value "
                    "outside [range_min, range_max] means no return."
                ),
            }
        ),
    ]
    odom: OptPose3 = Field(
        default=None, description="Odometry pose [x, y, theta] in its own frame (optional)."
    )

    @model_validator(mode="after")
    def _geometry(self) -> Self:
        try:
            if self.angle_increment <= 0.0:
                raise FieldError(f"must be > 0, got {self.angle_increment!r}", "angle_increment")
            if self.range_min < 0.0:
                raise FieldError(f"must be >= 0, got {self.range_min!r}", "range_min")
            if not self.range_min < self.range_max:
                raise FieldError(
                    f"must be > range_min ({self.range_min!r}), got {self.range_max!r}",
                    "range_max",
                )
            fov = (len(self.ranges) - 1) * self.angle_increment
            if fov > MAX_FOV:
                raise FieldError(
                    f"{len(self.ranges)} beams x {self.angle_increment!r} rad spans "
                    f"{fov:.6g} rad, more than 2*pi",
                    "angle_increment",
                )
        except FieldError as f:
            raise custom_error(f) from None
        return self

    def to_wire(self, ranges_as_bytes: bool = False) -> dict[str, Any]:
        """As :meth:`WireModel.to_wire`; ``ranges_as_bytes`` packs ranges as little-endian
        float32 bytes (msgpack only; values are rounded to float32)."""
        out = super().to_wire()
        if ranges_as_bytes:
            out["ranges"] = self.ranges.astype("<f4").tobytes()
        return out


_STATUS = Literal["tracking", "lost", "initializing"]
_STATE = Literal["tracking", "dead_reckoning", "searching", "probation"]


class PoseMsg(WireModel):
    """A pose estimate: published on ``<prefix>/robots/<robot_id>/pose`` after every scan.

    ``seq``/``stamp`` are those of the scan it answers; ``pose`` is in the map frame.
    ``covariance``, ``explained``, ``ambiguity``, ``hypotheses``, ``candidates``, ``odom`` and
    ``state`` are project additions (optional).
    """

    schema_name: ClassVar[str] = "pose"

    robot_id: Ident
    seq: Count = Field(description="seq of the scan this estimate answers.")
    stamp: FiniteFloat = Field(description="stamp of the scan this estimate answers, seconds.")
    pose: Pose3 = Field(description="[x, y, theta] in the map frame.")
    status: _STATUS
    score: FiniteFloat = Field(description="Match quality (method-specific; higher is better).")
    method: Ident = Field(description="Localisation method that produced the estimate.")
    map_id: Ident
    latency_ms: FiniteFloat = Field(description="Scan received -> estimate published, ms.")
    covariance: Annotated[
        np.ndarray | None,
        PlainValidator(as_validator(optional_check(check_covariance))),
        WithJsonSchema(
            nullable_schema(
                {
                    "type": "array",
                    "items": {"type": "number"},
                    "minItems": 9,
                    "maxItems": 9,
                    "description": "Row-major 3x3 covariance of [x, y, theta].",
                }
            )
        ),
    ] = Field(default=None, description="Project addition: 3x3 pose covariance (exposed 3x3).")
    explained: UnitFloat = Field(
        default=None,
        description="Project addition: fraction of the scan explained by the map, [0, 1].",
    )
    ambiguity: UnitFloat = Field(
        default=None,
        description="Project addition, during a search: the probability that the best "
        "hypothesis is not the place, 1 / (1 + e^LLR) of the relocalisation's decision, "
        "[0, 1] (1: no place leads yet).",
    )
    hypotheses: Annotated[
        int | None,
        PlainValidator(as_validator(optional_check(check_count))),
        WithJsonSchema(nullable_schema({"type": "integer", "minimum": 0, "maximum": MAX_UINT})),
    ] = Field(
        default=None,
        description="Project addition: live pose hypotheses of a global search (initializing "
        "or lost); absent while tracking.",
    )
    candidates: Annotated[
        np.ndarray | None,
        PlainValidator(as_validator(optional_check(check_candidates))),
        WithJsonSchema(
            nullable_schema(
                {
                    "type": "array",
                    "maxItems": MAX_CANDIDATES,
                    "items": {
                        "type": "array",
                        "items": {"type": "number"},
                        "minItems": 4,
                        "maxItems": 4,
                    },
                    "description": "Best hypotheses first: [x, y, theta, cost] (map frame; "
                    "lower cost is better).",
                }
            )
        ),
    ] = Field(
        default=None,
        description="Project addition: the best few pose hypotheses of a global search.",
    )
    odom: OptPose3 = Field(
        default=None,
        description=(
            "Project addition: the odometry pose of the scan this estimate answers (absent "
            "if it carried none), so that another service instance can take the robot over."
        ),
    )
    state: _STATE | None = Field(
        default=None,
        description=(
            "Project addition: the localiser's state behind the status (shape method; absent "
            "for methods without one). tracking: the map confirms the pose (status "
            "tracking). dead_reckoning: the map does not explain the scans; the pose is "
            "carried by the odometry, its covariance growing (status lost). searching: a "
            "global search, the pose its best guess (status initializing, or lost after a "
            "fix). probation: a search's winner tracked before it is published (the same)."
        ),
    )


def _ident_list(v: object) -> list[str]:
    if not isinstance(v, (list, tuple)):
        raise FieldError(f"must be a list, got {type_name(v)}")
    if len(v) > MAX_POLYLINES:
        raise FieldError(f"{len(v)} entries exceeds limit {MAX_POLYLINES}")
    out = []
    for i, x in enumerate(v):
        try:
            out.append(check_ident(x))
        except FieldError as e:
            raise FieldError(e.reason, f"[{i}]") from None
    return out


def _ms_stats(v: object) -> dict[str, float]:
    if not isinstance(v, dict):
        raise FieldError(f"must be a map, got {type_name(v)}")
    if len(v) > 16:
        raise FieldError(f"{len(v)} entries exceeds limit 16")
    out: dict[str, float] = {}
    for k, x in v.items():
        if not isinstance(k, str) or not 1 <= len(k) <= 16:
            raise FieldError(f"key {k!r} must be a string of 1-16 characters")
        out[k] = check_finite(x, f"[{k!r}]")
    return out


def _bool(v: object) -> bool:
    if not isinstance(v, (bool, np.bool_)):
        raise FieldError(f"must be a boolean, got {type_name(v)}")
    return bool(v)


_OPT_BOOL = Annotated[
    bool | None,
    PlainValidator(as_validator(optional_check(_bool))),
    WithJsonSchema(nullable_schema({"type": "boolean"})),
]
_IDENT_LIST = Annotated[
    list[str] | None,
    PlainValidator(as_validator(optional_check(_ident_list))),
    WithJsonSchema(
        nullable_schema({"type": "array", "items": {"type": "string", "pattern": ID_PATTERN}})
    ),
]
_MS_STATS = Annotated[
    dict[str, float] | None,
    PlainValidator(as_validator(optional_check(_ms_stats))),
    WithJsonSchema(nullable_schema({"type": "object", "additionalProperties": NUM_SCHEMA})),
]


class Health(WireModel):
    """Service health: reply to ``get <prefix>/service/health``.

    ``instance_id``, ``uptime_s``, ``errors``, ``robots_by_status``, ``ready``, ``maps_ready``,
    ``maps_indexed`` and ``scan_cpu_ms`` are project additions.

    What to wait for before robots start: a map put is acknowledged by its id in
    ``maps_ready`` (the client library: ``put_map(..., ready=True)``), once all of the map's
    first-use work is done (prepared on every worker, view index of global localisation
    built). Robots configured on a ready map are localised at full speed from their first
    scan, with or without an initial pose; before that they are served, but their first
    scans may wait and share the cores with the map's preparation.
    """

    schema_name: ClassVar[str] = "health"

    status: Annotated[
        str,
        PlainValidator(as_validator(text_check(64, allow_empty=False))),
        WithJsonSchema({"type": "string", "minLength": 1, "maxLength": 64}),
    ] = Field(description='"ok" when serving.')
    version: Annotated[
        str,
        PlainValidator(as_validator(text_check(256, allow_empty=False))),
        WithJsonSchema({"type": "string", "minLength": 1, "maxLength": 256}),
    ]
    robots: Count
    maps: Count
    scans_processed: Count
    scans_rejected: Count
    instance_id: OptIdent = Field(
        default=None, description="Project addition: id of the answering service instance."
    )
    uptime_s: Annotated[
        float | None,
        PlainValidator(as_validator(optional_check(check_finite))),
        WithJsonSchema(nullable_schema(NUM_SCHEMA)),
    ] = Field(default=None, description="Project addition: seconds since the service started.")
    errors: CountDict = Field(
        default=None, description="Project addition: rejected messages per error kind."
    )
    robots_by_status: CountDict = Field(
        default=None, description="Project addition: number of robots per tracking status."
    )
    ready: _OPT_BOOL = Field(
        default=None,
        description=(
            "Project addition: true once the service's workers have warmed up (methods "
            "imported, compiled kernels loaded, each method run once) and every stored map "
            "is in maps_ready; false while it is still preparing."
        ),
    )
    maps_ready: _IDENT_LIST = Field(
        default=None,
        description=(
            "Project addition: ids of the stored maps whose first-use work is done: every "
            "tracking worker holds the map prepared (map model, ray caster, a synthetic scan "
            "localised on it) and, with a search worker, its view index is built (or its "
            "build failed). The acknowledgement of a map put: robots on such a map are "
            "localised at full speed from their first scan. A map put again leaves this "
            "list until the new version is ready (a second for an office, ~10 s of CPU for "
            "a large building the first time it is stored; a stored map's index is cached)."
        ),
    )
    maps_indexed: _IDENT_LIST = Field(
        default=None,
        description=(
            "Project addition: ids of the stored maps whose view index of global "
            "localisation is built (by the search worker, right after the map is stored): "
            "robots without an initial pose start their search without waiting for it. A "
            "map whose index build failed is ready but not listed here. Absent when the "
            "service has no search worker (the first search then builds the index)."
        ),
    )
    scan_cpu_ms: _MS_STATS = Field(
        default=None,
        description=(
            "Project addition: CPU milliseconds per processed scan over the last 4096 "
            "scans, keys p50, p99, mean and n: the service process's threads (decoding and "
            "validating the scan, scheduling, building and publishing the pose) plus the "
            "worker's localisation; Zenoh's own threads are not counted."
        ),
    )


class ErrorNotice(WireModel):
    """One rejected message: published on ``<prefix>/errors``."""

    schema_name: ClassVar[str] = "error_notice"

    key: Annotated[
        str,
        PlainValidator(as_validator(text_check(MAX_KEY_LEN, allow_empty=False))),
        WithJsonSchema({"type": "string", "minLength": 1, "maxLength": MAX_KEY_LEN}),
    ] = Field(description="Key expression of the rejected message.")
    error: Annotated[
        str,
        PlainValidator(as_validator(text_check(MAX_TEXT_LEN, allow_empty=False))),
        WithJsonSchema({"type": "string", "minLength": 1, "maxLength": MAX_TEXT_LEN}),
    ] = Field(description="Why it was rejected.")

    @classmethod
    def make(cls, key: str, error: str) -> ErrorNotice:
        """Build a notice, truncating over-long ``key``/``error`` text to the limits."""
        k = key[:MAX_KEY_LEN] or "?"
        e = error if len(error) <= MAX_TEXT_LEN else error[: MAX_TEXT_LEN - 3] + "..."
        return cls(key=k, error=e or "unknown error")


class Truth(WireModel):
    """Ground-truth pose from the simulator: ``<prefix>/robots/<robot_id>/truth``."""

    schema_name: ClassVar[str] = "truth"

    seq: Count = Field(description="seq of the scan taken at this pose.")
    stamp: FiniteFloat = Field(description="stamp of that scan, seconds.")
    pose: Pose3 = Field(description="True [x, y, theta] in the map frame.")


#: Every wire message, in a stable order.
MESSAGES: tuple[type[WireModel], ...] = (
    Map,
    RobotConfig,
    Scan,
    PoseMsg,
    Health,
    ErrorNotice,
    Truth,
)
