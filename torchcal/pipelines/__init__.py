"""Drivers that run the stages end to end: calibration, the effect loop, fleets, pose planning,
PSD calibration, 3-RRRU calibration and dynamic identification."""
