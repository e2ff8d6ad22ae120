"""Close the loop: find what the drift model lacks in measured data, add it, report before and after.

``diagnose()`` trains the baseline on the declared inputs, tests generic candidate effects
against its held-out residual with a family-wise permutation test, adds those that pass and that
the retrained network confirms on held-out data, and repeats (:mod:`.loop`, :mod:`.choose`). The
candidates (:mod:`.candidates`) are built from whatever the recording holds, so a new channel in
a new recording needs no new code; the rows they are scored on are in :mod:`.rows`, the test in
:mod:`.screen`, the report and its figures in :mod:`.report`. Equivalent explanations are grouped
in :mod:`.choose` (the simplest kept, the others its ``alternatives``); several runs
(``data.paths``) go through :mod:`.runs`, with run-level candidates (``run_offset``, orientation)
and their null in :mod:`.runlevel`; what to record next is :mod:`.advice`. The table (docs/results/effects.md) on
the simulator's effects (both bundles checked on another history) is :mod:`.effects`.
"""
from gyronet.analysis.diagnose.candidates import CandidateGrid, candidate_specs, effect_kind, filter_tau
from gyronet.analysis.diagnose.loop import DiagnoseOptions, diagnose
from gyronet.analysis.diagnose.rows import ScreenRows
from gyronet.analysis.diagnose.screen import screen, shift_fractions

__all__ = ["CandidateGrid", "DiagnoseOptions", "ScreenRows", "candidate_specs", "diagnose", "effect_kind",
           "filter_tau", "screen", "shift_fractions"]
