"""The unit's work after the step means, fifth round: the new paths give what the old ones
gave, bit for bit.

- ``summarise`` reads the repetitions' values from the fits' parameter blocks (arrays), not
  from one ``Param`` per parameter: the same summaries as from the parameter lists (NaN
  values and standard errors included), the same fallbacks (a repetition without a model, a
  fit without ``param_blocks``).
- every fit's ``parameters()`` is built from its blocks: the Params the former per-fit code
  built (names, values, units, order).
"""
from __future__ import annotations

import math
import struct
from dataclasses import dataclass, replace

import numpy as np

from calib_core import protocols
from calib_core.pipeline import calibrate_repetitions
from calib_core.results import (Param, _block_layout, _summarise_by_key, _summarise_params,
                                param_list, summarise)
from calib_core.xu2016 import AXES

from conftest import STEPS_WITH_VERIFICATION, unit_step_means


def _reps(n: int = 5, seed: int = 7, steps=STEPS_WITH_VERIFICATION):
    return [f.calibration for f in calibrate_repetitions(unit_step_means(n, seed, steps))]


def _bits(x):
    return struct.pack("<d", x) if type(x) is float else x


def _same_summaries(a, b) -> None:
    assert len(a) == len(b)
    for x, y in zip(a, b):
        assert type(x) is type(y)
        for k, v in vars(x).items():
            w = vars(y)[k]
            assert type(v) is type(w), k
            if isinstance(v, tuple):
                assert [_bits(e) for e in v] == [_bits(e) for e in w], k
            else:
                assert _bits(v) == _bits(w), (k, v, w)


def test_summarise_from_blocks_equals_summarise_from_params():
    reps = _reps()
    fast = summarise(reps)
    old = _summarise_params([r.parameters() for r in sorted(reps, key=lambda r: r.rep)])
    _same_summaries(fast, old)
    assert len(fast) == len(reps[0].parameters()) and fast[0].n_reps == 5
    # reps given in any order: summarised in rep order
    _same_summaries(summarise(reps[::-1]), fast)


def test_summarise_with_nan_parameters():
    # untilted dynamic steps: some lever-arm components are NaN (value and stderr)
    steps = protocols.to_frame(protocols.xu2016_multirate() + protocols.xu2016_multiposition()
                               + protocols.dynamic_steps(tilted=False))
    reps = _reps(seed=10, steps=steps)
    assert np.isnan(reps[0].fits["lever_arm"].lever_arm_mm).any()
    fast = summarise(reps)
    _same_summaries(fast, _summarise_params([r.parameters() for r in reps]))
    assert any(math.isnan(s.mean) and math.isnan(s.mean_stderr) for s in fast)
    # one repetition alone: std NaN, as before
    _same_summaries(summarise(reps[:1]), _summarise_params([reps[0].parameters()]))


def test_summarise_fallbacks():
    reps = _reps(3)
    # a repetition without the lever-arm model: by key, as before
    short = replace(reps[0], fits={k: v for k, v in reps[0].fits.items() if k != "lever_arm"})
    mixed = summarise([short] + reps[1:])
    _same_summaries(mixed, _summarise_by_key([short.parameters()] + [r.parameters()
                                                                      for r in reps[1:]]))
    assert {(x.model, x.name): x.n_reps for x in mixed}[("lever_arm", "r1x")] == 2

    # a fit without param_blocks: summarised from the parameter lists
    @dataclass(frozen=True)
    class Other:
        value: float
        model: str = "other"

        def parameters(self):
            return param_list(self.model, ["x"], [self.value], [0.5], "u")

    extra = [replace(r, fits={**r.fits, "other": Other(float(i))}) for i, r in enumerate(reps)]
    out = summarise(extra)
    _same_summaries(out, _summarise_params([r.parameters() for r in extra]))
    assert out[-1].name == "x" and out[-1].mean == 1.0


def test_parameters_from_blocks_are_the_former_params():
    rep = _reps(1)[0]
    fits = rep.fits

    def params(model, names, values, stderrs, unit):
        return [Param(model, n, float(v), float(e), unit) for n, v, e in
                zip(names, np.ravel(values), np.ravel(stderrs))]

    g, a, st, lv = fits["gyro"], fits["accel"], fits["accel_static"], fits["lever_arm"]
    mat = [f"{i}{j}" for i in "123" for j in "123"]
    expected = {
        "gyro": params("gyro", [f"k_g{s}" for s in mat], g.K, g.K_stderr,
                       f"deg/s per {g.raw_unit}")
        + params("gyro", [f"w0_{x}" for x in AXES], g.w0, g.w0_stderr, "deg/s"),
        "accel": params("accel", [f"k_a{s}" for s in mat], a.K, a.K_stderr,
                        f"g per {a.raw_unit}")
        + params("accel", [f"f0_{x}" for x in AXES], a.f0, a.f0_stderr, "g"),
        "accel_static": params("accel_static", [f"k_{x}" for x in AXES], st.scale,
                               st.scale_stderr, f"{st.unit}/g")
        + params("accel_static", [f"u0_{x}" for x in AXES], st.bias, st.bias_stderr, st.unit)
        + params("accel_static", [f"theta_{x}{y}" for x in AXES for y in AXES],
                 st.angles_deg, st.angles_stderr, "deg"),
        "lever_arm": params("lever_arm", [f"r{i}{x}" for i in "123" for x in AXES],
                            lv.lever_arm_mm, lv.stderr, "mm"),
    }
    for name in ("gyro_traditional", "accel_traditional"):
        t = fits[name]
        s, b = ("s_g", "b_g") if name.startswith("gyro") else ("s_a", "b_a")
        expected[name] = (params(name, [f"{s}{x}" for x in mat], t.S, t.S_stderr,
                                 f"{t.raw_unit} per {t.physical_unit}")
                          + params(name, [f"{b}_{x}" for x in AXES], t.b, t.b_stderr,
                                   t.raw_unit))
    assert set(expected) == set(fits)
    for name, fit in fits.items():
        got = fit.parameters()
        assert got == expected[name], name
        assert all(type(p.value) is float and type(p.stderr) is float for p in got)


def test_block_layout_is_keyed_by_heads():
    heads = (("m", ("a", "b"), "u"), ("n", ("a",), "v"))
    keys, units, distinct = _block_layout(heads)
    assert keys == (("m", "a"), ("m", "b"), ("n", "a")) and units == ("u", "u", "v")
    assert distinct
    assert not _block_layout((("m", ("a",), "u"), ("m", ("a",), "v")))[2]
    # another unit of the same names is another layout (units are not shared by mistake)
    assert _block_layout((("m", ("a", "b"), "w"), ("n", ("a",), "v")))[1] == ("w", "w", "v")
