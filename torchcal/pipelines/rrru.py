"""The 3-RRRU calibration of seed 004: LM and the real-coded GA on
:class:`~torchcal.problems.rrru.RRRUCalibration` for one set of tracker readings, and the
identifiability, observability and noise amplification of data sets. The study that simulates the
seed's lines and spiral and compares the calibrations is :func:`torchcal.studies.rrru.study`.
Lengths in m (mm where a name says so), angles in rad."""
from __future__ import annotations

import math
import time

import torch
from torch import Tensor

from torchcal.kinematics.rrru import RRRU
from torchcal.kinematics.rrru_params import PARAM_NAMES
from torchcal.optim import get_solver
from torchcal.problems.identifiability import jacobian_observability
from torchcal.problems.rrru import DecorrelatedProblem, RRRUCalibration, identifiability, prediction_std
from torchcal.problems.uncertainty import covariance

__all__ = ["FREE", "calibrate_rrru", "data_observability", "MM"]

MM = 1e-3
FREE = [n for n in PARAM_NAMES if n != "dr"]      # identifiable subset (see identifiability)


def calibrate_rrru(model: RRRU, theta: Tensor, meas: Tensor, targets: Tensor, *, seed: int = 0, ga_iter: int = 3000,
                   raw_ga: bool = False) -> dict:
    """LM and the seed's GA (in decorrelated coordinates; also in raw ones with ``raw_ga``) on one data
    set: commanded angles ``theta (N, 3)`` rad, tracker readings ``meas (N, 3)`` m at ``targets (N, 3)``
    m. Returns the problem, the fits (free values, m / rad), LM's covariance and the RMS residuals (m)."""
    prob = RRRUCalibration(model, theta, meas, free=FREE, p0=targets)
    t0 = time.perf_counter()
    lm = get_solver("lm").minimize(prob)
    t_lm = time.perf_counter() - t0
    J, r = lm.extra["jacobian"], lm.extra["residuals"]
    cov = covariance(J, r)
    dec = DecorrelatedProblem(prob)
    t0 = time.perf_counter()
    ga = get_solver("ga", seed=seed, max_iter=ga_iter, mutation_scale=0.05).minimize(dec)
    t_ga = time.perf_counter() - t0
    x_ga = dec.to_x(ga.x)
    out = dict(problem=prob, lm=lm, x_lm=lm.x, x_ga=x_ga, cov=cov, t_lm=t_lm, t_ga=t_ga,
               rms_lm=float(r.pow(2).mean().sqrt()),
               rms_ga=float(prob.residuals(x_ga[None]).pow(2).mean().sqrt()))
    if raw_ga:
        t0 = time.perf_counter()
        gr = get_solver("ga", seed=seed, max_iter=ga_iter, mutation_scale=0.05).minimize(prob)
        out.update(x_ga_raw=gr.x, t_ga_raw=time.perf_counter() - t0,
                   rms_ga_raw=float(prob.residuals(gr.x[None]).pow(2).mean().sqrt()))
    return out


def data_observability(model: RRRU, params: Tensor, data: dict) -> tuple[dict, dict, dict]:
    """Identifiability, observability and tracker-noise amplification of calibration data sets at
    ``params (14,)`` (m / rad). ``data``: ``{"lines": …, "spiral": …}``, each ``(theta (N, 3) rad,
    meas, targets (N, 3) m)``. Returns ``ident`` (per set), ``obs`` (O1… and condition per set,
    columns scaled by their common RMS) and ``amp``: prediction std / σ of each set's calibration
    at the other set's poses (max, mean, and where, mm)."""
    free = [PARAM_NAMES.index(n) for n in FREE]
    ident = {k: identifiability(model, th, params, p0=T) for k, (th, _, T) in data.items()}
    Jfree = {k: model.param_jacobian(th, params, p0=T)[..., free] for k, (th, _, T) in data.items()}
    allJ = torch.cat([J.reshape(-1, len(FREE)) for J in Jfree.values()])
    common = torch.linalg.vector_norm(allJ, dim=0) / math.sqrt(allJ.shape[0])
    obs = {k: jacobian_observability(J.reshape(-1, len(FREE)), common) for k, J in Jfree.items()}
    cal_on = lambda a, b: prediction_std(Jfree[a].reshape(-1, len(FREE)), Jfree[b])  # noqa: E731
    amp = {"line_cal_on_lines": cal_on("lines", "lines"), "line_cal_on_spiral": cal_on("lines", "spiral"),
           "spiral_cal_on_spiral": cal_on("spiral", "spiral"), "spiral_cal_on_lines": cal_on("spiral", "lines")}
    poses = {k: T for k, (_, _, T) in data.items()}
    amp = {k: dict(max=float(v.max()), mean=float(v.mean()),
                   at_mm=(poses[k.split("_on_")[1]][int(v.argmax())] / MM).tolist()) for k, v in amp.items()}
    return ident, obs, amp
