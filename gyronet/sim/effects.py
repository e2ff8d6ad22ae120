"""Optional drift effects that a model of temperature (and dT/dt) alone cannot represent.

Each effect is a function ``effect(context, **params) -> EffectOutput``: a drift of shape
(n, 3) in deg/s that adds to the sensor's thermal drift, and any recording columns it creates.
All are off unless named in ``simulate(effects={name: {params}})``; the name is the effect's kind
unless the params give ``kind`` (so two aux channels can be ``{"aux": {...}, "hum": {"kind":
"aux", "column": "humidity_pct", ...}}``).

=========== ======================================================================================
kind        drift added (per axis; ``T`` is the true die temperature, degC)
=========== ======================================================================================
lag2        ``gain_dps_per_c * (lag(T, tau_s) - T)``: a slower thermal path (e.g. the package or
            board), zero when settled; decays over ``tau_s`` after every ramp
hysteresis  ``gain_dps * (T - play(T)) / width_c``: the play (backlash) operator of half-width
            ``width_c`` stays within ``T +- width_c``, so the term is ``+gain`` while heating and
            ``-gain`` while cooling, and moves between them over ``2 width_c`` of reversal
aux         ``gain_dps_per_v * (lag(v, tau_s) - nominal)`` of an auxiliary channel ``v`` written as
            the column ``column`` (default ``vdd_v``: 3.3 V with slow wander and level steps)
warmup      ``amplitude_dps * exp(-t / tau_s)``: a settling after power-on (t = 0)
ageing      ``rate_dps_per_h * t / 3600``: a linear drift in time
board       ``gain_dps_per_c * (lag(B, tau_s) - T)``: a gradient between the board and the die, where
            the board ``B`` follows the chamber through its own ``board_tau_s`` (slower than the die)
            plus its warm-up, seen through ``tau_s`` where the gradient acts; ``B`` is recorded as
            ``column`` (default ``board_temp_c``), which no model is told about
=========== ======================================================================================

References
----------
M. Brokate and J. Sprekels, *Hysteresis and Phase Transitions*, Springer (1996), ch. 2 (the play
operator).
"""
from __future__ import annotations

import inspect
import logging
import zlib
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from gyronet.errors import GyronetError
from gyronet.sim.noise import ou_process, quantise
from gyronet.sim.sensor import first_order_lag, per_axis

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class EffectContext:
    """What an effect may depend on: time, temperatures and its own random stream."""

    time_s: np.ndarray
    fs_hz: float
    die_temp_c: np.ndarray
    chamber_temp_c: np.ndarray
    rng: np.random.Generator


@dataclass
class EffectOutput:
    """An effect's drift, shape (n, 3), deg/s, and the recording columns it adds."""

    drift_dps: np.ndarray
    columns: dict[str, np.ndarray] = field(default_factory=dict)


def _axes(gain: Any, values: np.ndarray, name: str) -> np.ndarray:
    """``values`` (n,) times a per-axis gain: shape (n, 3)."""
    return values[:, None] * per_axis(gain, name)[None, :]


def lag2(ctx: EffectContext, tau_s: float = 1800.0,
         gain_dps_per_c: Sequence[float] | float = (0.008, -0.006, 0.005)) -> EffectOutput:
    """A second, slower thermal time constant: drift in the gradient ``lag(T, tau_s) - T``."""
    gradient_c = first_order_lag(ctx.die_temp_c, ctx.fs_hz, tau_s) - ctx.die_temp_c
    return EffectOutput(_axes(gain_dps_per_c, gradient_c, "lag2.gain_dps_per_c"))


def play_operator(values: np.ndarray, width: float, start: float | None = None) -> np.ndarray:
    """The play (backlash) operator: ``p[k] = min(max(p[k-1], x[k] - width), x[k] + width)``.

    Parameters
    ----------
    values
        Input, shape (n,).
    width
        Half-width of the play: the output stays within ``values +- width``.
    start
        The initial state ``p[-1]``; by default ``values[0]`` (centred).

    Returns
    -------
    numpy.ndarray
        Shape (n,).
    """
    state = float(values[0]) if start is None else float(start)
    out = np.empty(len(values))
    for k, value in enumerate(values.tolist()):
        if value - width > state:
            state = value - width
        elif value + width < state:
            state = value + width
        out[k] = state
    return out


def hysteresis(ctx: EffectContext, width_c: float = 2.0,
               gain_dps: Sequence[float] | float = (0.05, -0.04, 0.03)) -> EffectOutput:
    """Heating-versus-cooling hysteresis: ``gain_dps * (T - play(T)) / width_c``."""
    if width_c <= 0:
        raise GyronetError(f"effect hysteresis: width_c must be positive, got {width_c}")
    branch = (ctx.die_temp_c - play_operator(ctx.die_temp_c, width_c)) / width_c
    return EffectOutput(_axes(gain_dps, branch, "hysteresis.gain_dps"))


def aux_channel(ctx: EffectContext, nominal: float, wander: float, wander_tau_s: float,
                step: float, step_rate_per_h: float, temp_coeff_per_c: float) -> np.ndarray:
    """True value of an auxiliary channel: nominal + wander + level steps + chamber coupling.

    The wander is a Gauss-Markov process of std ``wander`` and time constant ``wander_tau_s``;
    level changes come at Poisson times (``step_rate_per_h``), each to a new level drawn with std
    ``step``; ``temp_coeff_per_c`` couples the channel to the chamber temperature about 25 degC.
    """
    n = len(ctx.time_s)
    value = np.full(n, float(nominal))
    if wander > 0:
        value += ou_process(n, ctx.fs_hz, wander, wander_tau_s, ctx.rng)
    span_h = (ctx.time_s[-1] - ctx.time_s[0]) / 3600.0
    n_steps = ctx.rng.poisson(step_rate_per_h * span_h) if step > 0 else 0
    if n_steps:
        when_s = np.sort(ctx.rng.uniform(ctx.time_s[0], ctx.time_s[-1], n_steps))
        levels = np.concatenate([[0.0], step * ctx.rng.standard_normal(n_steps)])
        value += levels[np.searchsorted(when_s, ctx.time_s, side="right")]
    return value + temp_coeff_per_c * (ctx.chamber_temp_c - 25.0)


def aux(ctx: EffectContext, column: str = "vdd_v", nominal: float = 3.3, wander: float = 0.01,
        wander_tau_s: float = 1800.0, step: float = 0.05, step_rate_per_h: float = 0.5,
        temp_coeff_per_c: float = 0.0, read_noise: float = 0.002, lsb: float = 0.001,
        tau_s: float = 0.0, gain_dps_per_v: Sequence[float] | float | None = None,
        gain_dps_per_unit: Sequence[float] | float | None = None) -> EffectOutput:
    """Drift from an auxiliary channel (supply voltage by default), written as ``column``.

    ``gain_dps_per_unit`` is the same as ``gain_dps_per_v`` for a channel that is not a voltage
    (default (0.5, -0.3, 0.4) deg/s per unit). The recording gets the channel plus read noise of
    std ``read_noise``, quantised to ``lsb``; the drift uses the true value through a
    first-order lag of ``tau_s`` (0: none).
    """
    if gain_dps_per_v is not None and gain_dps_per_unit is not None:
        raise GyronetError("effect aux: give gain_dps_per_v or gain_dps_per_unit, not both")
    gain = next((g for g in (gain_dps_per_v, gain_dps_per_unit) if g is not None), (0.5, -0.3, 0.4))
    true_value = aux_channel(ctx, nominal, wander, wander_tau_s, step, step_rate_per_h, temp_coeff_per_c)
    seen = first_order_lag(true_value, ctx.fs_hz, tau_s) - nominal
    reading = quantise(true_value + read_noise * ctx.rng.standard_normal(len(true_value)), lsb)
    return EffectOutput(_axes(gain, seen, "aux.gain"), {column: reading})


def warmup(ctx: EffectContext, tau_s: float = 900.0,
           amplitude_dps: Sequence[float] | float = (0.08, -0.06, 0.05)) -> EffectOutput:
    """Exponential settling after power-on: ``amplitude_dps * exp(-t / tau_s)``."""
    decay = np.exp(-(ctx.time_s - ctx.time_s[0]) / tau_s)
    return EffectOutput(_axes(amplitude_dps, decay, "warmup.amplitude_dps"))


def ageing(ctx: EffectContext,
           rate_dps_per_h: Sequence[float] | float = (0.004, -0.003, 0.005)) -> EffectOutput:
    """A linear drift in time: ``rate_dps_per_h * t / 3600``."""
    hours = (ctx.time_s - ctx.time_s[0]) / 3600.0
    return EffectOutput(_axes(rate_dps_per_h, hours, "ageing.rate_dps_per_h"))


def board(ctx: EffectContext, column: str = "board_temp_c", board_tau_s: float = 1500.0, offset_c: float = 1.0,
          self_heating_c: float = 2.0, warmup_tau_s: float = 1800.0, tau_s: float = 600.0,
          read_noise_c: float = 0.05, lsb_c: float = 0.01,
          gain_dps_per_c: Sequence[float] | float = (0.008, -0.006, 0.005)) -> EffectOutput:
    """A board/die gradient: drift ``gain * (lag(B, tau_s) - T)``, the board temperature ``B`` recorded.

    ``B`` is the chamber through the board's own time constant ``board_tau_s``, ``offset_c``
    above it, plus the board's self-heating ``self_heating_c * (1 - exp(-t / warmup_tau_s))``;
    ``tau_s`` is the path from the board to where the gradient acts (0: none). Settled, the
    gradient is a constant; on every ramp it follows the lag between board and die, which a lag
    of the die temperature alone can only approximate. The column gets read noise of std
    ``read_noise_c``, quantised to ``lsb_c``.
    """
    elapsed_s = ctx.time_s - ctx.time_s[0]
    board_c = (first_order_lag(ctx.chamber_temp_c, ctx.fs_hz, board_tau_s) + offset_c
               + self_heating_c * -np.expm1(-elapsed_s / warmup_tau_s))
    gradient_c = first_order_lag(board_c, ctx.fs_hz, tau_s) - ctx.die_temp_c
    reading = quantise(board_c + read_noise_c * ctx.rng.standard_normal(len(board_c)), lsb_c)
    return EffectOutput(_axes(gain_dps_per_c, gradient_c, "board.gain_dps_per_c"), {column: reading})


EFFECTS: dict[str, Callable[..., EffectOutput]] = {
    "lag2": lag2, "hysteresis": hysteresis, "aux": aux, "warmup": warmup, "ageing": ageing, "board": board,
}


def apply_effect(name: str, params: Mapping[str, Any] | None, time_s: np.ndarray, fs_hz: float,
                 die_temp_c: np.ndarray, chamber_temp_c: np.ndarray, seed: int) -> EffectOutput:
    """Run the effect ``name`` (kind ``params['kind']``, else ``name``) with its own random stream.

    The stream depends on ``seed`` and ``name`` only, so adding an effect leaves the others and the
    noise unchanged.
    """
    params = dict(params or {})
    kind = str(params.pop("kind", name))
    if kind not in EFFECTS:
        raise GyronetError(f"unknown effect {kind!r}; choose from {', '.join(EFFECTS)}")
    function = EFFECTS[kind]
    known = [p for p in inspect.signature(function).parameters if p != "ctx"]
    unknown = sorted(set(params) - set(known))
    if unknown:
        raise GyronetError(f"effect {name!r}: unknown option(s) {', '.join(unknown)}; "
                           f"known: {', '.join(known)}")
    rng = np.random.default_rng([int(seed), 3000, zlib.crc32(name.encode())])
    ctx = EffectContext(time_s, fs_hz, die_temp_c, chamber_temp_c, rng)
    return function(ctx, **params)
