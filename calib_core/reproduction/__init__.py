"""Reproductions of the seed papers on simulated units: each module has
``reproduce(rate_hz, reps, seed) -> ReproductionReport`` (printable ``text`` and ``to_dict()``)."""
