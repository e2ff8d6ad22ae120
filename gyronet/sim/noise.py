"""Gyro noise (angle random walk, bias instability, rate random walk), quantisation, Earth rate.

Units follow IEEE Std 952: angle random walk ``N`` in deg/sqrt(h), bias instability ``B`` in
deg/h, rate random walk ``K`` in deg/h/sqrt(h). Their Allan deviations are::

    sigma(tau) = N / sqrt(tau)          white rate noise
    sigma(tau) = 0.664 B                flicker rate noise (the plateau)
    sigma(tau) = K sqrt(tau / 3)        random walk of the rate

The flicker noise has the PSD ``B^2 / (2 pi f)`` of IEEE Std 952 Annex C, whose Allan formula
``sigma^2 = 4 int S(f) sin^4(pi f tau) / (pi f tau)^2 df`` makes it a two-sided density: the
one-sided PSD is ``B^2 / (pi f)`` and the plateau is ``B sqrt(2 ln 2 / pi) = 0.664 B``. It is
shaped in the frequency domain from white noise on twice the record length (so the circular
FFT does not join the record's end to its start).

References
----------
IEEE Std 952-1997, *IEEE Standard Specification Format Guide and Test Procedure for Single-Axis
Interferometric Fiber Optic Gyros*, Annex C.

W. J. Riley, *Handbook of Frequency Stability Analysis*, NIST SP 1065 (2008), section 5.

J. Timmer and M. Koenig, "On generating power law noise", *Astron. Astrophys.* 300, 707 (1995).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy import fft, signal

from gyronet.sim.sensor import N_AXES, per_axis

log = logging.getLogger(__name__)

EARTH_RATE_DEG_HR = 15.041  # sidereal rotation, 7.292115e-5 rad/s
SECONDS_PER_HOUR = 3600.0


@dataclass(frozen=True)
class NoiseSpec:
    """The gyro noise, per axis (x, y, z) or one number for all three.

    Attributes
    ----------
    arw_deg_rthr
        Angle random walk N, deg/sqrt(h) (the paper's raw figures by default).
    bias_instability_deg_hr
        Bias instability B, deg/h (near the paper's compensated figures by default).
    rrw_deg_hr_rthr
        Rate random walk K, deg/h/sqrt(h).
    lsb_dps
        Output quantisation step, deg/s (8.75 mdps: a 16-bit gyro at +-250 deg/s); 0 for none.
    """

    arw_deg_rthr: Sequence[float] | float = (3.03, 4.55, 5.89)
    bias_instability_deg_hr: Sequence[float] | float = (2.9, 3.9, 1.6)
    rrw_deg_hr_rthr: Sequence[float] | float = (0.5, 0.6, 0.4)
    lsb_dps: float = 0.00875


def white_rate_noise_dps(n: int, fs_hz: float, arw_deg_rthr: float,
                         rng: np.random.Generator) -> np.ndarray:
    """White rate noise of angle random walk ``N``: sample sigma = N[deg/sqrt(s)] * sqrt(fs), deg/s."""
    # deg/sqrt(h) -> deg/sqrt(s): divide by sqrt(3600) = 60
    return (arw_deg_rthr / 60.0) * np.sqrt(fs_hz) * rng.standard_normal(n)


def flicker_rate_noise_dps(n: int, fs_hz: float, bias_instability_deg_hr: float,
                           rng: np.random.Generator) -> np.ndarray:
    """Flicker (1/f) rate noise whose Allan plateau is ``0.664 B``, deg/s.

    Unit-variance white noise has the one-sided PSD ``2 / fs``; each frequency bin is scaled by
    ``sqrt(S(f) fs / 2)`` with the one-sided target ``S(f) = B^2 / (pi f)``, DC removed.
    """
    if bias_instability_deg_hr == 0:
        return np.zeros(n)
    length = fft.next_fast_len(2 * n, real=True)
    spectrum = fft.rfft(rng.standard_normal(length), workers=-1)
    freq_hz = fft.rfftfreq(length, d=1.0 / fs_hz)
    b_dps = bias_instability_deg_hr / SECONDS_PER_HOUR
    gain = np.zeros_like(freq_hz)
    # |H(f)| = sqrt(S(f) fs / 2),  S(f) = B^2 / (pi f)
    gain[1:] = np.sqrt(b_dps**2 / (np.pi * freq_hz[1:]) * fs_hz / 2.0)
    return fft.irfft(spectrum * gain, n=length, workers=-1)[:n]


def rate_random_walk_dps(n: int, fs_hz: float, rrw_deg_hr_rthr: float,
                         rng: np.random.Generator) -> np.ndarray:
    """Random walk of the rate, starting at 0: steps of K[deg/s/sqrt(s)] * sqrt(1/fs), deg/s."""
    # deg/h/sqrt(h) -> deg/s/sqrt(s): divide by 3600 * 60
    k_dps_rts = rrw_deg_hr_rthr / (SECONDS_PER_HOUR * 60.0)
    return np.cumsum(k_dps_rts / np.sqrt(fs_hz) * rng.standard_normal(n))


def gyro_noise_dps(n: int, fs_hz: float, spec: NoiseSpec, seed: int) -> np.ndarray:
    """The sum of the three noise processes for each axis (before quantisation), shape (n, 3), deg/s.

    Every process and axis has its own stream derived from ``seed``, so switching one off leaves
    the others' realisations unchanged.
    """
    arw = per_axis(spec.arw_deg_rthr, "noise.arw_deg_rthr")
    bias = per_axis(spec.bias_instability_deg_hr, "noise.bias_instability_deg_hr")
    rrw = per_axis(spec.rrw_deg_hr_rthr, "noise.rrw_deg_hr_rthr")
    out = np.empty((n, N_AXES))
    for axis in range(N_AXES):
        stream = lambda k: np.random.default_rng([int(seed), 1000 + 10 * axis + k])  # noqa: E731
        out[:, axis] = (white_rate_noise_dps(n, fs_hz, arw[axis], stream(0))
                        + flicker_rate_noise_dps(n, fs_hz, bias[axis], stream(1))
                        + rate_random_walk_dps(n, fs_hz, rrw[axis], stream(2)))
    return out


def quantise(values: np.ndarray, lsb: float) -> np.ndarray:
    """Round to the nearest multiple of ``lsb`` (no change when ``lsb`` is 0)."""
    if lsb <= 0:
        return np.asarray(values, dtype=float).copy()
    return np.round(np.asarray(values) / lsb) * lsb


def body_from_enu(orientation_deg: Sequence[float]) -> np.ndarray:
    """Rotation taking East-North-Up vectors into the sensor frame, shape (3, 3).

    ``orientation_deg`` is (roll, pitch, yaw) in degrees, applied as yaw about Up, then pitch
    about the new y, then roll about the new x (z-y-x), each right-handed about its axis;
    (0, 0, 0) is x East, y North, z Up.
    """
    roll, pitch, yaw = np.radians(np.asarray(orientation_deg, dtype=float))
    cr, sr = np.cos(roll), np.sin(roll)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cy, sy = np.cos(yaw), np.sin(yaw)
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    enu_from_body = rz @ ry @ rx
    return enu_from_body.T


def earth_rate_dps(latitude_deg: float, orientation_deg: Sequence[float],
                   rate_deg_hr: float = EARTH_RATE_DEG_HR) -> np.ndarray:
    """Earth's rotation seen by a static sensor, shape (3,), deg/s.

    In East-North-Up the Earth rate is ``Omega (0, cos(lat), sin(lat))``.
    """
    lat = np.radians(latitude_deg)
    enu = rate_deg_hr / SECONDS_PER_HOUR * np.array([0.0, np.cos(lat), np.sin(lat)])
    return body_from_enu(orientation_deg) @ enu


def gravity_g(orientation_deg: Sequence[float]) -> np.ndarray:
    """Specific force on a static sensor, shape (3,), g: (0, 0, +1) when level with z Up."""
    return body_from_enu(orientation_deg) @ np.array([0.0, 0.0, 1.0])


def ou_process(n: int, fs_hz: float, std: float, tau_s: float, rng: np.random.Generator) -> np.ndarray:
    """Stationary Ornstein-Uhlenbeck (first-order Gauss-Markov) process of ``std`` and ``tau_s``."""
    decay = np.exp(-1.0 / (fs_hz * tau_s))
    drive = std * np.sqrt(1.0 - decay**2) * rng.standard_normal(n)
    start = std * rng.standard_normal()
    # x[k] = a x[k-1] + sqrt(1 - a^2) std e[k]
    out, _ = signal.lfilter([1.0], [1.0, -decay], drive, zi=[decay * start])
    return out
