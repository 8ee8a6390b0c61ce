"""What the loop returns: every stage's model and errors, the decisions and why, the evidence."""
from __future__ import annotations

from dataclasses import dataclass, field

from torchcal.deploy.model import CalibratedModel
from torchcal.measure.records import Stage, StageErrors, Suspect
from torchcal.measure.setup import Setup
from torchcal.measure.trust import FOREIGN, stage_problems
from torchcal.params import ParamSet
from torchcal.pipelines.loop.records import Candidate, Finding
from torchcal.pipelines.crossval.scores import OUTLIER_K, T_ACCEPT
from torchcal.pipelines.precision import PLAUSIBLE, implausible_reason, implausible_values

__all__ = ["LoopResult"]


@dataclass
class LoopResult:
    """Outcome of :func:`run_loop`, a record: :func:`torchcal.report.write_report` writes its
    report files, :func:`torchcal.report.report_json` gives ``report.json``'s content.

    Attributes:
        params: geometry + accepted effects, fitted on all training rows.
        effects: accepted effect objects (fitted ``theta``); ``elm``: the residual ELM or None.
        stages: per stage, error statistics (mm) on the training and held-out rows.
        accepted / candidates: what was added, and every candidate examined, with the numbers
            that decided (cross-validated) and the held-out gain measured afterwards.
        geometric: the geometric sets and priors tried and the one chosen; ``again``: each time the
            geometry was judged again after an effect (:func:`~torchcal.pipelines.loop.geometry.geometry_again`).
        noise_sigma_mm: robust per-axis noise estimate of the final model (mm);
            ``huber_mm``: the Huber threshold of the last round (mm).
        suspects: training observations beyond ``OUTLIER_K σ̂``: row, marker, error (mm).
        flags: warnings about candidates (a covariate outside its training range on the test rows).
    """

    robot: object
    params: ParamSet
    effects: list
    elm: object | None
    stages: list[Stage]
    accepted: list[Finding]
    candidates: list[Candidate]
    geometric: dict
    n_train: int
    n_test: int
    noise_floor_mm: float | None
    timings: dict = field(default_factory=dict)
    errors: dict[str, StageErrors] = field(default_factory=dict)  # stage name -> its errors (m)
    evidence: dict = field(default_factory=dict)  # effect -> arrays for plots
    elm_covariates: list = field(default_factory=list)
    geometric_fits: dict = field(default_factory=dict)  # set name -> ParamSet fitted on all training rows
    noise_sigma_mm: float | None = None
    huber_mm: float | None = None
    suspects: list[Suspect] = field(default_factory=list)
    flags: list = field(default_factory=list)
    prior_mm: float | None = None
    parameters: list = field(default_factory=list)     # [{name, value, unit, std_error}] of the final model
    observability: dict = field(default_factory=dict)  # condition number, O1-O4 of its identified set
    setup: Setup | None = None  # planes and fixed points the rows measured against (None: positions only)
    heldout: object = None  # HeldOutCheck: another session, a moved instrument, an effect extrapolating
    leftover: object = None     # Leftover: the final model against the noise floor, what the residual follows
    removed: list = field(default_factory=list)  # modes accepted once, then explained by later findings
    plausible: dict | None = None  # the largest plausible joint error per unit the run judged with
    noise_floor_source: str | None = None  # where noise_floor_mm comes from, in words
    breaks_placed: list = field(default_factory=list)  # breaks in time or row order placed again (loop.breaks)

    def __repr__(self) -> str:
        last = self.stages[-1]
        te = f", held-out mean {last.test.mean:.4f} mm" if last.test is not None else ""
        return (f"LoopResult({self.robot.name}: {' → '.join(s.name for s in self.stages)}; training mean "
                f"{last.train.mean:.4f} mm{te}; {len(self.suspects)} suspect observation(s))")

    def problems(self) -> list[str]:
        """Reasons not to trust this model, in words: a final model worse than the nominal one on
        its own training rows, held-out rows that do not belong to this robot, or joints moved or
        turned by more than a plausible error. Empty when none."""
        out = stage_problems(self.stages)
        h = self.heldout
        if h is not None:
            if h.reregister and h.explained_by_reregistration:  # the instrument moved; the robot's model holds
                out = [p for p in out if not p.startswith(FOREIGN)]
            elif h.causes():
                hint = "; registering the instrument frame anew on them explains them: rerun with reregister=True " \
                    "(--reregister)" if h.explained_by_reregistration else ""
                out = [p + " Found: " + "; ".join(h.causes()) + hint if p.startswith(FOREIGN) else p for p in out]
        bad = implausible_values(self.params, self.robot, self.plausible)
        if bad:
            out.append(implausible_reason(bad, dict(zip(self.params.names, self.params.units)),
                                          self.plausible or PLAUSIBLE))
        return out

    def heldout_suspects(self) -> list[Suspect]:
        """Held-out observations farther from the final model than the training rows' suspect bound
        (``OUTLIER_K · √dims · σ̂``): row (0-based, held-out file order), marker, error (mm), largest
        first. Empty without held-out rows or a noise estimate."""
        if not self.errors or self.noise_sigma_mm is None:
            return []
        d = self.errors[self.stages[-1].name].test_details
        if d is None or d.row is None or not d.e.numel():
            return []
        bound = OUTLIER_K * d.dims.double().sqrt() * self.noise_sigma_mm * 1e-3
        bad = (d.e > bound).nonzero().flatten().tolist()
        out = [Suspect(int(d.row[i]), self.robot.marker_names[int(d.marker[i])], float(d.e[i]) * 1e3) for i in bad]
        return sorted(out, key=lambda s: -s.error_mm)

    @property
    def rule(self) -> str:
        """The acceptance rule every decision of the run followed, in words."""
        return (f"accept when the paired t statistic of the cross-validated per-row Huber-score improvement "
                f"exceeds {T_ACCEPT} and mean*(1+2k/n_obs) decreases (k: effective parameters); a family's modes "
                f"are added one by one under the same rule with the threshold raised for the number of modes tried")

    def model(self, *, force: bool = False, meta: dict | None = None):
        """A deployable :class:`~torchcal.deploy.model.CalibratedModel` carrying ``meta`` (the
        command line stores the run's report and provenance there); refused (``ValueError``) when
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
                               meta=dict(meta or {}))
