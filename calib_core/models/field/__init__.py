"""Field calibration without a turntable, from a recording moved by hand through static poses:

- :mod:`calib_core.models.field.static_detection`: static intervals found from the data
  itself, and the pose means;
- :mod:`calib_core.models.field.imu_tk`: the reference-free procedure of Tedaldi et al. 2014
  (IMU-TK): accelerometer from |f| = g at rest, gyro from the gravity direction across moves;
- :mod:`calib_core.models.field.joint`: the hand-held calibration with a joint gyro fit,
  standard errors and held-out figures.

The hand-held session simulator these are tested against is :mod:`calib_core.sim.hand_held`.
"""
