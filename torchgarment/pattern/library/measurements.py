"""Body measurements for pattern drafting, with proportion-rule defaults.

All values are in metres (angles in radians). Only ``height``, ``bust``, ``underbust``, ``waist`` and ``hips``
are required; every other measurement defaults to a documented proportion rule and can be given explicitly.

Sources of the proportion rules:

* Heights above the floor follow the segment-length ratios of Drillis & Contini (1966), as tabulated in
  D. A. Winter, *Biomechanics and Motor Control of Human Movement*, fig. 4.1: shoulder (acromion) 0.818 H,
  chest 0.720 H, greater trochanter (used as hip line) 0.530 H, knee 0.285 H, upper arm 0.186 H and forearm
  0.146 H.
* Waist height, crotch depth (body rise) and girths not derivable from the five required girths follow the
  size-12 row of W. Aldrich, *Metric Pattern Cutting for Women's Wear* (bust 88 cm, height about 164 cm):
  waist to floor 104 cm (0.634 H), body rise 28 cm (0.171 H), neck size 37 cm, top arm 28.6 cm, wrist 16 cm;
  and its grading increments per size (4 cm of bust): neck +1 cm, top arm +1.2 cm, wrist +0.25 cm,
  armscye depth +0.5 cm, across back +1 cm.
* Thigh girth 0.58 hips and the A-pose arm angle (45 deg) are those of GarmentCode's mean female body
  (leg_circ 60.7 cm at hips 104.1 cm; arm_pose_angle 45.5 deg).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields

from torchgarment.errors import InputError

_REF_BUST = 0.88  # Aldrich size 12
_REF_HEIGHT = 1.64

_REQUIRED = ("height", "bust", "underbust", "waist", "hips")


@dataclass
class DraftMeasurements:
    """Body measurements in metres for drafting sewing patterns.

    ``None`` fields are filled in ``__post_init__`` from the proportion rules in the module docstring.

    Attributes:
        height: stature.
        bust: bust girth (fullest part of the chest).
        underbust: girth just under the bust.
        waist: natural-waist girth.
        hips: hip girth (fullest part of the seat).
        waist_height: natural waist above the floor; default 0.634 height (Aldrich).
        hip_height: hip line above the floor; default 0.530 height (Drillis & Contini trochanter).
        bust_height: bust (= armscye) line above the floor; default 0.720 height, lowered by 0.125 of the
            bust excess over 0.88 m (Aldrich armscye grading).
        crotch_height: crotch above the floor; default waist_height - 0.171 height (Aldrich body rise).
        knee_height: knee above the floor; default 0.285 height.
        shoulder_height: shoulder point (acromion) above the floor; default 0.818 height.
        neck_girth: neck base girth; default 0.37 + 0.25 (bust - 0.88) (Aldrich).
        shoulder_width: shoulder point to shoulder point, across the back; default
            0.365 height / 1.64 + 0.25 (bust - 0.88) (Aldrich across back plus shoulder tips).
        arm_length: shoulder point to wrist; default (0.186 + 0.146) height (Drillis & Contini).
        upper_arm_girth: biceps girth; default 0.286 + 0.3 (bust - 0.88) (Aldrich top arm).
        wrist_girth: default 0.16 + 0.0625 (bust - 0.88) (Aldrich).
        thigh_girth: upper-thigh girth; default 0.58 hips (GarmentCode mean body).
        arm_angle: the body's arms, radians below horizontal (A-pose about pi/4).
    """

    height: float
    bust: float
    underbust: float
    waist: float
    hips: float
    waist_height: float | None = None
    hip_height: float | None = None
    bust_height: float | None = None
    crotch_height: float | None = None
    knee_height: float | None = None
    shoulder_height: float | None = None
    neck_girth: float | None = None
    shoulder_width: float | None = None
    arm_length: float | None = None
    upper_arm_girth: float | None = None
    wrist_girth: float | None = None
    thigh_girth: float | None = None
    arm_angle: float = math.pi / 4

    def __post_init__(self) -> None:
        for name in _REQUIRED:
            v = getattr(self, name)
            if v is None or not math.isfinite(float(v)) or float(v) <= 0:
                raise InputError(f"measurement '{name}' must be a positive number of metres, got {v!r}")
            setattr(self, name, float(v))
        if not 0.8 < self.height < 2.6:
            raise InputError(f"height {self.height} m is outside 0.8..2.6 m (measurements are in metres)")
        for name in ("bust", "underbust", "waist", "hips"):
            if not 0.3 < getattr(self, name) < 2.5:
                raise InputError(f"{name} {getattr(self, name)} m is outside 0.3..2.5 m (girths are in "
                                 "metres)")
        h, db = self.height, self.bust - _REF_BUST
        rules = {
            "waist_height": 0.634 * h,
            "hip_height": 0.530 * h,
            "bust_height": 0.720 * h - 0.125 * db,
            "knee_height": 0.285 * h,
            "shoulder_height": 0.818 * h,
            "neck_girth": 0.37 + 0.25 * db,
            "shoulder_width": 0.365 * h / _REF_HEIGHT + 0.25 * db,
            "arm_length": (0.186 + 0.146) * h,
            "upper_arm_girth": 0.286 + 0.3 * db,
            "wrist_girth": 0.16 + 0.0625 * db,
            "thigh_girth": 0.58 * self.hips,
        }
        for name, value in rules.items():
            if getattr(self, name) is None:
                setattr(self, name, value)
        if self.crotch_height is None:
            self.crotch_height = self.waist_height - 0.171 * h
        for f in fields(self):
            v = float(getattr(self, f.name))
            if not math.isfinite(v):
                raise InputError(f"measurement '{f.name}' is not finite")
            setattr(self, f.name, v)
            if f.name != "arm_angle" and v <= 0:
                raise InputError(f"measurement '{f.name}' must be positive, got {v}")
        order = ["knee_height", "crotch_height", "hip_height", "waist_height", "bust_height",
                 "shoulder_height"]
        for lo, hi in zip(order[:-1], order[1:]):
            if not getattr(self, lo) < getattr(self, hi):
                raise InputError(f"{lo} ({getattr(self, lo):.3f} m) must be below {hi} "
                                 f"({getattr(self, hi):.3f} m)")
        if self.shoulder_height >= self.height:
            raise InputError("shoulder_height must be below height")
        if not -0.1 <= self.arm_angle <= math.pi / 2:
            raise InputError(f"arm_angle {self.arm_angle} rad is outside -0.1..pi/2 (radians below "
                             "horizontal)")

    @classmethod
    def from_dict(cls, d: dict[str, float]) -> "DraftMeasurements":
        """Build from a mapping of measurement names to metres; unknown or missing names raise InputError."""
        if isinstance(d, DraftMeasurements):
            return d
        if not isinstance(d, dict):
            raise InputError(f"measurements must be a dict of metres, got {type(d).__name__}")
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise InputError(f"unknown measurement(s) {unknown}; valid names: {sorted(known)}")
        missing = [k for k in _REQUIRED if k not in d]
        if missing:
            raise InputError(f"missing required measurement(s) {missing}")
        try:
            values = {k: (None if v is None else float(v)) for k, v in d.items()}
        except (TypeError, ValueError) as exc:
            raise InputError(f"measurements must be numbers: {exc}") from None
        return cls(**values)

    def to_dict(self) -> dict[str, float]:
        """All measurements (required and derived) as a plain dict of floats."""
        return {k: float(v) for k, v in asdict(self).items()}
