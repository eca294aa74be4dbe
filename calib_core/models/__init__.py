"""Calibration methods, one module (or package) per method: each fits its parameters from step
means or poses and returns result objects (:class:`calib_core.results.Param` lists) that
:mod:`calib_core.models.pipeline` turns into one :class:`calib_core.calibration.Calibration`.

- :mod:`calib_core.models.xu2016`: multirate gyro, multiposition accelerometer, the
  traditional inverse model, Table 3 compensation errors;
- :mod:`calib_core.models.zhang2017`: 15-parameter static accelerometer model and lever arms;
- :mod:`calib_core.models.ferraris`: Ferraris' six poses and three turns by hand;
- :mod:`calib_core.models.field`: reference-free calibration of hand-held recordings;
- :mod:`calib_core.models.pipeline`: every applicable method on a session or a unit's
  repetitions, and the applied calibration built from their fits.

May import: the shared modules at the top of ``calib_core`` and :mod:`calib_core.effects`.
"""
