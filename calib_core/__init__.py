"""Pure numerics of mimucal, no file or network I/O: the shared types at the top (steps,
results, calibration, linalg, guards, tables, outliers, errors), the calibration methods
(:mod:`calib_core.models`), the effect catalogue (:mod:`calib_core.effects`), simulated units
and protocols (:mod:`calib_core.sim`), model discovery (:mod:`calib_core.discovery`) and the
seed papers reproduced (:mod:`calib_core.paper`). docs/DESIGN.md says what each may import."""
