"""Suspect observations of the training rows: listed for a person to check, never dropped (the
Huber loss already keeps them from steering the fit)."""
from __future__ import annotations

import math

import torch

from torchcal.measure.observations import KIND_NAMES
from torchcal.measure.records import Suspect
from torchcal.pipelines.crossval.models import Context, Model, observation_model
from torchcal.pipelines.crossval.scores import OUTLIER_K

__all__ = ["suspect_rows"]


def suspect_rows(ctx: Context, m: Model, sigma: float, say) -> list[Suspect]:
    """Training observations farther from ``m`` than ``OUTLIER_K · √dims · σ̂`` (``sigma``: σ̂, m
    per axis; a 3-D error reaches √3 σ̂ typically, an observation of fewer components
    proportionally less): row, marker, kind and error (mm), largest first."""
    train = ctx.data
    prob = observation_model(ctx, m.params, m.effects, train)
    err = prob.errors(m.params.values[None])[0]
    obs = prob.obs
    bad = torch.nonzero(err > OUTLIER_K * obs.dims.sqrt() * sigma).flatten()
    out = [Suspect(int(obs.rows[i]), train.marker_names[int(obs.data_marker[i])], float(err[i] * 1e3),
                   KIND_NAMES[int(obs.kind[i])]) for i in bad[torch.argsort(err[bad], descending=True)].tolist()]
    if out:
        say(f"{len(out)} suspect observation(s) beyond {OUTLIER_K:g}·√3·σ̂ = "
            f"{1e3 * OUTLIER_K * math.sqrt(3) * sigma:.3f} mm (down-weighted by the Huber loss, kept): rows "
            + ", ".join(str(s.row) for s in out[:10]) + (" …" if len(out) > 10 else ""))
    return out
