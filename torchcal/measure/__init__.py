"""Measurement models: measured data and its CSV form, the observations a fit reads (positions, poses,
partial positions, plane contacts, distances), the registration of the instrument frame, and the
typed records of a model's error on the data (statistics, details, the trust judgement)."""
from torchcal.measure.data import Measurements
from torchcal.measure.io import load_measurements

__all__ = ["Measurements", "load_measurements"]
