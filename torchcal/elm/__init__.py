"""Extreme learning machines: the residual model a calibration's loop fits (:class:`ELM`) and its
tuning by swarm solvers (:func:`tune_elm`). Saving and loading one belongs to
:mod:`torchcal.deploy`."""
from torchcal.elm.model import ACTIVATIONS, ELM
from torchcal.elm.tune import TuneOptions, tune_elm

__all__ = ["ELM", "ACTIVATIONS", "TuneOptions", "tune_elm"]
