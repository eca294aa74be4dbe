"""The seed papers on simulated units, and what their published numbers say.

- :mod:`calib_core.paper.xu2016`, :mod:`calib_core.paper.zhang2017`: each paper's unit
  simulated, its method run, its tables printed beside the published ones
  (``reproduce(rate_hz, reps, seed) -> ReproductionReport``, printable ``text`` and
  ``to_dict()``; ``mimucal reproduce``);
- :mod:`tools.xu2016_gap`: model discovery on xu2016's published tables (what a
  linear unit cannot reproduce, and which catalogue effect closes the gap).

May import every other part of ``calib_core``; nothing in ``calib_core`` imports it.
"""
