"""Where the loop's decision rule lived; kept so that code written against it still imports. The rule
is :mod:`torchcal.pipelines.crossval.scores` (``calibrate``'s prior uses it too) and the noise
estimator :mod:`torchcal.measure.noise`."""
from __future__ import annotations

from torchcal.measure.noise import SIGMA_FLOOR, robust_sigma
from torchcal.pipelines.crossval.scores import (HUBER_K, OUTLIER_K, T_ACCEPT, T_EXIT, compare, effective_params,
                                                penalised, rmse_mm, row_scores, selection_threshold)

__all__ = ["T_ACCEPT", "T_EXIT", "HUBER_K", "OUTLIER_K", "SIGMA_FLOOR", "robust_sigma", "row_scores", "compare",
           "penalised", "rmse_mm", "effective_params", "selection_threshold"]
