"""What the loop returns: every stage's model and errors, the decisions and why, the evidence."""
from __future__ import annotations

from dataclasses import dataclass, field

from torchcal.deploy.model import CalibratedModel
from torchcal.measure.setup import Setup
from torchcal.params import ParamSet
from torchcal.pipelines.loop.selection import T_ACCEPT
from torchcal.pipelines.fitting import PLAUSIBLE, implausible_reason, implausible_values
from torchcal.report.calibration import stage_problems

__all__ = ["LoopResult"]


@dataclass
class LoopResult:
    """Outcome of :func:`run_loop`; :meth:`report` has the JSON shape of ``report.json``.

    Attributes:
        params: geometry + accepted effects, fitted on all training rows.
        effects: accepted effect objects (fitted ``theta``); ``elm``: the residual ELM or None.
        stages: per stage, error statistics (mm) on the training and held-out rows.
        accepted / candidates: what was added, and every candidate examined, with the numbers
            that decided (cross-validated) and the held-out gain measured afterwards.
        geometric: the geometric sets and priors tried and the one chosen.
        noise_sigma_mm: robust per-axis noise estimate of the final model (mm);
            ``huber_mm``: the Huber threshold of the last round (mm).
        suspects: training observations beyond ``OUTLIER_K σ̂``: row, marker, error (mm).
        flags: warnings about candidates (a covariate outside its training range on the test rows).
    """

    robot: object
    params: ParamSet
    effects: list
    elm: object | None
    stages: list[dict]
    accepted: list[dict]
    candidates: list[dict]
    geometric: dict
    n_train: int
    n_test: int
    noise_floor_mm: float | None
    timings: dict = field(default_factory=dict)
    errors: dict = field(default_factory=dict)   # stage -> {"train": Tensor, "test": Tensor} (m)
    evidence: dict = field(default_factory=dict)  # effect -> arrays for plots
    elm_covariates: list = field(default_factory=list)
    geometric_fits: dict = field(default_factory=dict)  # set name -> ParamSet fitted on all training rows
    noise_sigma_mm: float | None = None
    huber_mm: float | None = None
    suspects: list = field(default_factory=list)
    flags: list = field(default_factory=list)
    prior_mm: float | None = None
    parameters: list = field(default_factory=list)     # [{name, value, unit, std_error}] of the final model
    observability: dict = field(default_factory=dict)  # condition number, O1-O4 of its identified set
    setup: Setup | None = None  # planes and fixed points the rows measured against (None: positions only)
    leftover: object = None     # Leftover: the final model against the noise floor, what the residual follows
    removed: list = field(default_factory=list)  # modes accepted once, then explained by later findings
    plausible: dict | None = None  # the largest plausible joint error per unit the run judged with
    noise_floor_source: str | None = None  # where noise_floor_mm comes from, in words

    def __repr__(self) -> str:
        last = self.stages[-1]
        te = f", held-out mean {last['test']['mean_mm']:.4f} mm" if last.get("test") else ""
        return (f"LoopResult({self.robot.name}: {' → '.join(s['name'] for s in self.stages)}; training mean "
                f"{last['train']['mean_mm']:.4f} mm{te}; {len(self.suspects)} suspect observation(s))")

    def problems(self) -> list[str]:
        """Reasons not to trust this model, in words: a final model worse than the nominal one on
        its own training rows, held-out rows that do not belong to this robot, or joints moved or
        turned by more than a plausible error. Empty when none."""
        out = stage_problems(self.stages)
        bad = implausible_values(self.params, self.robot, self.plausible)
        if bad:
            out.append(implausible_reason(bad, dict(zip(self.params.names, self.params.units)),
                                          self.plausible or PLAUSIBLE))
        return out

    def report(self) -> dict:
        return {"robot": self.robot.name, "n_train": self.n_train, "n_test": self.n_test,
                "noise_floor_mm": self.noise_floor_mm, "noise_floor_source": self.noise_floor_source,
                "noise_sigma_mm": self.noise_sigma_mm,
                "huber_threshold_mm": self.huber_mm, "stages": self.stages, "effects": self.accepted,
                "candidates": self.candidates, "geometric_set": self.geometric, "prior_mm": self.prior_mm,
                "suspect_rows": self.suspects, "flags": self.flags, "parameters": self.parameters,
                "observability": self.observability, "problems": self.problems(),
                "setup": None if self.setup is None else self.setup.describe(
                    self.params.values[self.robot.n_params:self.robot.n_params + self.setup.n_params]),
                "rule": f"accept when the paired t statistic of the cross-validated per-row Huber-score "
                        f"improvement exceeds {T_ACCEPT} and mean*(1+2k/n_obs) decreases (k: effective "
                        f"parameters); a family's modes are added one by one under the same rule with the "
                        f"threshold raised for the number of modes tried",
                "residual_elm": self.elm is not None, "timings_s": self.timings,
                "leftover": None if self.leftover is None else self.leftover.report(), "removed_modes": self.removed}

    def model(self, *, force: bool = False):
        """A deployable :class:`~torchcal.deploy.model.CalibratedModel`; refused (``ValueError``) when
        :meth:`problems` says the model cannot be trusted, unless ``force``."""

        if self.problems() and not force:
            raise ValueError("this calibration is not fit to deploy: " + "; ".join(self.problems()))
        geo = self.robot.params(self.params.values[: self.robot.n_params])
        geo.free = self.params.free[: self.robot.n_params].clone()
        residual = self.elm
        if residual is not None and residual.n_outputs_ != 3:
            raise ValueError("the residual ELM predicts several markers at once; a deployable model holds a "
                             "residual for one marker: run the loop with that marker only")
        return CalibratedModel(self.robot, geo, effects=list(self.effects), residual=residual,
                               covariates=self.elm_covariates if residual is not None else None,
                               meta={"report": self.report()})
