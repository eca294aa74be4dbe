"""Model discovery: where the fitted model is wrong, which catalogue effect
(:mod:`calib_core.effects`) explains it, and what extending the model buys on data it was
not fitted to. One engine, two kinds of data:

- :mod:`calib_core.discovery.turntable`: repetitions of a unit on the turntable against the
  table's references (:func:`diagnose_unit`);
- :mod:`calib_core.discovery.static`: static poses of a recording without references
  (:func:`diagnose_static`);

sharing the F test and finding type (:mod:`calib_core.discovery.results`) and the stepwise
selection (:mod:`calib_core.discovery.selection`).
"""

from calib_core.discovery.results import DEFAULT_ALPHA, DEFAULT_MIN_GAIN, EffectFinding, FTest, f_test
from calib_core.discovery.static import StaticDiagnosis, StaticPoses, diagnose_static
from calib_core.discovery.turntable import Diagnosis, diagnose_unit

__all__ = [
    "DEFAULT_ALPHA",
    "DEFAULT_MIN_GAIN",
    "Diagnosis",
    "EffectFinding",
    "FTest",
    "StaticDiagnosis",
    "StaticPoses",
    "diagnose_static",
    "diagnose_unit",
    "f_test",
]
