"""Where the loop's fitting lived before it was split by what each part does; kept so that code
written against it still imports. New code imports from the modules themselves:

* :mod:`torchcal.pipelines.crossval.models`: :class:`Context`, :class:`Model`, folds, the measurement
  model of a candidate (``effect_problem``, ``observation_model``, ``observation_errors``) and its noise;
* :mod:`torchcal.pipelines.crossval.priors`: prior weights and scales;
* :mod:`torchcal.pipelines.crossval.evaluate`: a candidate fitted and cross-validated;
* :mod:`torchcal.pipelines.loop.parts`: a model's parameters cut by effect;
* :func:`torchcal.problems.template.geometric_start`: the loop's start, from the one start template.
"""
from __future__ import annotations

from torchcal.pipelines.crossval.evaluate import cv_mean_mm, evaluate, evaluate_prior, fit_params, rescore
from torchcal.pipelines.crossval.models import (Context, Model, duplicate_groups, effect_problem, fit_noise, folds_of,
                                                noise_sigma, noise_sigma_of, observation_errors, observation_model,
                                                orientation_count)
from torchcal.pipelines.crossval.priors import PRIOR_SCALES_MM, plausible_scale, prior_weights
from torchcal.pipelines.loop.parts import assemble, split_params
from torchcal.problems.template import geometric_start

__all__ = ["Context", "Model", "geometric_start", "observation_model", "observation_errors", "prior_weights",
           "evaluate", "evaluate_prior", "plausible_scale", "fit_params", "fit_noise", "cv_mean_mm", "folds_of",
           "duplicate_groups", "split_params", "assemble", "PRIOR_SCALES_MM", "effect_problem", "rescore",
           "noise_sigma", "noise_sigma_of", "orientation_count"]
