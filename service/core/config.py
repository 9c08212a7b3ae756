"""The ``shape`` localiser's configuration as one tree: a named preset and the knobs a user may
turn (:class:`LocalizerConfig`).

The tree::

    LocalizerConfig
    ├── preset        "metric" (a map drawn from the robot's scans) | "floor_plan"
    ├── knobs         Knobs: the documented settings a user may change (None: the preset's)
    ├── tracking()    -> ShapeConfig   the tracker: extraction, matching, fit, motion model
    │                    (service.core.tracking.shape_config, ~70 internal settings)
    └── reloc()       -> GlobalConfig  relocalisation: view index, search, evidence, decision,
                         the integrity of tracking (service.core.reloc.config)

Every internal setting carries its reason in its ``description`` (relocalisation's that no
preset changes are named constants of the modules that use them, each with its reason); the
presets are :meth:`ShapeConfig.for_kind` and :meth:`GlobalConfig.for_kind` (``floor_plan`` is
the map kind ``schematic``). A knob left ``None`` keeps the preset's value; a knob set
overrides it in the section it belongs to.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from service.core.reloc.config import GlobalConfig
from service.core.tracking.shape_config import ShapeConfig

Preset = Literal["metric", "floor_plan"]
#: The map kind of each preset.
KIND: dict[str, str] = {"metric": "metric", "floor_plan": "schematic"}


class Knobs(BaseModel):
    """What a user may turn (``None``: the preset's value). Units: metres, radians, nats,
    reference milliseconds."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    use_odometry: bool | None = Field(
        None,
        description="Use the odometry sent with the scans as the tracker's motion prior and "
        "for dead reckoning (off: the paper's no-odometry mode). Default on.",
    )
    scan_odometry: bool | None = Field(
        None,
        description="Correct each odometry increment by matching the scan to the previous one "
        "before any use (off: as received). Default on.",
    )
    odometry_noise: float | None = Field(
        None,
        gt=0,
        description="Scale of the odometry noise model (the alpha terms): 2 for an odometry "
        "twice as noisy as the tuning logs'. Sets the tracker's prior and how fast a "
        "dead-reckoned pose's covariance grows. Default 1.",
    )
    max_range: float | None = Field(
        None,
        gt=0,
        description="Returns beyond this (m) are not matched (the map view's range): below the "
        "laser's range where its far returns are unreliable. Default 15.",
    )
    search_budget_ms: float | None = Field(
        None,
        ge=0,
        description="Work a global search may do per scan (reference ms; None: a whole "
        "search per scan). The service sets 50.",
    )
    lost_after: int | None = Field(
        None,
        ge=1,
        description="Scans in a row the map must contradict (beams through drawn walls) before "
        "a search starts. Default 3.",
    )
    track_sigma: float | None = Field(
        None,
        gt=0,
        description="A scan the map explains poorly is published as tracking only while the "
        "odometry's position sigma since the last well-explained scan is below this (m); "
        "beyond, the robot dead-reckons (status lost). Default 0.15.",
    )
    max_dead_reckoning_sigma: float | None = Field(
        None,
        gt=0,
        description="Dead reckoning gives way to a global search (its pose the prior) once "
        "its position sigma exceeds this (m). Default 3.",
    )
    relock_scans: int | None = Field(
        None,
        ge=1,
        description="Scans in a row the map must explain well near the dead-reckoned pose to "
        "track again. Default 3.",
    )
    fix_llr: float | None = Field(
        None,
        gt=0,
        description="Evidence (nats) the best place must have over all others before a search "
        "fixes it: higher is safer and slower. Default: the preset's, set from the false-fix "
        "rate on the tuning split.",
    )
    kidnap_weight: float | None = Field(
        None,
        gt=0,
        le=1,
        description="After a loss, the prior share of 'carried elsewhere' against 'near the "
        "dead-reckoned pose'. Default 0.01.",
    )
    probation_travel: float | None = Field(
        None,
        ge=0,
        description="With odometry, a search's winner is tracked this far (m) before it is "
        "published. Default 0 (metric), 2 (floor plan).",
    )
    evidence_span: float | None = Field(
        None,
        gt=0,
        description="A search judges its places on the keyframes of the last this many metres "
        "at a time. Default 6.",
    )
    keep: int | None = Field(
        None, ge=1, description="Places a search keeps judged (and as many being judged). 8."
    )
    min_support: float | None = Field(
        None,
        gt=0,
        le=1,
        description="The tracker rejects a fit that explains less than this share of the scan "
        "(and keeps the motion prior). Default 0.3.",
    )
    settle_scans: int | None = Field(
        None,
        ge=0,
        description="Scans after a search's fix during which a service keeps the robot on its "
        "search worker. Default 20.",
    )


#: Which section each knob sets, and under which name there.
_TRACKING = {
    "lost_after": "lost_after",
    "max_range": "view_max_range",
    "min_support": "min_support",
}
_RELOC = {
    "search_budget_ms": "search_budget_ms",
    "track_sigma": "track_sigma",
    "max_dead_reckoning_sigma": "max_dead_reckoning_sigma",
    "relock_scans": "relock_scans",
    "fix_llr": "fix_llr",
    "kidnap_weight": "kidnap_weight",
    "probation_travel": "probation_travel",
    "evidence_span": "evidence_span",
    "keep": "keep",
    "settle_scans": "settle_scans",
}


class LocalizerConfig(BaseModel):
    """The ``shape`` localiser's configuration (see the module docstring)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    preset: Preset = Field(
        "metric",
        description="metric: a map drawn from the robot's scans "
        "(furniture included); floor_plan: a plan of the walls.",
    )
    knobs: Knobs = Field(default_factory=Knobs, description="What a user may turn.")

    @classmethod
    def for_kind(cls, kind: str, **knobs: object) -> LocalizerConfig:
        """The preset of a map ``kind`` (``metric`` or ``schematic``) with ``knobs``."""
        preset = "floor_plan" if kind == "schematic" else "metric"
        return cls(preset=preset, knobs=Knobs(**knobs))  # type: ignore[arg-type]

    @property
    def kind(self) -> str:
        """The map kind of the preset."""
        return KIND[self.preset]

    def tracking(self) -> ShapeConfig:
        """The tracker's settings: the preset's, with the knobs applied."""
        base = ShapeConfig.for_kind(self.kind)
        k = self.knobs
        update = {name: getattr(k, knob) for knob, name in _TRACKING.items()}
        update = {n: v for n, v in update.items() if v is not None}
        motion = base.motion
        m_update: dict[str, object] = {}
        if k.use_odometry is not None:
            m_update["use_odometry"] = k.use_odometry
        if k.scan_odometry is not None:
            m_update["scan_odometry"] = motion.scan_odometry.model_copy(
                update={"enabled": k.scan_odometry}
            )
        if k.odometry_noise is not None:
            for a in ("alpha_rot_rot", "alpha_rot_trans", "alpha_trans_trans", "alpha_trans_rot"):
                m_update[a] = getattr(motion, a) * k.odometry_noise
        if m_update:
            update["motion"] = motion.model_copy(update=m_update)
        return ShapeConfig.model_validate({**base.model_dump(), **update}) if update else base

    def reloc(self) -> GlobalConfig:
        """Relocalisation's settings: the preset's, with the knobs applied."""
        base = GlobalConfig.for_kind(self.kind)
        update = {name: getattr(self.knobs, knob) for knob, name in _RELOC.items()}
        update = {n: v for n, v in update.items() if v is not None}
        return GlobalConfig.model_validate({**base.model_dump(), **update}) if update else base
