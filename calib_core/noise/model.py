"""The measured noise model of one recording: per channel, the processes that discovery
named with their coefficients (inside units: the channel unit and seconds, see
:mod:`calib_core.noise.units`), periodic lines and the output resolution.

:meth:`NoiseModel.to_dict` writes the stable JSON of ``mimucal noise --json`` (coefficients
in IEEE 952/1293 units, each with its unit and interval; :class:`NoiseAnalysis` adds the
Allan curves and the fit); :meth:`NoiseModel.from_dict` reads it back (either document),
converting every figure from the unit written beside it.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

from calib_core.noise import units

FORMAT_VERSION = 1
COEFFICIENTS = ("quantization", "white", "bias_instability", "random_walk", "ramp")
GYRO_CHANNELS = ("gx", "gy", "gz")
ACCEL_CHANNELS = ("ax", "ay", "az")


@dataclass(frozen=True)
class ChannelNoise:
    """Noise of one channel. ``coefficients`` holds the named processes only (inside units);
    a process that is not there is not in the model, and ``reasons`` says why (with an upper
    bound in ``upper_bounds`` where the record gives one). ``gauss_markov`` is (sigma,
    correlation time in s); ``periodic`` is ((frequency_hz, amplitude), ...) of
    ``A sin(2 pi f t + phi)``; ``resolution`` the output step (channel unit), if known."""

    unit: str
    coefficients: Mapping[str, float] = field(default_factory=dict)
    intervals: Mapping[str, tuple[float, float]] = field(default_factory=dict)
    gauss_markov: tuple[float, float] | None = None
    gauss_markov_interval: tuple[float, float] | None = None
    periodic: tuple[tuple[float, float], ...] = ()
    resolution: float | None = None
    reasons: Mapping[str, str] = field(default_factory=dict)
    upper_bounds: Mapping[str, float] = field(default_factory=dict)

    def value(self, name: str) -> float:
        """A coefficient in inside units, 0 when the process is not in the model."""
        return float(self.coefficients.get(name, 0.0))

    def _entry(self, name: str) -> dict | None:
        unit = units.ieee_unit(name, self.unit)
        if name in self.coefficients:
            lo, hi = self.intervals.get(name, (self.coefficients[name],) * 2)
            return {
                "value": units.to_ieee(name, self.coefficients[name], self.unit),
                "lo": units.to_ieee(name, lo, self.unit),
                "hi": units.to_ieee(name, hi, self.unit),
                "unit": unit,
                "convention": "IEEE 952/1293",
                "native": {
                    "value": self.coefficients[name],
                    "unit": units.native_unit(name, self.unit),
                },
            }
        reason = self.reasons.get(name, "not in the model")
        if name in self.upper_bounds:
            return {
                "value": None,
                "lo": 0.0,
                "hi": units.to_ieee(name, self.upper_bounds[name], self.unit),
                "unit": unit,
                "convention": "IEEE 952/1293",
                "reason": reason,
            }
        return {"value": None, "unit": unit, "reason": reason}

    def to_dict(self) -> dict:
        coefficients = {name: self._entry(name) for name in COEFFICIENTS}
        if self.gauss_markov is not None:
            sigma, tc = self.gauss_markov
            lo, hi = self.gauss_markov_interval or (sigma, sigma)
            coefficients["gauss_markov"] = {
                "value": units.to_ieee("gauss_markov", sigma, self.unit),
                "lo": units.to_ieee("gauss_markov", lo, self.unit),
                "hi": units.to_ieee("gauss_markov", hi, self.unit),
                "unit": units.ieee_unit("gauss_markov", self.unit),
                "correlation_time_s": tc,
                "convention": "IEEE 952/1293",
            }
        return {
            "unit": self.unit,
            "coefficients": coefficients,
            "periodic": [{"frequency_hz": f, "amplitude": a, "unit": self.unit} for f, a in self.periodic],
            "resolution": None if self.resolution is None else {"value": self.resolution, "unit": self.unit},
        }

    @classmethod
    def from_dict(cls, d: Mapping) -> ChannelNoise:
        unit = str(d["unit"])
        units.channel_kind(unit)  # a physical unit, or ValueError
        coefficients, intervals, reasons, upper = {}, {}, {}, {}
        gm = gm_interval = None
        for name, entry in (d.get("coefficients") or {}).items():
            if entry is None:
                continue
            if name == "gauss_markov":
                if entry.get("value") is not None:
                    sigma = units.from_unit(name, entry["value"], entry["unit"], unit)
                    gm = (sigma, float(entry["correlation_time_s"]))
                    if entry.get("lo") is not None:
                        gm_interval = (
                            units.from_unit(name, entry["lo"], entry["unit"], unit),
                            units.from_unit(name, entry["hi"], entry["unit"], unit),
                        )
                continue
            if name not in COEFFICIENTS:
                raise ValueError(f"unknown noise coefficient {name!r}")
            if entry.get("value") is None:
                reasons[name] = str(entry.get("reason", "not in the model"))
                if entry.get("hi") is not None:
                    upper[name] = units.from_unit(name, entry["hi"], entry["unit"], unit)
                continue
            coefficients[name] = units.from_unit(name, entry["value"], entry["unit"], unit)
            if entry.get("lo") is not None and entry.get("hi") is not None:
                intervals[name] = (
                    units.from_unit(name, entry["lo"], entry["unit"], unit),
                    units.from_unit(name, entry["hi"], entry["unit"], unit),
                )
        periodic = []
        for line in d.get("periodic") or []:
            if line.get("unit", unit) != unit:
                raise ValueError(f"periodic amplitude in {line.get('unit')!r}, channel unit is {unit!r}")
            periodic.append((float(line["frequency_hz"]), float(line["amplitude"])))
        res = d.get("resolution")
        return cls(
            unit,
            coefficients,
            intervals,
            gm,
            gm_interval,
            tuple(periodic),
            None if res is None else float(res["value"]),
            reasons,
            upper,
        )


@dataclass(frozen=True)
class NoiseModel:
    """Noise model of one recording: ``channels`` {gx, gy, gz, ax, ay, az (any subset):
    ChannelNoise}, measured at ``rate_hz`` over ``duration_s``."""

    rate_hz: float
    duration_s: float
    channels: Mapping[str, ChannelNoise]

    def to_dict(self) -> dict:
        return {
            "format_version": FORMAT_VERSION,
            "rate_hz": self.rate_hz,
            "duration_s": self.duration_s,
            "channels": {name: ch.to_dict() for name, ch in self.channels.items()},
        }

    @classmethod
    def from_dict(cls, d: Mapping) -> NoiseModel:
        """Read a model or a whole ``mimucal noise --json`` document; ValueError names the
        first figure that cannot be read."""
        try:
            channels = {}
            for name, ch in d["channels"].items():
                try:
                    channels[str(name)] = ChannelNoise.from_dict(ch)
                except (KeyError, TypeError, ValueError) as exc:
                    raise ValueError(f"channel {name}: {exc}") from exc
            return cls(float(d["rate_hz"]), float(d["duration_s"]), channels)
        except KeyError as exc:
            raise ValueError(f"noise model lacks {exc.args[0]!r}") from exc
