"""Measurement models: measured data and its CSV form, residual blocks (positions, poses, partial
observations: planes, distances, single axes), the registration of the instrument frame."""
from torchcal.measure.data import Measurements
from torchcal.measure.io import load_measurements

__all__ = ["Measurements", "load_measurements"]
