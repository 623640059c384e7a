"""Shared drafting blocks: bodice/torso outline, skirt outline, two-piece set-in sleeve, trouser leg.

Drafting follows the structure of W. Aldrich, *Metric Pattern Cutting for Women's Wear* (blocks drawn on a
frame of horizontal construction lines: bust/armscye line, waist line, hip line, hem), simplified:

* waist shaping is taken entirely in the side seams (no darts), drawn as cubic Beziers with vertical end
  tangents between the construction lines, so front and back side seams are congruent and sew exactly;
* the bust line is the armscye line (Aldrich squares the bust width across at armscye depth), so the
  underarm point sits at ``bust_height``;
* front and back differ by a constant ``front_bias`` added to every front quarter width and removed from
  every back one (side seam moved towards the back), and by the neckline depth.

Panel coordinates: y is the height above the floor in metres and x = 0 is the centre front/back line, so a
front panel placed with identity rotation sits at its true height.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from torchgarment.errors import InputError
from torchgarment.pattern.library.builder import Chain, cubic_length, side_curve
from torchgarment.pattern.library.measurements import DraftMeasurements

# GarmentCode mean body shoulder_incl 20.9 deg; Aldrich ~ 4.5 cm over 12 cm
SHOULDER_SLOPE = math.radians(20.0)
CLEARANCE = 0.03  # gap between the body's bounding girth and a placed panel, metres


def panel_depth(m: DraftMeasurements, clearance: float = CLEARANCE) -> float:
    """Distance of front/back panels from the body axis: largest girth / (2 pi) + clearance (metres).

    A section's half-depth is at most ``g / (2 pi)`` when it is an ellipse no deeper than wide (the perimeter
    of such an ellipse is at least that of the circle of its depth), so panels clear a body of that shape.
    """
    return max(m.bust, m.underbust, m.waist, m.hips) / (2.0 * math.pi) + clearance


def positive(name: str, value: float, *, allow_zero: bool = False) -> float:
    """Check a drafting option: finite and > 0 (or >= 0)."""
    v = float(value)
    if not math.isfinite(v) or v < 0 or (v == 0 and not allow_zero):
        raise InputError(f"drafting option '{name}' must be {'>= 0' if allow_zero else '> 0'}, got {value}")
    return v


@dataclass
class Neck:
    """Shoulder and neckline frame of a bodice (panel coordinates, metres)."""

    shoulder_point: np.ndarray  # (2,) right shoulder point
    neck_point: np.ndarray  # (2,) right high-shoulder (neck) point
    front_depth: float  # front neck drop below the neck point
    back_depth: float
    front_scoop: float = 0.75  # armhole: horizontal tangent length at the underarm, fraction of its width
    back_scoop: float = 0.6


def neck_frame(m: DraftMeasurements, *, shoulder_extension: float = 0.0, neck_widening: float = 0.0,
               front_neck_drop: float = 0.0, same_armholes: bool = False) -> Neck:
    """Shoulder point, neck point and neck depths (Aldrich: half neck width neck/5 - 2 mm, front depth
    neck/5 + 8 mm, back depth 2 cm; shoulder slope 20 deg). ``same_armholes`` gives the back the front's
    armhole scoop (for sleeves cut as two identical halves)."""
    xs = 0.5 * m.shoulder_width + shoulder_extension
    xn = m.neck_girth / 5.0 - 0.002 + neck_widening
    if xn >= xs - 0.03:
        raise InputError(f"neck half-width {xn:.3f} m leaves no shoulder (shoulder half-width {xs:.3f} m)")
    ys = m.shoulder_height
    yn = ys + (xs - xn) * math.tan(SHOULDER_SLOPE)
    return Neck(np.array([xs, ys]), np.array([xn, yn]), m.neck_girth / 5.0 + 0.008 + front_neck_drop, 0.02,
                back_scoop=0.75 if same_armholes else 0.6)


def add_armhole_shoulder_neck(chain: Chain, neck: Neck, *, front: bool) -> Chain:
    """Continue a right half from the underarm point: armhole, shoulder line, half neckline to x = 0."""
    u = chain.points[-1]
    sp, npt = neck.shoulder_point, neck.neck_point
    dx, dy = u[0] - sp[0], sp[1] - u[1]
    if dx <= 0.005 or dy <= 0.02:
        raise InputError(f"armhole cannot be drawn: underarm point {u} is not below and outside the shoulder "
                         f"point {sp} (bust too narrow for the shoulders?)")
    scoop = neck.front_scoop if front else neck.back_scoop
    chain.cubic(u + np.array([-scoop * dx, 0.0]), sp - np.array([0.0, 0.5 * dy]), sp, "armhole_r")
    chain.line(npt, "shoulder_r")
    depth = neck.front_depth if front else neck.back_depth
    cf = np.array([0.0, npt[1] - depth])
    chain.cubic(npt - np.array([0.0, 0.6 * depth]), np.array([0.6 * npt[0], cf[1]]), cf, "neck_r")
    return chain


def armhole_length(neck: Neck, underarm: np.ndarray, *, front: bool) -> float:
    """Length of the armhole that :func:`add_armhole_shoulder_neck` draws (metres)."""
    c = Chain.start(underarm)
    add_armhole_shoulder_neck(c, neck, front=front)
    s = c.segments[0]
    return cubic_length(underarm, s.controls[0], s.controls[1], neck.shoulder_point)


def skirt_half(m: DraftMeasurements, *, waist_width: float, hip_width: float, hem_height: float,
               flare: float, top_height: float | None = None) -> Chain:
    """Right half of a skirt panel from the hem centre up to the waist centre.

    Args:
        waist_width, hip_width: half-panel widths at the waist and hip lines (metres).
        hem_height: hem height above the floor at the centre line.
        flare: side-seam angle from vertical below the hip line (radians); the hem is a quadratic that
            meets the side seam at a right angle (Aldrich's A-line hem).
        top_height: height of the top edge (default the waist).
    """
    yw = m.waist_height if top_height is None else top_height
    yh = m.hip_height
    if not hem_height < yh - 0.02:
        raise InputError(f"hem height {hem_height:.3f} m must be below the hip line {yh:.3f} m")
    t = math.tan(flare)
    # hem corner (hw_hem, hem_height + d) on the side line of angle ``flare`` through the hip point, with
    # d = hw_hem t / 2 so that the quadratic hem (control at half width on the centre height) meets it square
    hw_hem = (hip_width + (yh - hem_height) * t) / (1.0 + 0.5 * t * t)
    d = 0.5 * hw_hem * t
    c = Chain.start((0.0, hem_height))
    if flare > 0:
        c.quad((0.5 * hw_hem, hem_height), (hw_hem, hem_height + d), "hem_r")
    else:
        c.line((hw_hem, hem_height), "hem_r")
    c.line((hip_width, yh), "side_low_r")
    side_curve((hip_width, yh), (waist_width, yw), c, "side_hip_r")
    c.line((0.0, yw), "waist_r")
    return c


def sleeve_half(*, cap_length: float, bicep_half: float, cuff_half: float, length: float) -> Chain:
    """Front half of a left sleeve, arm along +x from the shoulder point at (0, 0), overarm line y = 0.

    The cap is a cubic from the shoulder point to the underarm point ``(h, -bicep_half)`` with tangents
    across the sleeve at both ends (the bell-shaped set-in sleeve crown); the cap height ``h`` is solved by
    bisection so that the cap is ``cap_length`` long.

    Returns:
        closed counter-clockwise chain: cap, underarm, cuff, overarm.
    """
    if cap_length <= bicep_half * 1.01:
        raise InputError(f"armhole ({cap_length:.3f} m) is too short for a sleeve of half width "
                         f"{bicep_half:.3f} m; reduce sleeve ease or lower the armhole")

    def cap(h: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return np.array([0.0, -0.4 * bicep_half]), np.array([h, -0.6 * bicep_half]), np.array([h,
                                                                                               -bicep_half])

    lo, hi = 0.0, cap_length
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if cubic_length(np.zeros(2), *cap(mid)) < cap_length:
            lo = mid
        else:
            hi = mid
    h = 0.5 * (lo + hi)
    if length <= h + 0.02:
        raise InputError(f"sleeve length {length:.3f} m is shorter than its cap height {h:.3f} m")
    c1, c2, u = cap(h)
    c = Chain.start((0.0, 0.0))
    c.cubic(c1, c2, u, "cap")
    c.line((length, -cuff_half), "underarm")
    c.line((length, 0.0), "cuff")
    c.line((0.0, 0.0), "overarm")
    return c


def trouser_leg(m: DraftMeasurements, *, hip_width: float, waist_width: float, centre_shift: float,
                fork: float, inseam_run: float, side_run: float, hem_height: float) -> Chain:
    """One trouser panel in the canonical layout of the left front leg (side seam at +x, centre at 0).

    Args:
        hip_width: panel width at the hip line from the centre line to the side (metres).
        waist_width: panel width at the waist.
        centre_shift: how far the centre seam moves towards the side at the waist (back seat shaping).
        fork: crotch extension past the centre line at crotch level.
        inseam_run, side_run: horizontal inward run of the inseam and side seam from crotch/hip to hem.
        hem_height: hem above the floor.

    Returns:
        closed counter-clockwise chain (last point = first) starting at the crotch point: inseam, hem,
        side_low, side_hip, waist, centre, crotch.
    """
    yc, yh, yw = m.crotch_height, m.hip_height, m.waist_height
    if not hem_height < yc - 0.1:
        raise InputError(f"trouser hem {hem_height:.3f} m must be well below the crotch {yc:.3f} m")
    p0 = np.array([-fork, yc])
    c = Chain.start(p0)
    c.line((-fork + inseam_run, hem_height), "inseam")
    c.line((hip_width - side_run, hem_height), "hem")
    c.line((hip_width, yh), "side_low")
    side_curve((hip_width, yh), (centre_shift + waist_width, yw), c, "side_hip")
    c.line((centre_shift, yw), "waist")
    c.line((0.0, yh), "centre")
    c.cubic((0.0, yc + 0.35 * (yh - yc)), (-0.5 * fork, yc), p0, "crotch")
    return c
