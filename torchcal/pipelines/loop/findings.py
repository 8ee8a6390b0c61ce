"""What the loop states about each accepted effect (:class:`~torchcal.pipelines.loop.records.Finding`):
its stage, the modes that survived the later rounds, its gains, its evidence and its values."""
from __future__ import annotations

from torchcal.measure.data import Measurements
from torchcal.pipelines.loop.breaks import renamed
from torchcal.pipelines.loop.diagnosis import Step
from torchcal.pipelines.loop.evidence import evidence_for
from torchcal.pipelines.crossval.models import Model
from torchcal.pipelines.loop.parts import split_params
from torchcal.pipelines.loop.records import Finding
from torchcal.pipelines.loop.stages import StageBook

__all__ = ["state_findings"]


def state_findings(book: StageBook, steps: list[Step], final: Model, train: Measurements,
                   n_obs: float, moves: list[tuple[str, str]] = ()) -> tuple[list[Finding], dict, list[dict]]:
    """One stage per accepted step in ``book`` and, for each effect the ``final`` model keeps,
    its :class:`Finding` (its modes named as the final model names them: ``moves``, every break
    placed again, in order); also the evidence plots per stage and the modes pruned on the way."""
    findings, evidence, removed = [], {}, []
    kept_modes = _final_modes(final)
    seen: set[str] = set()
    for step in steps:
        name, m, line = step.name, step.model, step.trial.line
        for e, p in zip(m.effects, split_params(m.params, book.robot, m.effects)[1]):
            e.theta = p.values.clone()
        label = f"+{name}" if name not in seen else f"+{name} ({', '.join(line.added_modes)})"
        seen.add(name)
        prev = book.stages[-1]
        s = book.add(label, m.k, m.params, m.effects, cv=m.cv_rmse_mm(n_obs))
        gain = None if s.test is None or prev.test is None else prev.test.mean - s.test.mean
        removed += step.trial.pruned
        if name not in kept_modes:  # a later round's findings explained it away
            continue
        ev_text, evidence[label.lstrip("+")] = evidence_for(book.robot, m, train, book.setup)
        findings.append(_finding(step, label, kept_modes[name], gain, ev_text, list(moves[step.moves_at:])))
    return findings, evidence, removed


def _final_modes(final: Model) -> dict[str, set[str]]:
    """Each effect of the final model -> its modes and its parts at breaks; an extension carries the
    modes of what it extends: those stay found."""
    out = {e.name: {lab for lab, _ in [*e.modes(), *e.break_parts()]} for e in final.effects}
    for e in final.effects:
        for name in e.supersedes:
            out.setdefault(name, set()).update(out[e.name])
    return out


def _finding(step: Step, label: str, final: set[str], test_gain: float | None, evidence: str,
             moves: list[tuple[str, str]]) -> Finding:
    """The step's finding, its modes renamed by the breaks ``moves`` placed again after it."""
    m, line = step.model, step.trial.line
    eff = m.effects[-1]
    kept = m.params.free[len(m.params) - eff.n_params:].clone()
    now = lambda lab: renamed(lab, moves)  # noqa: E731
    for lab, idx in eff.modes():
        if now(lab) not in final and eff.selectable:
            kept[[i for i in idx if i not in set(eff.shared())]] = False
    for lab, idx in eff.break_parts():  # a load change a later finding explained is not stated as found
        if now(lab) not in final:
            kept[idx] = False
    found = eff.describe(free=kept) + [f"{a} cannot be told from {', '.join(b)} by these data: one finding, either "
                                       "of them" for a, b in line.aliases.items()]
    if eff.ridge is not None:
        found.append(f"all {len(eff.modes())} modes kept under a Gaussian prior of {eff.ridge_mm:.3g} mm RMS at the "
                     "markers per mode (its scale chosen by CV): together they explain what no single mode shows "
                     "clearly")
    own = eff.name + "."
    return Finding(
        name=step.name, stage=label, joints=list(eff.joints), n_params=eff.n_params,
        modes=[now(lab) for lab, _ in eff.modes() if now(lab) in final or not eff.selectable],
        added_modes=[now(lab) for lab in line.added_modes if now(lab) in final], extends=line.extends,
        cv_gain_mm=line.cv_gain_mm, test_gain_mm=test_gain, evidence=evidence, found=found,
        soft_prior_mm=eff.ridge_mm, aliases=line.aliases,
        params={n: float(v) for n, v, f in zip(m.params.names, m.params.values.tolist(), m.params.free.tolist())
                if n.startswith(own) and f},
        standard_errors={n: v for n, v in m.info.get("se", {}).items() if n.startswith(own)},
        units=dict(zip(eff.param_names, eff.param_units)))
