"""Close the loop: find what the drift model lacks in measured data, add it, report before and after.

``diagnose()`` trains the baseline on the declared inputs, tests generic candidate effects
against its held-out residual with a family-wise permutation test, adds those that pass and that
the retrained network confirms on held-out data, and repeats (:mod:`.loop`, :mod:`.choose`). The
candidates (:mod:`.candidates`) are built from whatever the recording holds, so a new channel in
a new recording needs no new code; the rows they are scored on are in :mod:`.rows`, the test in
:mod:`.screen`, the report and its figures in :mod:`.report`.
"""
from gyronet.diagnose.candidates import (CandidateGrid, candidate_specs, describe, effect_kind, effect_params,
                                         effect_source, filter_tau, source_columns)
from gyronet.diagnose.choose import Choice, ranked, refine
from gyronet.diagnose.loop import DiagnoseOptions, Stage, diagnose
from gyronet.diagnose.report import data_notes, rivals, write_report
from gyronet.diagnose.rows import ScreenRows
from gyronet.diagnose.screen import ScreenResult, assign_folds, choose_ridge, score_only, screen, shift_fractions

__all__ = [
    "CandidateGrid", "Choice", "DiagnoseOptions", "ScreenResult", "ScreenRows", "Stage", "assign_folds",
    "candidate_specs", "choose_ridge", "data_notes", "describe", "diagnose", "effect_kind", "effect_params",
    "effect_source", "filter_tau", "ranked", "refine", "rivals", "score_only", "screen", "shift_fractions",
    "source_columns", "write_report",
]
