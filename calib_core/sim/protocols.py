"""Turntable protocols as step tables (the columns of the contract's steps.parquet).

A protocol is a ``pandas.DataFrame`` with the contract columns plus ``duration_s`` (how long
the table holds the step; an optional column the contract allows us to add). References are
nominal: rate about the vertical table axis, gravity along the body axis that points up.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

STEP_COLUMNS = (
    "step",
    "test",
    "up_axis",
    "rate_dps",
    "angle_deg",
    "w_ref_x",
    "w_ref_y",
    "w_ref_z",
    "f_ref_x",
    "f_ref_y",
    "f_ref_z",
    "settle_s",
)

# xu2016 section 2.2.1: x-up and y-up rates (deg/s), z-up rates (deg/s)
XU2016_RATES_XY = (6, 12, 24, 30, 60, 120, 180, 240, 300)
XU2016_RATES_Z = (10, 40, 100, 240, 400, 720, 1000, 1800, 2160, 2880, 3600)
# xu2016 section 2.2.2 / appendix: medium/inner frame angles of the multiposition test
XU2016_ANGLES = (0, 15, 30, 45, 60, 90, 120, 135, 150, 165, 180)
# zhang2017 section 3.2: constant rates of the dynamic test
ZHANG2017_DYNAMIC_RATES = (100, 150, 200)

_AXES = {
    "+x": (1, 0, 0),
    "-x": (-1, 0, 0),
    "+y": (0, 1, 0),
    "-y": (0, -1, 0),
    "+z": (0, 0, 1),
    "-z": (0, 0, -1),
}


def up_axis_of(f: np.ndarray) -> str:
    """Nominal up axis: the body axis closest to the specific-force direction."""
    i = int(np.argmax(np.abs(f)))
    return ("+" if f[i] >= 0 else "-") + "xyz"[i]


def _row(
    test: str, up: np.ndarray, rate: float, angle: float | None, duration_s: float, settle_s: float
) -> dict:
    up = np.asarray(up, dtype=float)
    up = up / np.linalg.norm(up)
    w = rate * up
    return {
        "test": test,
        "up_axis": up_axis_of(up),
        "rate_dps": float(rate),
        "angle_deg": np.nan if angle is None else float(angle),
        "w_ref_x": w[0] + 0.0,
        "w_ref_y": w[1] + 0.0,
        "w_ref_z": w[2] + 0.0,
        "f_ref_x": up[0] + 0.0,
        "f_ref_y": up[1] + 0.0,
        "f_ref_z": up[2] + 0.0,
        "settle_s": float(settle_s),
        "duration_s": float(duration_s),
    }


def xu2016_multirate(duration_s: float = 3.0, settle_s: float = 0.5) -> list[dict]:
    """Stationary step then +/- rates about the vertical, for x-up, y-up and z-up."""
    rows = []
    for axis, rates in (("+x", XU2016_RATES_XY), ("+y", XU2016_RATES_XY), ("+z", XU2016_RATES_Z)):
        up = _AXES[axis]
        rows.append(_row("stationary", up, 0.0, None, duration_s, settle_s))
        for r in rates:
            rows.append(_row("multirate", up, +r, None, duration_s, settle_s))
            rows.append(_row("multirate", up, -r, None, duration_s, settle_s))
    return rows


def multiposition_f(orientation: str, angle_deg: float) -> np.ndarray:
    """Specific force (g) of the xu2016 appendix for the 'z', 'x' or 'y' down sequence."""
    a = np.radians(angle_deg)
    s, c = np.sin(a), np.cos(a)
    return {
        "z": np.array([0.0, -s, -c]),  # F_z(i): z down, medium frame rotates about x
        "x": np.array([-c, 0.0, -s]),  # F_x(i): x down
        "y": np.array([-s, -c, 0.0]),  # F_y(i): y down, inner frame
    }[orientation]


def xu2016_multiposition(duration_s: float = 3.0, settle_s: float = 0.5) -> list[dict]:
    """11 angles x 3 orientations (appendix F_z, F_x, F_y, in the paper's step order)."""
    rows = []
    for orientation in ("z", "x", "y"):
        for ang in XU2016_ANGLES:
            rows.append(
                _row("multiposition", multiposition_f(orientation, ang), 0.0, ang, duration_s, settle_s)
            )
    return rows


def dynamic_steps(
    rates=ZHANG2017_DYNAMIC_RATES,
    duration_s: float = 3.0,
    settle_s: float = 0.5,
    tilted: bool = True,
    tilted_rates=(200,),
    stationary: bool = False,
) -> list[dict]:
    """Constant-rate rotation about the vertical with x-, y- and z-up, +/- each rate.

    With only principal axes up, accelerometer i sees nothing but the i-th component of its
    own lever arm (the centripetal term along the rotation axis vanishes): r_iy, r_iz of the
    x accelerometer are unobservable. zhang2017 works around this by tilting the unit against
    the table ("make an angle deviate between the turntable frame and carrier frame"); the
    ``tilted`` steps do this with the up direction on the three 45-degree diagonals.
    """
    rows = []
    ups = [_AXES["+x"], _AXES["+y"], _AXES["+z"]]
    for up in ups:
        if stationary:
            rows.append(_row("stationary", up, 0.0, None, duration_s, settle_s))
        for r in rates:
            rows.append(_row("dynamic", up, +r, None, duration_s, settle_s))
            rows.append(_row("dynamic", up, -r, None, duration_s, settle_s))
    if tilted:
        for up in ((1, 1, 0), (0, 1, 1), (1, 0, 1)):
            for r in tilted_rates:
                rows.append(_row("dynamic", up, +r, None, duration_s, settle_s))
                rows.append(_row("dynamic", up, -r, None, duration_s, settle_s))
    return rows


def verification_sweep(duration_s: float = 3.0, settle_s: float = 0.5) -> list[dict]:
    """Rates about x, y (to +/-300 deg/s) and z (to +/-3600 deg/s) not used by the fits,
    for the compensation errors of xu2016 Table 3."""
    rows = []
    xy = (-300, -270, -210, -150, -90, -50, -20, 0, 20, 50, 90, 150, 210, 270, 300)
    z = (-3600, -3000, -2500, -1500, -900, -500, -200, -50, 0, 50, 200, 500, 900, 1500, 2500, 3000, 3600)
    for axis, rates in (("+x", xy), ("+y", xy), ("+z", z)):
        for r in rates:
            rows.append(_row("verification", _AXES[axis], r, None, duration_s, settle_s))
    return rows


def zhang2017_six_position(duration_s: float = 60.0, settle_s: float = 1.0) -> list[dict]:
    """Static +/-1 g on each axis, one minute each (zhang2017 section 3.1)."""
    rows = []
    for axis in ("+x", "-x", "+y", "-y", "+z", "-z"):
        rows.append(
            _row("multiposition", _AXES[axis], 0.0, 0.0 if axis[0] == "+" else 180.0, duration_s, settle_s)
        )
    return rows


def to_frame(rows: list[dict]) -> pd.DataFrame:
    """Number the steps 0..n-1 and give the contract dtypes."""
    df = pd.DataFrame(rows)
    df.insert(0, "step", np.arange(len(df), dtype=np.int32))
    return df.astype({"step": "int32", "test": "string", "up_axis": "string"})


def default_session(
    duration_s: float = 3.0, settle_s: float = 0.5, dynamic: bool = True, verification: bool = False
) -> pd.DataFrame:
    """The full production protocol: xu2016 multirate + multiposition, zhang2017 dynamic
    (+ the verification sweep on request)."""
    rows = xu2016_multirate(duration_s, settle_s) + xu2016_multiposition(duration_s, settle_s)
    if dynamic:
        rows += dynamic_steps(duration_s=duration_s, settle_s=settle_s)
    if verification:
        rows += verification_sweep(duration_s, settle_s)
    return to_frame(rows)


def zhang2017_session(duration_s: float = 60.0, settle_s: float = 1.0, tilted: bool = True) -> pd.DataFrame:
    """zhang2017 protocol: six-position static, then stationary + constant-rate dynamic steps."""
    rows = zhang2017_six_position(duration_s, settle_s)
    rows += dynamic_steps(duration_s=duration_s, settle_s=settle_s, tilted=tilted, stationary=True)
    return to_frame(rows)


def _with_heading(rows: list[dict], heading_deg: float) -> list[dict]:
    return [{**r, "heading_deg": float(heading_deg)} for r in rows]


def two_heading_stationary(duration_s: float = 3.0, settle_s: float = 0.5) -> list[dict]:
    """The six-position static steps at headings 0 and 90 deg: the horizontal Earth rate
    changes direction in the body between the two, a bias does not."""
    six = zhang2017_six_position(duration_s, settle_s)
    for r in six:
        r["test"] = "stationary"
    return _with_heading(six, 0.0) + _with_heading(six, 90.0)


def diagonal_dynamic(duration_s: float = 3.0, settle_s: float = 0.5) -> list[dict]:
    """Constant-rate rotation about the vertical with the unit's up on the 45-degree
    diagonals: the lever arm's components off the rotation axis."""
    return dynamic_steps(
        rates=(), duration_s=duration_s, settle_s=settle_s, tilted=True, tilted_rates=(200, 400)
    )


WHOLE_TURN_RATES = (90, 120, 180, 240)  # deg/s, within a 300 deg/s gyro range about x and y


def whole_turn_session(
    min_duration_s: float = 3.0, settle_s: float = 0.5, rates=WHOLE_TURN_RATES
) -> pd.DataFrame:
    """Every step turns about the vertical, +/- each rate with x, y, z and the three
    45-degree diagonals up, and averages over whole turns (the step lasts its settling time
    plus the fewest whole turns that fill ``min_duration_s``): the horizontal Earth rate
    averages out exactly and its vertical part is an isotropic gyro g-sensitivity. The
    protocol on which the two cannot be told apart."""
    rows = []
    for up in ((1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 0), (0, 1, 1), (1, 0, 1)):
        for r in rates:
            turn_s = 360.0 / r
            window = turn_s * np.ceil((min_duration_s - settle_s) / turn_s)
            for sign in (1, -1):
                rows.append(_row("dynamic", up, sign * r, None, settle_s + window, settle_s))
    return to_frame(rows)


# step sets the protocol advisor may add (calib_core.discovery.plan.advise): label -> rows
STEP_SETS = {
    "stationary steps at two headings": two_heading_stationary,
    "dynamic steps on the 45-degree diagonals": diagonal_dynamic,
    "multiposition steps (33 static orientations)": xu2016_multiposition,
    "multirate steps about each axis": xu2016_multirate,
}


def extended(steps: pd.DataFrame, rows: list[dict]) -> pd.DataFrame:
    """``steps`` with ``rows`` appended (numbered after its last step)."""
    add = pd.DataFrame(rows)
    add.insert(0, "step", np.arange(len(add), dtype=np.int64) + int(steps["step"].max()) + 1)
    out = pd.concat([steps, add], ignore_index=True)
    if "heading_deg" in out:
        out["heading_deg"] = out["heading_deg"].fillna(0.0)
    return out
