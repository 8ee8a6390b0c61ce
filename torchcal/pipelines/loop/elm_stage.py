"""The loop's last model stage: a residual ELM on what the physical model leaves, kept only when
it passes the same cross-validated rule as an effect."""
from __future__ import annotations

from torchcal.elm import ELM
from torchcal.pipelines.crossval.models import Context, Model
from torchcal.pipelines.loop.records import Candidate
from torchcal.pipelines.crossval.scores import compare, rmse_mm
from torchcal.pipelines.loop.stages import StageBook, elm_inputs, residual_matrix
from torchcal.pipelines.loop.steps import clipped, elm_cv

__all__ = ["elm_stage"]


def elm_stage(ctx: Context, current: Model, book: StageBook, hidden: int | None, seed: int,
              say) -> tuple[ELM | None, Candidate | None]:
    """The residual ELM (``hidden`` units; default N/4, 8–64) judged against ``current``: its
    candidate line, and the ELM fitted on all training rows when it passes (its stage added to
    ``book``). Not tried on rows holding partial positions, plane contacts or distances (it
    learns 3-D position errors) nor on fewer than 20 rows."""
    train = ctx.data
    if not (train.positions_only and (book.test is None or book.test.positions_only)):
        say("residual ELM not tried: it learns 3-D position errors, and these rows hold partial positions, plane "
            "contacts or distances")
        return None, None
    if len(train) < 20:
        return None, None
    n_obs = ctx.n_obs
    H = hidden or max(8, min(64, len(train) // 4))
    sc_elm, sq_elm = elm_cv(ctx, current, H, seed)
    k_elm = H * 3 * len(train.marker_names)
    t, pen_ok, ok = compare(current.scores, sc_elm, current.k, current.k + k_elm, n_obs)
    gain = current.cv_rmse_mm(n_obs) - rmse_mm(sq_elm, n_obs)
    line = Candidate("residual_elm", "residual_elm", n_params=k_elm, cv_rmse_mm=rmse_mm(sq_elm, n_obs),
                     cv_gain_mm=gain, t=t, penalised_ok=pen_ok, accepted=ok)
    say(f"residual ELM ({H} hidden): CV {rmse_mm(sq_elm, n_obs):.4f} mm  gain {gain:+.4f} mm  t = {t:.1f}"
        f"  {'kept' if ok else 'not kept'}")
    if not ok:
        return None, line
    r = clipped(residual_matrix(ctx.robot, current.params, current.effects, train, ctx.setup), ctx.c)
    model = ELM(n_hidden=H, ridge=1e-3, seed=seed).fit(elm_inputs(train), r)
    book.add("+residual_elm", current.k + k_elm, current.params, current.effects, model)
    return model, line
