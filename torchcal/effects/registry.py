"""The one registry of effect classes.

Every effect class is registered once, with :func:`register_effect`, and is then found two ways:

* by its ``name`` (``"joint_compliance"``) in :data:`EFFECTS`: the candidates the loop tries and
  the names the CLI and :func:`~torchcal.effects.build_effect` accept (classes derived from
  :class:`~torchcal.effects.base.Effect`);
* by the type key a saved model records (:func:`effect_type`: ``cls.effect_type`` when set, else
  the class name), through :func:`effect_class`, when :func:`torchcal.deploy.persist.load`
  rebuilds a model. Loading never imports code named by a file: a user's effect class must be
  registered (imported) before its model is loaded.

A user-defined effect registers with one decorator::

    @register_effect
    class MyEffect:                       # or a subclass of torchcal.effects.Effect
        effect_type = "my_effect"         # the key saved files carry (default: the class name)
        def joint_correction(self, q, covariates): ...
        def state_dict(self): ...
        @classmethod
        def from_state_dict(cls, state, robot): ...
"""
from __future__ import annotations

from torchcal.effects.base import Effect

__all__ = ["EFFECTS", "register_effect", "effect_class", "effect_type"]

EFFECTS: dict[str, type[Effect]] = {}
"""Effect models the loop can fit, by ``name``."""

_BY_TYPE: dict[str, type] = {}

_HOOKS = ("joint_correction", "state_dict", "from_state_dict")


def effect_type(cls: type) -> str:
    """The key a saved model records for an effect class: ``cls.effect_type`` when set, else the
    class name."""
    return getattr(cls, "effect_type", None) or cls.__name__


def register_effect(cls: type) -> type:
    """Class decorator: make ``cls`` loadable from saved models (by :func:`effect_type`) and, for a
    subclass of :class:`~torchcal.effects.base.Effect`, a candidate of the loop (by ``name``).
    Refuses a class that lacks what a deployed model calls (``joint_correction``, ``state_dict``,
    ``from_state_dict``)."""
    for need in _HOOKS:
        if not hasattr(cls, need):
            raise TypeError(f"effect class {cls.__name__} lacks {need}(); see torchcal.deploy.model.EffectHook")
    _BY_TYPE[effect_type(cls)] = cls
    if isinstance(cls, type) and issubclass(cls, Effect) and cls.name != Effect.name:
        EFFECTS[cls.name] = cls
    return cls


def effect_class(key: str) -> type:
    """The effect class registered under the saved type ``key``."""
    try:
        return _BY_TYPE[key]
    except KeyError:
        raise ValueError(f"unknown effect type {key!r}; registered: {sorted(_BY_TYPE)}. Import the module that "
                         "defines it (it registers itself with @torchcal.effects.register_effect) before "
                         "loading") from None
