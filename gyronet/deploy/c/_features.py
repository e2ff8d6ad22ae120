"""Feature specs (``meta.json`` ``features``) as C: the same causal features as gyronet.model.features, per sample.

Each spec becomes a few statements of ``features_accepted`` (an accepted sample: filters restart on
an event, then step), ``features_power_on`` (a rejected sample before any accepted one: the fresh
filters' output at ``PRIOR_TEMP_C``) and ``time_features`` (at every sample's own time). ``v[0]``
is the temperature, ``v[1 + k]`` the k-th aux input.
"""
from __future__ import annotations

import math
from typing import Any, Mapping, NamedTuple, Sequence

from gyronet.deploy.c import c_float
from gyronet.errors import BundleError
from gyronet.model.feature_kinds import lagged_inputs
from gyronet.model.feature_specs import feature_name, product_rate_index
from gyronet.recordings.guard import MAX_TEMP_RATE_C_PER_S

# an unbounded slope for a rate of another column than the temperature
_NO_SLOPE_BOUND = 3.0e38


class FeatureCode(NamedTuple):
    """The C of a feature list: constants and the three function bodies, and the state they need."""

    constants: str
    accepted: str
    power_on: str
    time: str
    n_filter: int  # floats of filter state
    n_play: int  # hysteresis play operators


def aux_inputs(specs: Sequence[Mapping[str, Any]], input_columns: Sequence[str]) -> list[str]:
    """The columns besides temperature that the features read, in the order ``input_columns`` lists them."""
    from gyronet.model.features import required_columns

    needed = [c for c in required_columns(specs) if c not in ("time_s", "temp_c")]
    return [c for c in input_columns if c in needed] + [c for c in needed if c not in input_columns]


def feature_code(specs: Sequence[Mapping[str, Any]], fs_hz: float, aux: Sequence[str], source: str) -> FeatureCode:
    """C for ``specs`` at ``fs_hz``; ``aux``: the aux inputs' order; ``source`` names the bundle in errors."""
    dt_s = 1.0 / fs_hz
    constants, accepted, power_on, timed = [], [], [], []
    n_filter = n_play = 0
    raw_slope_of = {}  # (source, tau_s, max_slope) -> a feature holding that tracker's slope, unlagged
    # v as a fresh filter sees it in a rejected row: the prior temperature, other columns 0 where not finite
    power_on.append("    float w[1 + GYRONET_N_AUX];\n    w[0] = PRIOR_TEMP_C;")
    for k in range(len(aux)):
        power_on.append(f"    w[{k + 1}] = isfinite(v[{k + 1}]) ? v[{k + 1}] : 0.0f;")
    index_of = {feature_name(spec): i for i, spec in enumerate(specs)}
    for i, spec in enumerate(specs):
        kind, column = spec["kind"], spec.get("source", "temp_c")
        k = 1 + list(aux).index(column) if column in aux else 0  # where v holds the source column
        where = f"{source}: features[{i}] ({kind})"
        if kind == "temp":
            accepted.append(f"    x[{i}] = v[0];")
            power_on.append(f"    x[{i}] = w[0];")
        elif kind == "rate":
            tau_s = float(spec.get("tau_s", 5.0))
            theta = math.exp(-dt_s / tau_s)
            max_slope = MAX_TEMP_RATE_C_PER_S if column == "temp_c" else _NO_SLOPE_BOUND
            # alpha = 1 - theta^2, beta = (1 - theta)^2 (gyronet.model.filters.RateTracker); alpha - 1 and
            # beta / dt in float64, which float32 then holds to its full precision
            lagged = float(spec.get("lag_s", 0.0)) > 0
            tracker = (column, tau_s, max_slope)
            if lagged and tracker in raw_slope_of:  # the same tracker on the same input: the same slope, run once
                slope = f"x[{raw_slope_of[tracker]}]"
            else:
                constants.append(f"static const tracker_coef TRACKER_{i} = {{{c_float(dt_s)}, {c_float(-theta ** 2)}, "
                                 f"{c_float((1 - theta) ** 2 / dt_s)}, {c_float(tau_s)}, {c_float(max_slope)}}};")
                accepted.append(f"    if (event != EVENT_NONE) {{\n        tracker_restart(&s->filter[{n_filter}], "
                                f"&TRACKER_{i}, v[{k}], event, gap_s);\n    }}\n"
                                f"    x[{i}] = tracker_step(&s->filter[{n_filter}], &TRACKER_{i}, v[{k}]);")
                n_filter += 3
                slope = f"x[{i}]"
                if not lagged:
                    raw_slope_of.setdefault(tracker, i)
            power_on.append(f"    x[{i}] = 0.0f;")
            if lagged:  # then through a lag (gyronet.model.filters.LaggedRate)
                constant, statement = _lag_c(f"RATE_LAG_{i}", float(spec["lag_s"]), dt_s, n_filter, slope, i)
                constants.append(constant)
                accepted.append(statement)
                n_filter += 2
        elif kind == "product" and float(spec.get("lag_s", 0.0)) > 0:
            temp_name, rate_name = lagged_inputs(spec)
            if temp_name not in index_of or rate_name not in index_of:
                raise BundleError(f"{where}: a lagged 'product' feature needs {temp_name} and {rate_name} before it")
            accepted.append(f"    x[{i}] = x[{index_of[temp_name]}] * x[{index_of[rate_name]}];")
            power_on.append(f"    x[{i}] = 0.0f;")
        elif kind == "product":
            try:
                rate_index = product_rate_index(specs, i)
            except ValueError as err:
                raise BundleError(f"{where}: {err}") from None
            accepted.append(f"    x[{i}] = v[0] * x[{rate_index}];")
            power_on.append(f"    x[{i}] = 0.0f;")
        elif kind == "lag" or (kind == "column" and float(spec.get("tau_s", 0.0)) > 0):
            constant, statement = _lag_c(f"LAG_{i}", float(spec["tau_s"]), dt_s, n_filter, f"v[{k}]", i)
            constants.append(constant)
            accepted.append(statement)
            power_on.append(f"    x[{i}] = w[{k}];")
            n_filter += 2
        elif kind == "column":
            accepted.append(f"    x[{i}] = v[{k}];")
            power_on.append(f"    x[{i}] = w[{k}];")
        elif kind == "power":
            exponent = float(spec["exponent"])
            if not exponent.is_integer() or abs(exponent) > 64:
                raise BundleError(f"{where}: exponent {exponent:g} is not a whole number up to 64, which the C "
                                  "export needs (it has no powf)")
            term = f"ipow(%s - {c_float(float(spec.get('centre', 0.0)))}, {int(exponent)})"
            accepted.append(f"    x[{i}] = {term % f'v[{k}]'};")
            power_on.append(f"    x[{i}] = {term % f'w[{k}]'};")
        elif kind == "hysteresis":
            width = c_float(float(spec["width"]))
            # play operator: follows v only when v leaves [play - width, play + width]
            accepted.append(f"    s->play[{n_play}] = clampf(event == EVENT_POWER_ON ? v[{k}] : s->play[{n_play}], "
                            f"v[{k}] - {width}, v[{k}] + {width});\n    x[{i}] = v[{k}] - s->play[{n_play}];")
            power_on.append(f"    x[{i}] = 0.0f;")
            n_play += 1
        elif kind == "time":
            accepted.append(f"    x[{i}] = 0.0f;")
            power_on.append(f"    x[{i}] = 0.0f;")
            tau_s = spec.get("tau_s")
            elapsed = "(time_s - s->start_time_s)"
            timed.append(f"    x[{i}] = expf((float)(-{elapsed} / {float(tau_s)!r}));" if tau_s else
                         f"    x[{i}] = (float)({elapsed} / 3600.0);")
        else:
            raise BundleError(f"{where}: a feature kind the C export does not know")
    unused = "    (void)s;\n    (void)event;\n    (void)gap_s;\n"
    power_on.append("    (void)v;\n    (void)w;")
    return FeatureCode("\n".join(constants), unused + "\n".join(accepted), "\n".join(power_on),
                       "    (void)s;\n    (void)time_s;\n    (void)x;\n" + "\n".join(timed),
                       max(n_filter, 1), max(n_play, 1))


def _lag_c(name: str, tau_s: float, dt_s: float, n_filter: int, source: str, i: int) -> tuple[str, str]:
    """A first-order lag's constant ``name`` and the statement that runs ``source`` through it into ``x[i]``."""
    gain = c_float(-math.expm1(-dt_s / tau_s))  # 1 - decay
    state = f"&s->filter[{n_filter}], &{name}, {source}"
    return (f"static const lag_coef {name} = {{{gain}, {c_float(tau_s)}}};",
            f"    x[{i}] = event != EVENT_NONE ? lag_restart({state}, event, gap_s)\n"
            f"                            : lag_step({state});")
