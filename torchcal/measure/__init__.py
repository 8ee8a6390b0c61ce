"""Measurement models: measured data and its CSV form, residual blocks (positions, poses, partial
observations: planes, distances, single axes), the registration of the instrument frame."""
from torchcal.measure.io import Measurements, load_measurements

__all__ = ["Measurements", "load_measurements"]
