"""What discovery reports, shared by the turntable and the static-pose discovery: the F test,
one finding per term, and the JSON form (non-finite numbers become ``null``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from scipy import special

from calib_core.results import to_jsonable

DEFAULT_ALPHA = 0.01
DEFAULT_MIN_GAIN = 1.05  # a named term must cut the held-out rms of its channels by 5 %
# a term's held-out gain counts on the steps that carry this share of its effect: an effect
# that only some steps excite (a scale nonlinearity at the high rates, the accelerometer's at
# 4 g) is judged where it acts, not diluted by the steps where it is zero
EXCITED_SHARE = 0.9


@dataclass(frozen=True)
class FTest:
    statistic: float
    dof1: int
    dof2: int
    p_value: float
    threshold: float

    @property
    def rejects(self) -> bool:
        return bool(self.p_value < self.threshold)

    def to_dict(self) -> dict[str, Any]:
        return {
            "test": "F",
            "statistic": self.statistic,
            "dof1": self.dof1,
            "dof2": self.dof2,
            "p_value": self.p_value,
            "threshold": self.threshold,
        }


def f_test(ss_num: float, dof_num: float, ss_den: float, dof_den: float, threshold: float) -> FTest:
    """F = (ss_num / dof_num) / (ss_den / dof_den) against F(dof_num, dof_den) (dof may be
    fractional: Satterthwaite's and Box's effective dof)."""
    if dof_num <= 0 or dof_den <= 0 or ss_den <= 0:
        return FTest(float("nan"), round(dof_num), round(dof_den), 1.0, threshold)
    F = (max(ss_num, 0.0) / dof_num) / (ss_den / dof_den)
    # special.fdtrc is what stats.f.sf evaluates, without its argument checking overhead
    p = float(special.fdtrc(dof_num, dof_den, F))
    return FTest(float(F), round(dof_num), round(dof_den), p, threshold)


@dataclass(frozen=True)
class EffectFinding:
    """One catalogue term tested on a unit or recording: its estimate, evidence and
    held-out gain. ``estimate``/``stderr`` are None for an undetermined parameter, whose
    reason is in ``undetermined``. ``channels``: where the held-out rms was measured;
    ``heldout_steps``: (step means counted, step means on those channels), the ones that carry
    most of the term's effect (turntable; None: all of them).
    ``block`` (static poses: "gyro" or "accel") and ``heldout_unit`` say what the held-out
    rms is in (turntable: units of the noise, sigma)."""

    name: str
    axes: tuple[str, ...]
    estimate: dict[str, float | None]
    stderr: dict[str, float | None]
    units: dict[str, str]
    evidence: FTest
    heldout_rms_before: float
    heldout_rms_after: float
    channels: tuple[str, ...] = ()
    undetermined: dict[str, str] = field(default_factory=dict)
    block: str | None = None
    heldout_unit: str = "sigma"
    heldout_steps: tuple[int, int] | None = None

    @property
    def gain(self) -> float:
        return (
            self.heldout_rms_before / self.heldout_rms_after if self.heldout_rms_after > 0 else float("inf")
        )

    def to_dict(self) -> dict[str, Any]:
        out = {
            "name": self.name,
            "axes": list(self.axes),
            "estimate": self.estimate,
            "stderr": self.stderr,
            "units": self.units,
            "evidence": self.evidence.to_dict(),
            "heldout_unit": self.heldout_unit,
            "heldout_channels": list(self.channels),
            "heldout_rms_before": self.heldout_rms_before,
            "heldout_rms_after": self.heldout_rms_after,
            "heldout_steps": None if self.heldout_steps is None else list(self.heldout_steps),
            "gain": self.gain,
            "undetermined": dict(self.undetermined),
        }
        if self.block is not None:
            out["block"] = self.block
        return out


def jsonable(doc: Any) -> Any:
    return to_jsonable(doc)


@dataclass(frozen=True)
class ConfoundedFinding:
    """Terms the unit's steps cannot tell apart, significant together: the combined fit is
    applied and no one of them is named. ``members``: each term fitted as if it were the whole
    explanation (with the unit's other chosen terms), what either reading would estimate;
    ``separated_by`` the step sets that would tell them apart
    (:func:`calib_core.discovery.identifiability.separating_additions`)."""

    terms: tuple[str, ...]
    members: tuple[EffectFinding, ...]
    evidence: FTest
    heldout_rms_before: float
    heldout_rms_after: float
    channels: tuple[str, ...] = ()
    sin_angle: float = 0.0
    separated_by: tuple[str, ...] = ()
    separable: bool = False  # the protocol sees a part of each (calib_core.discovery.plan.separable)
    heldout_unit: str = "sigma"
    heldout_steps: tuple[int, int] | None = None  # as EffectFinding's

    @property
    def name(self) -> str:
        return "confounded: " + ", ".join(self.terms)

    @property
    def gain(self) -> float:
        return (
            self.heldout_rms_before / self.heldout_rms_after if self.heldout_rms_after > 0 else float("inf")
        )

    def advice(self) -> str:
        what = f"{', '.join(self.terms)} cannot be told apart on these steps"
        if self.separable:
            return (
                f"{', '.join(self.terms)}: these steps see a part of each of its own, too "
                f"weakly here to single one out (more repetitions or longer steps)"
            )
        if not self.separated_by:
            return f"{what}; no step set of the library separates them"
        return f"{what}; add {' or '.join(self.separated_by)}"

    def to_dict(self) -> dict[str, Any]:
        return {
            "terms": list(self.terms),
            "members": [m.to_dict() for m in self.members],
            "evidence": self.evidence.to_dict(),
            "heldout_unit": self.heldout_unit,
            "heldout_channels": list(self.channels),
            "heldout_rms_before": self.heldout_rms_before,
            "heldout_rms_after": self.heldout_rms_after,
            "heldout_steps": None if self.heldout_steps is None else list(self.heldout_steps),
            "gain": self.gain,
            "sin_angle": self.sin_angle,
            "separated_by": list(self.separated_by),
            "separable": self.separable,
            "advice": self.advice(),
        }
