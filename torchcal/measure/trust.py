"""Whether a calibrated model can be trusted, judged from its stages' error statistics alone:
the same judgement for calibrate, the loop and the fleet, made before anything is saved."""
from __future__ import annotations

from torchcal.measure.records import Stage

__all__ = ["stage_problems", "FOREIGN_RATIO", "FOREIGN"]

# held-out rows this many times worse than the training rows do not come from the same robot
FOREIGN_RATIO = 20.0
FOREIGN = "the held-out rows do not belong to this robot's model"


def stage_problems(stages: list[Stage]) -> list[str]:
    """Reasons not to trust a calibration, in words, from its stage statistics (first: nominal,
    last: final): the final model worse than the nominal one on its own training rows, or
    held-out rows that fit far worse than the training rows. Empty when none."""
    out = []
    nom, fin = stages[0].train, stages[-1].train
    if fin.mean > nom.mean:
        out.append(f"the calibrated model ({fin.mean:.4f} mm) is worse than the nominal one "
                   f"({nom.mean:.4f} mm) on its own training rows: the fit failed (check the joint "
                   "order and units of the data, the declared markers, and the method's settings)")
    # medians: one glitch among the held-out rows is a gross error, not another robot
    test = stages[-1].test
    if test is not None and test.n:
        tr, te = fin.median, test.median
        if te > FOREIGN_RATIO * max(tr, 1e-9):
            out.append(f"{FOREIGN}: their median error ({te:.4g} mm) is "
                       f"{te / max(tr, 1e-9):.0f}× the training rows' ({tr:.4g} mm); are they from another robot, "
                       "another set-up (the instrument moved), or another marker?")
    return out
