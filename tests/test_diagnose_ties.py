"""Equivalent explanations (issue 24, item 4): the tie test holds for collinear candidates, a measured
column comes first, and a derived effect says which measured column it approximates.

Fast tests on synthetic block arrays (the screen, the tie groups, the span clustering); the slow one
diagnoses a simulated board/die gradient (``sim/effects=board``) whose board sensor nobody declared.
"""
from types import SimpleNamespace

import numpy as np
import pytest

from gyronet.analysis.diagnose import screen
from gyronet.analysis.diagnose.choose import Choice, approximations, complexity, tie_groups
from gyronet.analysis.diagnose.report import approximation_sentence, evidence
from gyronet.analysis.diagnose.screen import assign_folds
from gyronet.analysis.diagnose.ties import block_contributions, paired_noise, span_labels
from gyronet.model.features import feature_name
from gyronet.sim import first_order_lag, simulate, write_simulation

N_BLOCKS = 560  # a 9.3 h record in 60 s blocks, 56 spans of 600 s
LAG_T = {"kind": "lag", "source": "temp_c", "tau_s": 1200.0}  # derived from the die temperature
BOARD_LAG = {"kind": "column", "source": "board_temp_c", "tau_s": 1200.0}  # a measured column through a lag


def _arrays(seed: int, own_noise: tuple = (0.1, 0.1)):
    """A basis, a target that follows ``signal``, and two near-copies of it: a lag of temp_c and the
    board column through a lag, each off the signal by its own smooth error of relative size
    ``own_noise`` (equal: by construction they fit equally well; the record only draws the errors)."""
    rng = np.random.default_rng(seed)
    time_s = np.arange(N_BLOCKS) * 60.0
    basis = np.column_stack([np.sin(2 * np.pi * k * time_s / time_s[-1]) for k in (1, 2)])
    signal = first_order_lag(rng.standard_normal(N_BLOCKS), 1.0, 15.0) * 5
    target = np.outer(signal, [0.3, -0.2, 0.1]) + 0.15 * rng.standard_normal((N_BLOCKS, 3))
    copies = np.column_stack([signal + size * signal.std() * 3 * first_order_lag(rng.standard_normal(N_BLOCKS), 1.0, 3.0)
                              for size in own_noise])
    return basis, target, copies, assign_folds(time_s, 56, 5)


def _collinear(seed: int, own_noise: tuple = (0.1, 0.1)):
    """The screen of ``_arrays``: row 0 the lag of temp_c, row 1 the board column through a lag."""
    basis, target, copies, fold = _arrays(seed, own_noise)
    return screen(basis, target, copies, fold, np.zeros(N_BLOCKS, int), ["temp_c_lag1200s", "board_temp_c_lag1200s"],
                  [LAG_T, BOARD_LAG], n_shifts=19, span_rows=10)


class _Rows:
    """The two methods of ``ScreenRows`` that ``approximations`` uses, on ready-made block features."""

    def __init__(self, columns: dict):
        self.columns = columns

    def __len__(self) -> int:
        return len(next(iter(self.columns.values())))

    def features(self, specs) -> np.ndarray:
        return np.column_stack([self.columns[feature_name(s)] for s in specs])


def test_collinear_equivalents_are_tied_with_the_measured_column_first():
    # the seeds of 24 where the derived lag scored higher by chance: the case of the issue, where
    # the old rule named `lag of temp_c` with no alternative (or, tied, put it first by its score)
    results = [r for r in map(_collinear, range(24)) if r.score[0] > r.score[1]]
    assert len(results) >= 8
    tied = 0
    for result in results:
        assert result.score[0] - result.score[1] > 0.0  # ordered best first, the derived lag leads
        group = tie_groups(result, np.array([0, 1]))[0]
        tied += group == [1, 0]  # the measured column first, the lag its alternative
    # equivalents are called apart only as often as chance makes a difference exceed 2 standard errors
    assert tied >= len(results) - 1, f"{tied} of {len(results)} equivalents tied"


def test_a_clearly_better_candidate_is_not_tied_with_a_noisier_copy():
    # the lag is the signal itself, the board column carries an error of its own: the test keeps its power
    results = [_collinear(seed, own_noise=(0.0, 0.15)) for seed in range(6)]
    assert all(r.score[0] > r.score[1] for r in results)
    assert all(tie_groups(r, np.array([0, 1])) == [[0], [1]] for r in results)


def test_the_paired_difference_is_the_score_difference_and_its_noise_is_measured():
    result = _collinear(3)
    share = block_contributions(*result.row_sse, result.gain, np.array([0, 1]))
    np.testing.assert_allclose(share.sum(0), result.score, rtol=1e-9)
    noise = paired_noise(*result.row_sse, result.gain, result.span, 0, np.array([1]))
    assert noise[0] > 0 and noise[0] == result.tie_noise(0, np.array([1]))[0]
    # pairing: the difference of two near-copies is far less noisy than either score alone
    alone = np.sqrt(len(np.unique(result.span)) * np.bincount(result.span, weights=share[:, 0]).var(ddof=1))
    assert noise[0] < 0.5 * alone


def test_a_derived_effect_names_the_measured_column_it_approximates():
    seed = next(k for k in range(24) if (lambda r: r.score[0] > r.score[1])(_collinear(k)))  # the lag leads
    basis, target, copies, fold = _arrays(seed)
    result = _collinear(seed)
    rows = _Rows({"temp_c_lag1200s": copies[:, 0], "board_temp_c_lag1200s": copies[:, 1]})
    kept = Choice(LAG_T, 0, result.gain[0], float(result.score[0]), result.rmse_after[0])
    found = approximations(kept, result, np.array([0, 1]), rows, (basis, None))
    assert [a["name"] for a in found] == ["board_temp_c_lag1200s"] and found[0]["corr"] > 0.9
    sentence = approximation_sentence(LAG_T, kept.score, found)
    assert "approximates a measured column: board_temp_c through a 1200 s lag" in sentence
    assert "Look at what `board_temp_c` measures" in sentence
    # a measured effect approximates nothing; a measured column far below the effect is not named
    measured = Choice(BOARD_LAG, 1, result.gain[1], float(result.score[1]), result.rmse_after[1])
    assert approximations(measured, result, np.array([0, 1]), rows, (basis, None)) == []
    assert approximations(kept, result, np.array([0, 1]), rows, (basis, None), near=1e-6) == []
    assert approximation_sentence(LAG_T, kept.score, []) == ""


def test_spans_are_runs_of_one_fold_cut_to_their_length_and_skip_rows_never_held_out():
    fold = np.array([0] * 3 + [1] * 3 + [0] * 2 + [-1] * 2 + [0] * 5)
    recording = np.array([0] * 10 + [1] * 5)
    labels = span_labels(fold, recording, max_rows=3)
    assert labels[:3].tolist() == [0] * 3 and labels[3:6].tolist() == [1] * 3 and labels[6:8].tolist() == [2] * 2
    assert labels[8:10].tolist() == [-1, -1]
    assert labels[10:13].tolist() == [labels[10]] * 3 and labels[13] == labels[14] != labels[12]


def test_measured_columns_come_before_what_is_derived_from_the_temperature():
    order = sorted([LAG_T, {"kind": "time"}, {"kind": "time", "tau_s": 900.0}, BOARD_LAG,
                    {"kind": "hysteresis", "source": "temp_c", "width": 2.0},
                    {"kind": "column", "source": "board_temp_c", "tau_s": 0.0}], key=complexity)
    # no parameter first; then the clock's warm-up (a lagged column's start mimics one), the
    # measured column through a lag, and what is derived from the temperature, its lag last
    assert order == [{"kind": "column", "source": "board_temp_c", "tau_s": 0.0}, {"kind": "time"},
                     {"kind": "time", "tau_s": 900.0}, BOARD_LAG,
                     {"kind": "hysteresis", "source": "temp_c", "width": 2.0}, LAG_T]


@pytest.mark.slow
def test_a_board_die_gradient_names_the_board_column(tmp_path):
    """End to end, 4 h at 0.25 Hz (under a minute on a loaded machine): the gradient's record names
    the measured board column first, or lists it as an alternative and says that the lag kept
    approximates it. (On this record the lag of temp_c scores a hair higher than the column: the
    case of issue 24.)"""
    from test_diagnose import _diagnose

    path = tmp_path / "board.csv"
    write_simulation(simulate("cycle", fs_hz=0.25, duration_s=4 * 3600.0, seed=1, sensor_seed=3,
                              effects={"board": {"tau_s": 600.0}}), path)
    diagnosis = _diagnose(path, tmp_path / "out", n_centers=6, n_shifts=49, alpha=0.02, max_effects=1, refine_top=1,
                          refine_passes=0, train_cfg={"max_epochs": 300})
    assert diagnosis["effects"], "nothing found"
    first = diagnosis["effects"][0]
    sources = [first["source"], *(a["source"] for a in first["alternatives"])]
    assert "board_temp_c" in sources and "temp_c" in sources  # the equivalents come out as equivalents
    if first["source"] != "board_temp_c":
        assert "approximates a measured column" in first["evidence"] and "board_temp_c" in first["evidence"]
    report = (tmp_path / "out" / "report.md").read_text()
    assert "Equally good within the screen's own noise" in report and "`lag` of `temp_c`" in report


class _Noisy:
    """What ``tie_groups`` reads of a screen: two families, the second far behind with a difference
    whose standard error is as large as itself (a warm-up's gain, all in the first spans)."""

    specs = [{"kind": "time", "tau_s": 779.0}, {"kind": "column", "source": "acc_z_g", "tau_s": 2050.0}]
    score = np.array([0.76, 0.39])

    def tie_noise(self, head, rest):
        return np.full(len(rest), 0.37)


def test_a_candidate_far_behind_is_no_equal_however_noisy_the_difference():
    assert tie_groups(_Noisy(), np.array([0, 1])) == [[0], [1]]
    assert tie_groups(_Noisy(), np.array([0, 1]), max_shortfall=1.0) == [[0, 1]]  # the noise alone would tie them


def test_the_screen_counts_the_held_out_blocks_it_scored():
    # a separate validation recording: the training record's rows (fold -1) are fitted on, never scored
    basis, target, copies, _ = _arrays(0)
    fold = np.where(np.arange(N_BLOCKS) < 400, -1, 0)
    result = screen(basis, target, copies, fold, (fold >= 0).astype(int), ["a", "b"], [LAG_T, BOARD_LAG],
                    n_shifts=5, span_rows=10)
    assert result.n_rows == N_BLOCKS - 400


def test_a_refined_effects_p_value_is_said_to_be_its_grid_points():
    """The shift test ran on the grid: a refined lag's sentence named the refined score beside the grid's p."""
    grid = {"kind": "lag", "source": "temp_c", "tau_s": 60.0}
    result = SimpleNamespace(names=[feature_name(grid)], score=np.array([0.5]), p_value=np.array([0.005]),
                             null_max=np.full(199, 0.1), rmse_before=np.full(3, 0.02), n_folds=5, n_rows=900)
    refined = evidence({**grid, "tau_s": 16.0}, 0.6, np.full(3, 0.01), 0, result, ["x"], 0.01, 0.1, 0.4, 0.2)
    assert f"against its grid point {feature_name(grid)} (score 0.5)" in refined and "p = 0.005" in refined
    assert "against it, " in evidence(grid, 0.5, np.full(3, 0.01), 0, result, ["x"], 0.01, 0.1, 0.4, 0.2)
