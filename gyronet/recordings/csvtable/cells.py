"""Text cells to numbers, the one reading shared by the table parser and the ``bad_lines=drop`` filter."""
from __future__ import annotations

from typing import Sequence

import numpy as np
import pandas as pd

# what both parsers read as NaN (pandas' defaults, passed explicitly so the text path agrees)
NA_TOKENS = ("", "#N/A", "#N/A N/A", "#NA", "-1.#IND", "-1.#QNAN", "-NaN", "-nan", "1.#IND", "1.#QNAN",
             "<NA>", "N/A", "NA", "NULL", "NaN", "None", "n/a", "nan", "null")
MISSING = "missing value (an empty cell, NaN, NA, n/a, null or the like)"


def parse_numbers(cells: Sequence[str], decimal: str) -> tuple[np.ndarray, np.ndarray]:
    """Text cells -> float64 and a mask of the cells that are not numbers (NA spellings give NaN)."""
    text = pd.Series(cells, dtype=object).str.strip(" \t")
    missing = text.isin(NA_TOKENS).to_numpy()
    wrong = np.zeros(len(text), dtype=bool)
    if decimal != ".":
        wrong = text.str.contains(".", regex=False).to_numpy(dtype=bool)
        text = text.str.replace(decimal, ".", regex=False)
    values = pd.to_numeric(text, errors="coerce").to_numpy(dtype=np.float64)
    return values, wrong | (np.isnan(values) & ~missing)
