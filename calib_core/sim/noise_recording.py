"""A unit's long static recording, simulated: what ``lot=L/unit=U/noise/<name>.parquet``
holds (docs/data-contract.md), for the fleet simulator and the noise tests.

The unit sits at rest with ``up`` pointing up (specific force 1 g along it, no rotation);
its outputs are the truth's affine model inverted (raw = K^-1 (physical - bias)) plus noise
in physical units: either the truth's own (white per sample, ``MimuTruth.gyro_noise_dps`` /
``accel_noise_g``, times ``white_factor``) or a measured model's record (``noise``: (n, 6)
deg/s and g, e.g. :func:`calib_core.noise.synthesize` of a ``mimucal noise`` model).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from calib_core.sim.simulator import MimuTruth, _to_raw, _vec3


def static_noise_recording(
    truth: MimuTruth,
    duration_s: float,
    rate_hz: float,
    rng: np.random.Generator,
    up: tuple[float, float, float] = (0.0, 0.0, 1.0),
    noise: np.ndarray | None = None,
    dtype=np.float32,
) -> pd.DataFrame:
    """Raw samples (``t``, ``gx..az``) of a static recording of ``duration_s`` at ``rate_hz``."""
    n = int(round(duration_s * rate_hz))
    if n < 2:
        raise ValueError("a static recording needs at least two samples")
    phys = np.zeros((n, 6))
    phys[:, 3:] = np.asarray(up, float) / np.linalg.norm(up)
    if noise is None:
        sd = np.concatenate([_vec3(truth.gyro_noise_dps), _vec3(truth.accel_noise_g)])
        phys += rng.normal(0.0, 1.0, (n, 6)) * sd
    else:
        noise = np.asarray(noise, float)
        if noise.shape != (n, 6):
            raise ValueError(f"noise must be ({n}, 6), got {noise.shape}")
        phys += noise
    G, A = _to_raw(truth, phys)
    if truth.gyro_quantum:
        G = np.round(G / truth.gyro_quantum) * truth.gyro_quantum
    if truth.accel_quantum:
        A = np.round(A / truth.accel_quantum) * truth.accel_quantum
    out = {"t": np.arange(n) / rate_hz}
    for i, c in enumerate(("gx", "gy", "gz")):
        out[c] = G[:, i].astype(dtype)
    for i, c in enumerate(("ax", "ay", "az")):
        out[c] = A[:, i].astype(dtype)
    return pd.DataFrame(out)
