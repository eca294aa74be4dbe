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
  horizontal part turns with the body; its mean over the averaged window depends on the
  table angle at the window's start, which the contract does not record: it is left out
  there (it averages out over whole turns; 10.6 deg/h at 45 deg latitude at most);
- with the metadata ``latitude_deg`` and ``table_heading_deg`` the direction of the whole
  vector is known: one parameter, ``omega_up``, carries the horizontal part with it
  (omega_up cot(latitude) towards north), and ``omega_h1``/``omega_h2`` are not fitted.
  Expected value: 15.041 sin(latitude) deg/h.

An effect of where the table stands, not of the sensors: a calibration never removes it
from the unit's outputs (``sensor_effect`` False).
"""
from __future__ import annotations

import numpy as np

from calib_core.effects.base import (DEG, EffectTerm, FigureVariable, MotionContext,
                                     SensingGeometry, heading_reference, register_effect,
                                     turn_about, up_direction)

EARTH_RATE_DEG_H = 7.2921150e-5 / DEG * 3600.0  # sidereal rotation, 15.041 deg/h
MIN_PINNED_LATITUDE_DEG = 6.0  # below, the vertical part is too small to carry the vector


def pinned(ctx: MotionContext) -> bool:
    """The metadata give the Earth rate's direction in every step's body frame."""
    return (ctx.latitude_deg is not None and ctx.table_heading_deg is not None
            and abs(ctx.latitude_deg) >= MIN_PINNED_LATITUDE_DEG)


def body_columns(ctx: MotionContext) -> np.ndarray:
    """The Earth rate in the body frame per unit parameter, (n, 3 axes, 3 params), deg/s
    per deg/h."""
    up = up_direction(ctx)
    static = (np.linalg.norm(ctx.w, axis=1) < 1e-9)[:, None]
    heading = np.zeros(len(ctx)) if ctx.heading_deg is None else ctx.heading_deg
    out = np.zeros((len(ctx), 3, 3))
    if pinned(ctx):
        north = turn_about(heading_reference(up), up,
                           (heading + ctx.table_heading_deg) * DEG)
        cot = 1.0 / np.tan(ctx.latitude_deg * DEG)
        out[:, :, 0] = up + static * cot * north
    else:
        h1 = turn_about(heading_reference(up), up, heading * DEG)
        out[:, :, 0] = up
        out[:, :, 1] = static * h1
        out[:, :, 2] = static * np.cross(up, h1)
    return out / 3600.0


@register_effect
class EarthRate(EffectTerm):
    name = "earth_rate"
    description = "the Earth's rotation (15.04 deg/h) seen by the gyros"
    param_names = ("omega_up", "omega_h1", "omega_h2")
    param_units = ("deg/h",) * 3
    excited_by = ("stationary steps at two headings or a known table heading (the "
                  "horizontal part); the vertical part alone is a gyro g-sensitivity")
    max_useful_stderr = 5.0  # deg/h: a third of the Earth rate
    sensor_effect = False
    named_when_significant = True

    def sensor_regressors(self, ctx: MotionContext, geometry: SensingGeometry) -> np.ndarray:
        cols = body_columns(ctx)  # (n, 3, p) body frame
        out = np.zeros((len(ctx), 6, 3))
        out[:, :3] = np.einsum("ja,nap->njp", geometry.gyro_axes, cols)
        return out

    def realistic(self, rng, scale=1.0):
        """A latitude of 30-60 deg and a random table heading (``scale`` does not apply:
        the Earth turns at its own rate)."""
        lat = rng.uniform(30.0, 60.0) * rng.choice([-1.0, 1.0])
        heading = rng.uniform(0.0, 360.0)
        h = EARTH_RATE_DEG_H * np.cos(lat * DEG)
        theta = np.array([EARTH_RATE_DEG_H * np.sin(lat * DEG), h * np.cos(heading * DEG),
                          h * np.sin(heading * DEG)])
        return theta, f"latitude {lat:.0f} deg, table heading {heading:.0f} deg"

    def physics_knobs(self, theta):
        return {}

    def table_knobs(self, theta):
        up, h1, h2 = (float(x) for x in theta)
        return {"latitude_deg": float(np.degrees(np.arctan2(up, np.hypot(h1, h2)))),
                "heading_deg": float(np.degrees(np.arctan2(h2, h1)) % 360.0)}

    def figure_variable(self, ctx, channel):
        up = up_direction(ctx)
        return FigureVariable(f"up along {'xyz'[channel % 3]} (specific force direction)",
                              "", up[:, channel % 3])
