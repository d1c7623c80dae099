"""The options of a diagnosis and the words of its verdict."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

EXPLAINED, STRUCTURE, UNDETERMINED = "explained", "structure remains", "undetermined"
MIN_DETECTOR_POSES = 30   # below this the flexible detector sees only large structure
MIN_REPEAT_DOF = 8        # repeated-pose scatter with fewer degrees of freedom is not used
EQUIVALENT_P = 0.05       # held-out errors this close are "not significantly different"
SEPARABLE_CORRELATION = 0.99
MIN_TRAINING_RATIO = 3    # measured values per geometric error in a training fold, to select effects


@dataclass(frozen=True)
class DiagnoseOptions:
    """method 'lm' or 'ekf' for every fit; spot_sigma (m) / joint_sigma (rad)
    of the measurements, None when not known; folds of the cross-validation;
    alpha the significance level of every test; max_effects added at most;
    shortlist fitted per round; seed of the fold split and of LM restarts;
    restarts of LM for the geometric fit (estimation.EstimateOptions);
    compensate: keep the learned compensator when it wins held-out; robust:
    leave out the units the geometric estimate's robust rule rejects
    (diagnosis.screening); nested:
    the held-out error of the whole procedure, selection inside the folds
    (folds + 1 selections; the default of the library and the command line); progress:
    called as progress(done, total or None, note) after every fit
    (estimation.lm.ProgressCallback; report.progress.Progress on the console),
    not part of the diagnosis (not kept in its result)."""

    method: str = "lm"
    spot_sigma: float | None = None
    joint_sigma: float | None = None
    folds: int = 5
    alpha: float = 0.01
    max_effects: int = 4
    shortlist: int = 4
    seed: int = 0
    restarts: int = 6
    compensate: bool = True
    nested: bool = True
    robust: bool = True
    progress: Callable[[int, int | None, str], None] | None = field(default=None, compare=False, repr=False)

    def __post_init__(self):
        if self.spot_sigma is not None and not (math.isfinite(self.spot_sigma) and self.spot_sigma > 0):
            raise ValueError(f"spot sigma must be a positive number of metres, got {self.spot_sigma}")
        if self.joint_sigma is not None and not (math.isfinite(self.joint_sigma) and self.joint_sigma >= 0):
            raise ValueError(f"joint sigma must be a non-negative number of radians, got {self.joint_sigma}")
        if self.folds < 2:
            raise ValueError(f"cross-validation needs at least 2 folds, got {self.folds}")

