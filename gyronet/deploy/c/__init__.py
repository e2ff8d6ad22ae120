"""The C99 compensator's parts: templates (``*.in``), a host CSV driver, and the code generators.

``_features`` turns feature specs into C, ``_model`` a bundle's model, ``_kalman`` its Kalman stage;
:mod:`gyronet.deploy.c_export` puts them into the templates.
"""
from pathlib import Path

HERE = Path(__file__).resolve().parent


def c_float(value: float) -> str:
    """A C float literal that is exactly ``value`` rounded to float32 (9 significant digits)."""
    import math

    import numpy as np

    value = float(np.float32(value))
    if not math.isfinite(value):
        raise ValueError(f"{value} has no C float literal")
    text = f"{value:.9g}"
    if not any(c in text for c in ".e"):
        text += ".0"
    return text + "f"


def c_array(values, per_line: int = 6) -> str:
    """``{a, b, ...}`` of float literals, a nested list becoming nested braces."""
    import numpy as np

    values = np.asarray(values, dtype=np.float64)
    if values.ndim > 1:
        return "{" + ", ".join(c_array(v, per_line) for v in values) + "}"
    items = [c_float(v) for v in values]
    lines = [", ".join(items[i:i + per_line]) for i in range(0, len(items), per_line)]
    return "{" + (",\n    ".join(lines) if len(lines) > 1 else (lines[0] if lines else "0.0f")) + "}"
