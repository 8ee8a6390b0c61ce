"""Selection that can change its mind across rounds: a mode an earlier round accepted leaves when
what was accepted since explains it.

A cyclic error taken in round 1 may only have mimicked a joint's twist under gravity; once the
twist is in, the cyclic mode adds nothing of its own. After each accepted round, every mode of
every accepted family is judged again, as if it were being added last: around the current model
the measurement model is linear, so the model without the mode is the current one with the mode's
contribution taken back, and :class:`~torchcal.pipelines.loop.linear_cv.LinearCV` scores adding it
to that model. A mode that no longer passes the rule at the exit threshold (``t > T_EXIT`` and a
lower penalised error) is removed, the weakest first, and the model refitted without it; it is
not tried again in that run.

A load changed at a break in time or the row order (a payload swapped with nothing logged, placed
where the residual showed a change) is judged so too, its four mass moments as one mode
(:meth:`~torchcal.effects.session.SessionFindings.break_parts`): found before the tracker's knock at
nearly the same row, it stood in for the knock, and once the knock's frame step is in it carries
nothing of its own.

A mode whose every parameter the rank judgement dropped (held at zero: the later findings span
all it held, a thermal growth driven by a tool's number once the tool per number is in) carries
nothing; it leaves first, without a judgement. A family kept softly (every mode under one Gaussian
prior) is judged whole: refitted without it, the model must be worse by the exit rule, or the
family leaves.

Each removal is judged with the others in, so modes that stand in for one another can each look
redundant while together they carry what the data need: removed one after another, the model
falls back to where it was rounds ago, and the next rounds find the same modes again. So the
removals are also judged together: a removal after which the model as it was before any of them
passes the exit rule against the pruned one does not happen, and pruning stops there.
"""
from __future__ import annotations

from torchcal.effects import effect_params
from torchcal.params import ParamSet
from torchcal.pipelines.crossval.models import Context, Model, effect_problem
from torchcal.pipelines.crossval.evaluate import evaluate
from torchcal.pipelines.crossval.priors import prior_weights
from torchcal.pipelines.loop.parts import split_params
from torchcal.pipelines.loop.linear_cv import LinearCV
from torchcal.pipelines.crossval.scores import T_EXIT, compare

__all__ = ["prune", "weakest_mode", "without_mode", "idle_modes"]


def _judged(e) -> list[tuple[str, list[int]]]:
    """``(label, parameter indices)`` of what of effect ``e`` is judged again: the modes of a family
    selected mode by mode (their own parameters; a family kept softly is held by its prior, not judged
    mode by mode), and what it holds at a break beyond its modes (a load changed there)."""
    out = []
    if e.selectable and e.ridge is None:
        shared = set(e.shared())
        out += [(label, [i for i in idx if i not in shared]) for label, idx in e.modes()]
    return out + e.break_parts()


def _mode_columns(ctx: Context, m: Model) -> list[tuple[int, str, list[int]]]:
    """``(effect index, label, columns among the free parameters)`` of everything judged again
    (:func:`_judged`; what has no free parameter left out)."""
    col = {int(i): c for c, i in enumerate(m.params.free_index.tolist())}
    out, o = [], ctx.n_geo
    for k, e in enumerate(m.effects):
        for label, idx in _judged(e):
            cols = [col[o + i] for i in idx if (o + i) in col]
            if cols:
                out.append((k, label, cols))
        o += e.n_params
    return out


def idle_modes(ctx: Context, m: Model, protect=frozenset()) -> list[tuple[int, str]]:
    """``(effect index, label)`` of what is judged again (:func:`_judged`) with no free parameter left
    and every value zero: the rank judgement dropped it, and it adds nothing to the model."""
    free, vals = m.params.free.tolist(), m.params.values.tolist()
    out, o = [], ctx.n_geo
    for k, e in enumerate(m.effects):
        own = [(label, [o + i for i in idx]) for label, idx in _judged(e)]
        out += [(k, label) for label, idx in own if idx and (e.name, label) not in protect
                and not any(free[i] for i in idx) and not any(vals[i] for i in idx)]
        o += e.n_params
    return out


def weakest_mode(ctx: Context, m: Model, protect=frozenset()) -> tuple[int, str, float] | None:
    """The accepted mode with the smallest t that no longer passes the rule (at :data:`T_EXIT`) when
    added last to the current model without it: ``(effect index, label, t)``; None when every mode
    passes.
    Modes in ``protect`` (``(effect name, label)``) are not judged."""
    modes = [(k, lab, c) for k, lab, c in _mode_columns(ctx, m) if (m.effects[k].name, lab) not in protect]
    if len(modes) == 0:
        return None
    prior = prior_weights(ctx.robot, m.params, m.prior_mm, ctx.sigma, m.effects)
    prob = effect_problem(ctx, m.params, m.effects, ctx.data, prior)
    x = prob.x0
    r = prob.residual_vectors(m.params.values[None])[0]
    J = prob.data_jacobian(x)
    w = prob.observation_weights(x)
    pf = None if prior is None else prior[m.params.free_index]
    worst = None
    for k, label, cols in modes:
        base = [c for c in range(J.shape[1]) if c not in set(cols)]
        # the model without the mode: its fitted contribution taken back, to first order
        r0 = r - (J[:, cols] @ x[cols]).reshape(-1, 3)
        lcv = LinearCV(r0, w, J[:, base], x[base], None if pf is None else pf[base], [J[:, cols]], prob.rows,
                       len(ctx.data), ctx.folds, ctx.c)
        t, pen_ok, _ = compare(lcv.scores([]), lcv.scores([0]), lcv.k_eff([]), lcv.k_eff([0]), ctx.n_obs)
        if not (t > T_EXIT and pen_ok) and (worst is None or t < worst[2]):
            worst = (k, label, t)
    return worst


def without_mode(ctx: Context, m: Model, k: int, label: str | None) -> Model:
    """``m`` refitted without the mode ``label`` of its ``k``-th effect (``None``: every mode; the
    effect gone when it was its last mode), or without its part at a break of that label
    (:meth:`~torchcal.effects.session.SessionFindings.break_parts`); every other value starts where
    ``m`` has it."""
    eff = m.effects[k]
    part = label is not None and label in dict(eff.break_parts())
    keep = [lab for lab, _ in eff.modes() if label is not None and lab != label]
    geo, parts = split_params(m.params, ctx.robot, m.effects)
    effects, kept_parts = list(m.effects), list(parts)
    if keep or part:
        new = eff.without_part(label) if part else eff.with_modes(keep)
        old = dict(zip(eff.param_names, parts[k].values.tolist()))
        new.theta = new.theta.new_tensor([old.get(n, 0.0) for n in new.param_names])
        effects[k], kept_parts[k] = new, effect_params([new])
    else:
        del effects[k], kept_parts[k]
    params = ParamSet.concat(geo, *kept_parts)
    params.free[: ctx.n_geo] = m.info["candidates"]
    return evaluate(ctx, m.label, params, effects, m.prior_mm, info=m.info)


def prune(ctx: Context, m: Model, protect=frozenset(), say=None) -> tuple[Model, list[dict]]:
    """``m`` without the accepted modes that later ones made redundant (module docstring), refitted;
    and what left, with its t when it left (None: an idle mode, :func:`idle_modes`; a family kept softly
    leaves whole, its modes listed under ``"modes"``). The modes just
    accepted (``protect``: ``(effect name, label)``) passed the rule against everything before them
    and are not judged again here."""
    gone, before = [], m
    while idle := idle_modes(ctx, m, protect):
        k, label = idle[0]
        gone.append({"effect": m.effects[k].name, "mode": label, "t": None})  # no judgement: nothing to judge
        if say is not None:
            say(f"{m.effects[k].name}: mode {label} leaves (the later findings hold all it held: its parameters "
                "were dropped for identifiability)")
        m = before = without_mode(ctx, m, k, label)
    k = 0
    while k < len(m.effects):  # families kept softly, each judged whole
        e = m.effects[k]
        if not (e.selectable and e.ridge is not None) or any((e.name, lab) in protect for lab, _ in e.modes()):
            k += 1
            continue
        pruned = without_mode(ctx, m, k, None)
        t, pen_ok, _ = compare(pruned.scores, m.scores, pruned.k, m.k, ctx.n_obs)
        if t > T_EXIT and pen_ok:
            k += 1
            continue
        gone.append({"effect": e.name, "mode": "all modes (kept softly)", "t": t, "modes": [lab for lab, _ in e.modes()]})
        if say is not None:
            say(f"{e.name}: its modes, kept softly, leave (t = {t:.1f} once the later findings are in)")
        m = before = pruned  # effect k is gone: the next one takes its place
    for _ in range(sum(len(e.modes()) for e in m.effects)):
        weak = weakest_mode(ctx, m, protect)
        if weak is None:
            break
        k, label, t = weak
        name = m.effects[k].name
        pruned = without_mode(ctx, m, k, label)
        t_all, pen_ok, _ = compare(pruned.scores, before.scores, pruned.k, before.k, ctx.n_obs)
        if t_all > T_EXIT and pen_ok:  # with the modes gone before it, this one took what the data need
            if say is not None:
                say(f"{name}: mode {label} stays (t = {t:.1f} alone, but without it and the {len(gone)} "
                    f"gone before it the model is worse: t = {t_all:.1f})")
            break
        gone.append({"effect": name, "mode": label, "t": t})
        if say is not None:
            say(f"{name}: mode {label} leaves (t = {t:.1f} once the later findings are in)")
        m = pruned
    return m, gone
