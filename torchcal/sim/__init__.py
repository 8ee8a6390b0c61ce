"""Simulators that make measured data with known truth, for tests and scripts. The identifying code
never reads their truth."""
