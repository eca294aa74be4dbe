"""The Earth's rotation in the gyros: 15.04 deg/h about the Earth's axis, seen in the body
frame of each step through the orientation convention of docs/data-contract.md.

The Earth rate splits into a vertical part (15.04 sin(latitude) deg/h along the world's up,
which the body senses along the step's specific force) and a horizontal part (15.04
cos(latitude) deg/h towards true north):

- the vertical part is ``omega_up`` times the up direction on every step. On a turntable
  standing still on the ground that is exactly an isotropic gyro g-sensitivity (G = omega I
  times the specific force): the two are told apart only through the horizontal part;
- the horizontal part is seen on stationary steps, towards north: the step's heading
  reference (the body axis least aligned with up, projected on the horizontal plane) turned
  by the step's ``heading_deg`` and the table's unknown heading. Without the table heading
  it is the two parameters ``omega_h1`` (along the reference turned by the step's heading)
  and ``omega_h2`` (90 deg counter-clockwise from it seen from above). On rotating steps the
  horizontal part turns with the body: its mean over the averaged window follows from the
  angle turned at the window's start and end (the orientation convention: the rate is
  reached by a linear ramp over the first half of the settling time), and is left out
  where the settling time is not known;
- with the metadata ``latitude_deg`` and ``table_heading_deg`` the direction of the whole
  vector is known: one parameter, ``omega_up``, carries the horizontal part with it
  (omega_up cot(latitude) towards north), and ``omega_h1``/``omega_h2`` are not fitted.
  Expected value: 15.041 sin(latitude) deg/h.

An effect of where the table stands, not of the sensors: a calibration never removes it
from the unit's outputs (``sensor_effect`` False).
"""

from __future__ import annotations

import numpy as np

from calib_core.effects.base import (
    DEG,
    EffectTerm,
    FigureVariable,
    MotionContext,
    SensingGeometry,
    heading_reference,
    register_effect,
    sensor_zeros,
    turn_about,
    up_direction,
)

EARTH_RATE_DEG_H = 7.2921150e-5 / DEG * 3600.0  # sidereal rotation, 15.041 deg/h
MIN_PINNED_LATITUDE_DEG = 6.0  # below, the vertical part is too small to carry the vector


def pinned(ctx: MotionContext) -> bool:
    """The metadata give the Earth rate's direction in every step's body frame."""
    return (
        ctx.latitude_deg is not None
        and ctx.table_heading_deg is not None
        and abs(ctx.latitude_deg) >= MIN_PINNED_LATITUDE_DEG
    )


def horizontal_mean(ctx: MotionContext, up: np.ndarray) -> np.ndarray:
    """(n, 2): a horizontal vector fixed in the world, seen from the body, averaged over the
    window: ``n0 c + (up x n0) s`` with n0 its direction at the step's start. (1, 0) on a
    stationary step; on a rotating step the window's mean (StepMeans.turned_deg: the body
    turns by +phi about ``w``, world vectors by -phi); (0, 0) where the window is not
    known."""
    n = len(ctx)
    out = np.zeros((n, 2))
    rate = np.linalg.norm(ctx.w, axis=1)
    static = rate < 1e-9
    out[static, 0] = 1.0
    if ctx.turned_deg is None:
        return out
    # the body turns by phi >= 0 about w = s |w| up: a world vector is seen as
    # cos(phi) n0 - s sin(phi) (up x n0); averaged over the window's phi0..phi1
    s = np.sign(np.sum(ctx.w * up, axis=1))
    p0, p1 = np.radians(np.abs(ctx.turned_deg[:, 0])), np.radians(np.abs(ctx.turned_deg[:, 1]))
    span = p1 - p0
    ok = ~static & (span > 1e-12)
    out[ok, 0] = (np.sin(p1[ok]) - np.sin(p0[ok])) / span[ok]
    out[ok, 1] = s[ok] * (np.cos(p1[ok]) - np.cos(p0[ok])) / span[ok]
    return out


def body_columns(ctx: MotionContext) -> np.ndarray:
    """The Earth rate in the body frame per unit parameter, (n, 3 axes, 3 params), deg/s
    per deg/h."""
    up = up_direction(ctx)
    hm = horizontal_mean(ctx, up)
    heading = np.zeros(len(ctx)) if ctx.heading_deg is None else ctx.heading_deg

    def seen(n0: np.ndarray) -> np.ndarray:
        return hm[:, :1] * n0 + hm[:, 1:] * np.cross(up, n0)

    out = np.zeros((len(ctx), 3, 3))
    if pinned(ctx):
        north = turn_about(heading_reference(up), up, (heading + ctx.table_heading_deg) * DEG)
        cot = 1.0 / np.tan(ctx.latitude_deg * DEG)
        out[:, :, 0] = up + cot * seen(north)
    else:
        h1 = turn_about(heading_reference(up), up, heading * DEG)
        out[:, :, 0] = up
        out[:, :, 1] = seen(h1)
        out[:, :, 2] = seen(np.cross(up, h1))
    return out / 3600.0


_BODY_COLUMNS: dict[bytes, np.ndarray] = {}  # body_columns of the contexts last seen


def kept_body_columns(ctx: MotionContext) -> np.ndarray:
    """:func:`body_columns` (read-only), kept per context: they depend on the steps' motion,
    headings and where the table stands alone, the same for every unit of a protocol."""
    key = b"".join(
        [
            np.asarray(ctx.w, float).tobytes(),
            np.asarray(ctx.f, float).tobytes(),
            b"-" if ctx.heading_deg is None else np.asarray(ctx.heading_deg, float).tobytes(),
            b"-" if ctx.turned_deg is None else np.asarray(ctx.turned_deg, float).tobytes(),
            repr((len(ctx), ctx.latitude_deg, ctx.table_heading_deg)).encode(),
        ]
    )
    out = _BODY_COLUMNS.get(key)
    if out is None:
        out = body_columns(ctx)
        out.setflags(write=False)
        if len(_BODY_COLUMNS) >= 8:
            _BODY_COLUMNS.clear()
        _BODY_COLUMNS[key] = out
    return out


@register_effect
class EarthRate(EffectTerm):
    name = "earth_rate"
    description = "the Earth's rotation (15.04 deg/h) seen by the gyros"
    param_names = ("omega_up", "omega_h1", "omega_h2")
    param_units = ("deg/h",) * 3
    excited_by = (
        "stationary steps at two headings or a known table heading (the "
        "horizontal part); the vertical part alone is a gyro g-sensitivity"
    )
    max_useful_stderr = 5.0  # deg/h: a third of the Earth rate
    sensor_effect = False
    named_when_significant = False

    def sensor_regressors(self, ctx: MotionContext, geometry: SensingGeometry) -> np.ndarray:
        cols = kept_body_columns(ctx)  # (n, 3, p) body frame
        out = sensor_zeros(len(ctx), 3)
        # gyro j senses a_j . column: a sum of three products in the axes' order (as
        # einsum("ja,nap->njp") sums them), written to each gyro's rows
        G, by_sensor = geometry.gyro_axes, out.transpose(1, 0, 2)
        for j in range(3):
            by_sensor[j] = G[j, 0] * cols[:, 0] + G[j, 1] * cols[:, 1] + G[j, 2] * cols[:, 2]
        return out

    def realistic(self, rng, scale=1.0):
        """A latitude of 30-60 deg and a random table heading (``scale`` does not apply:
        the Earth turns at its own rate)."""
        lat = rng.uniform(30.0, 60.0) * rng.choice([-1.0, 1.0])
        heading = rng.uniform(0.0, 360.0)
        h = EARTH_RATE_DEG_H * np.cos(lat * DEG)
        theta = np.array(
            [EARTH_RATE_DEG_H * np.sin(lat * DEG), h * np.cos(heading * DEG), h * np.sin(heading * DEG)]
        )
        return theta, f"latitude {lat:.0f} deg, table heading {heading:.0f} deg"

    def physics_knobs(self, theta):
        return {}

    def table_knobs(self, theta):
        up, h1, h2 = (float(x) for x in theta)
        return {
            "latitude_deg": float(np.degrees(np.arctan2(up, np.hypot(h1, h2)))),
            "heading_deg": float(np.degrees(np.arctan2(h2, h1)) % 360.0),
        }

    def figure_variable(self, ctx, channel):
        up = up_direction(ctx)
        # the vertical part goes with the up direction: 1 g of specific force along the axis
        return FigureVariable(
            f"specific force along {'xyz'[channel % 3]} (the up direction)", "g", up[:, channel % 3]
        )
