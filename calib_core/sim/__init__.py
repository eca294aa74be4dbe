"""Simulators of units on the turntable.

- :mod:`calib_core.sim.physics`: an independent forward model written from the sensor physics
  (each sensor's own axis, position, polynomial, temperature, noise processes; a turntable
  whose axis and rate can be off; Earth rotation). It knows nothing of the estimators or of
  the effect catalogue's term code: model discovery is checked against it.
"""
