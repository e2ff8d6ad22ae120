"""``DiagnoseOptions``: how hard the diagnosis looks and how sure it must be, checked before it starts."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping

from gyronet.analysis.diagnose.candidates import CandidateGrid
from gyronet.errors import GyronetError
from gyronet.model.features import feature_name


@dataclass
class DiagnoseOptions:
    """How hard to look and how sure to be (``conf/diagnose.yaml``: ``diagnose``).

    Scores are fractions of a held-out sum of squares of the 60 s residual that an effect removes,
    summed over the axes (one axis halved in variance: 0.5).

    Attributes
    ----------
    alpha
        Family-wise false-positive rate of each round's permutation test, over all candidates.
    min_gain
        Smallest screen score worth a retraining.
    confirm_gain
        Smallest drop of the retrained network's own held-out residual, same scale: an effect
        that passes the screen but not this is a real but negligible association.
    n_shifts
        Circular time shifts in the permutation test (fewer on a short record: all there are).
    max_effects
        Stop after this many effects.
    block_s
        Residual block, s (the contract's 60 s).
    span_s, n_folds
        Cross-validation: spans of ``span_s`` seconds, span i held out in fold i % n_folds.
    ridge
        Ridge penalty of the screen's refits (relative, on standardised regressors); None picks it
        by cross-validation of the model's own regressors, each round.
    refine_top
        Families tried per round (refined, retrained, confirmed), simplest of the best group first.
    tie_z
        Families whose refined screen score is within this many standard errors of the best
        family's (of their paired difference on the same held-out blocks, clustered by span:
        :mod:`.ties`), or within 1 % of it, are equivalent explanations: a measured one and the
        simplest is tried first, the others are listed as its ``alternatives``. 2: a difference
        that chance gives two equivalent explanations 95 % of the time.
    refine_passes
        Times the chosen parameter is searched again with the retrained network (each may retrain).
    seed
        Seeds the shifts.
    candidates
        The candidate grids.
    """

    alpha: float = 0.01
    min_gain: float = 0.1
    confirm_gain: float = 0.2
    n_shifts: int = 199
    max_effects: int = 4
    block_s: float = 60.0
    span_s: float = 600.0
    n_folds: int = 5
    ridge: float | None = None
    refine_top: int = 3
    tie_z: float = 2.0
    refine_passes: int = 2
    seed: int = 0
    candidates: CandidateGrid = field(default_factory=CandidateGrid)

    def __post_init__(self) -> None:
        if isinstance(self.candidates, Mapping):
            self.candidates = CandidateGrid(**self.candidates)
        if self.n_folds < 2:
            raise GyronetError(f"diagnose.n_folds must be at least 2, got {self.n_folds}")
        # (name, ok, what it must be): a bad value would end deep inside the loop, or pass nothing
        for name, ok, must in (("alpha", 0.0 < self.alpha < 1.0, "between 0 and 1"),
                               ("min_gain", self.min_gain >= 0.0, "at least 0"),
                               ("confirm_gain", self.confirm_gain >= 0.0, "at least 0"),
                               ("n_shifts", self.n_shifts >= 1, "at least 1"),
                               ("max_effects", self.max_effects >= 0, "at least 0"),
                               ("block_s", self.block_s > 0.0, "positive"),
                               ("span_s", self.span_s > 0.0, "positive"),
                               ("ridge", self.ridge is None or self.ridge >= 0.0, "null or at least 0"),
                               ("refine_top", self.refine_top >= 1, "at least 1"),
                               ("tie_z", self.tie_z >= 0.0, "at least 0"),
                               ("refine_passes", self.refine_passes >= 0, "at least 0")):
            if not ok:
                raise GyronetError(f"diagnose.{name} must be {must}, got {getattr(self, name)}")
        if not self.candidates.max_tau_fraction > 0.0:
            raise GyronetError("diagnose.candidates.max_tau_fraction must be positive, got "
                               f"{self.candidates.max_tau_fraction}")
        for name in ("lag_tau_s", "hysteresis_width_c", "time_tau_s"):  # a value <= 0 was dropped without a word
            bad = [v for v in getattr(self.candidates, name) if not float(v) > 0.0]
            if bad:
                raise GyronetError(f"diagnose.candidates.{name} must hold positive values, got {bad[0]}")
        check_feature_specs(self.candidates.extra, "diagnose.candidates.extra")


def check_feature_specs(specs: Any, where: str) -> None:
    """Refuse a feature spec list that would fail inside feature building: not specs, or unknown kinds."""
    if not isinstance(specs, (list, tuple)):
        raise GyronetError(f"{where} must be a list of feature specs such as {{kind: temp}}, got {specs!r}")
    for spec in specs:
        try:
            if not isinstance(spec, Mapping):
                raise TypeError("not a mapping")
            feature_name(spec)
        except (KeyError, TypeError, ValueError) as err:
            raise GyronetError(f"{where}: bad feature spec {spec!r} ({err})") from None
