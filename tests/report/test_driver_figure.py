"""The figure of a parameter against its driver: a parameter's terms summed into one shape, the
partial residual around it."""
from __future__ import annotations

import numpy as np

from torchcal.report.drivers import driver_figure, driver_panels


def _ev():
    x = np.linspace(-30, 30, 61)
    lin, knee = 1e-5 * x, 1e-5 * np.clip(x, -15, 15)
    noise = 1e-6 * np.sin(7 * x)
    common = {"x": x.tolist(), "xlabel": "the gravity torque at j2 [N·m]", "ylabel": "j2.offset [rad]",
              "words": "joint j2's zero varies with the torque", "r": 1.0}
    return {"j2.offset~torque:j2~lin": {**common, "fitted": lin.tolist(), "residual": (lin + noise).tolist()},
            "j2.offset~torque:j2~sat15": {**common, "fitted": knee.tolist(), "residual": (knee + noise).tolist()}}


def test_terms_of_one_parameter_and_driver_are_one_shape():
    panels = driver_panels(_ev())
    assert list(panels) == ["j2.offset~torque:j2"]
    p = panels["j2.offset~torque:j2"]
    x = np.asarray(p["x"])
    assert np.allclose(p["fitted"], 1e-5 * x + 1e-5 * np.clip(x, -15, 15))
    assert np.allclose(p["residual"] - p["fitted"], 1e-6 * np.sin(7 * x))


def test_the_figure_is_written(tmp_path):
    assert driver_figure(_ev(), tmp_path / "drivers.png") is not None
    assert (tmp_path / "drivers.png").stat().st_size > 1000
    assert driver_figure({}, tmp_path / "none.png") is None
