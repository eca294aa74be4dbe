"""Simulated units, protocols and truths: what the estimators are checked against.

- :mod:`calib_core.sim.protocols`: step tables (the papers' protocols, the verification
  sweep, the step sets the protocol advisor proposes);
- :mod:`calib_core.sim.simulator`: the fast simulator in the calibration's own form
  (``MimuTruth``: K_g, w0, K_a, f0, noise, catalogue effects; samples or step means);
- :mod:`calib_core.sim.accel_unit`: an accelerometer unit in zhang2017's form (sensitive axes,
  lever arms);
- :mod:`calib_core.sim.navigation`: strapdown navigation on the turntable (zhang2017's
  navigation drift with and without lever-arm compensation);
- :mod:`calib_core.sim.hand_held`: hand-held multi-pose sessions for the field calibration;
- :mod:`calib_core.sim.physics`: an independent forward model written from the sensor physics
  (each sensor's own axis, position, polynomial, temperature, noise processes; a turntable
  whose axis and rate can be off; Earth rotation). It knows nothing of the estimators or of
  the effect catalogue's term code: model discovery is checked against it.

May import the shared modules at the top of ``calib_core``, :mod:`calib_core.effects` and
:mod:`calib_core.models` (the forms its truths are written in); never discovery or paper.
"""
