"""Measured noise of static IMU recordings (pure numerics, no I/O).

- :mod:`~calib_core.noise.allan`: overlapping Allan deviation with Stable32 intervals;
- :mod:`~calib_core.noise.processes`: the Allan variance of each noise process;
- :mod:`~calib_core.noise.fit`: the composite model fitted to the whole Allan curve;
- :mod:`~calib_core.noise.analysis`: noise discovery (lines, processes, held-out halves);
- :mod:`~calib_core.noise.model`: the measured model and its stable JSON;
- :mod:`~calib_core.noise.units`: IEEE 952/1293 and Kalibr units;
- :mod:`~calib_core.noise.synthesis`: records drawn from a measured model.

Channel names are gx, gy, gz (deg/s, or rad/s) and ax, ay, az (g, the project's inside unit,
or m/s^2); coefficients are kept in the channel unit and seconds.
"""

from calib_core.noise.allan import AllanCurve, allan_curve
from calib_core.noise.analysis import ChannelAnalysis, NoiseAnalysis, analyse_recording
from calib_core.noise.fit import AllanFit, Line, Term, fit_allan
from calib_core.noise.model import ChannelNoise, NoiseModel
from calib_core.noise.synthesis import synthesize

__all__ = [
    "AllanCurve",
    "AllanFit",
    "ChannelAnalysis",
    "ChannelNoise",
    "Line",
    "NoiseAnalysis",
    "NoiseModel",
    "Term",
    "allan_curve",
    "analyse_recording",
    "fit_allan",
    "synthesize",
]
