"""What an effect takes from, and gives to, the session's other findings: where it finds the session
to change (a step in time or the row order: a set-up changed there), the breaks it places such a change
at (which the loop may place again, :mod:`~torchcal.pipelines.loop.breaks`), what it waits for, and
what it becomes once other effects are found (:meth:`SessionFindings.given`).

:class:`~torchcal.effects.base.Effect` holds these; an effect that reads no session finding keeps the
defaults (nowhere, no break, nothing to wait for, itself).
"""
from __future__ import annotations

__all__ = ["SessionFindings"]


class SessionFindings:
    """The session half of :class:`~torchcal.effects.base.Effect` (module docstring)."""

    reads_load_changes = False  # given() wants where the residual shows the load to have changed

    def session_steps(self) -> list[str]:
        """Where this effect found the session to change, as ``<column>~step<k>`` (a step of ``time``
        or of the row order): a set-up changed there. Default: nowhere."""
        return []

    def breaks(self) -> list[str]:
        """Every break in time or the row order this effect's shapes or loads sit at, as
        ``<column>~step<k>`` or ``<column>~win<a>@<b>``: where it places a set-up change, which
        :mod:`~torchcal.pipelines.loop.breaks` may place again. Default: its session steps."""
        return self.session_steps()

    def with_break(self, old: str, new: str) -> "SessionFindings":
        """A copy with the break ``old`` moved to ``new`` (both as :meth:`breaks` names them): the same
        parameters in the same order, the values kept, only the place of the change moved. Default:
        itself (it holds no break)."""
        return self

    def break_parts(self) -> list[tuple[str, list[int]]]:
        """What this effect holds at a break beyond its modes, each of which can leave alone: ``(label,
        its parameter indices)``. A load changed at a step that a later finding explains otherwise (the
        tracker was knocked there, no payload swapped) is judged again as a mode is
        (:mod:`~torchcal.pipelines.loop.prune`). Default: nothing."""
        return []

    def without_part(self, label: str) -> "SessionFindings":
        """A copy without the part ``label`` of :meth:`break_parts` and its parameters (the others
        named as before; values are the caller's to carry by name). Default: itself."""
        return self

    def _carried(self, out: "SessionFindings") -> "SessionFindings":
        """``out`` (a copy with the same parameters under other names) with this one's values and prior."""
        out.theta = self.theta.detach().clone()
        if self.ridge is not None:
            out.ridge, out.ridge_mm = self.ridge.clone(), self.ridge_mm
        return out

    def waiting(self) -> str | None:
        """Why this candidate has nothing to offer yet (it waits for what a later round may find), or
        None. A waiting candidate is not tried in that round: its line in the record says why, the log
        says nothing."""
        return None

    def given(self, found: list, data, changes: list[str] = ()) -> "SessionFindings":
        """This candidate as what the current model has found informs it (``found``: its accepted
        effects; ``data``: the training rows; ``changes``: where the residual shows the load to have
        changed, as ``<column>~step<b>`` loads, asked for only by an effect that
        :attr:`reads_load_changes`): a set-up change found in the session may have changed more than
        the parameters it was found in. Default: itself."""
        return self
