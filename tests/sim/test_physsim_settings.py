"""The independent simulator takes one settings record (issue 34), its fields also as keywords."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from torchcal.sim.physsim import PhysicalOptions, PhysicalRobot

UR5E = (Path(__file__).resolve().parents[2] / "urdf" / "ur5e.urdf").read_text()


def test_a_settings_record_and_keywords_make_the_same_robot():
    a = PhysicalRobot(UR5E, ["tool@flange"], PhysicalOptions(seed=5, noise_m=1e-5, torsion={"elbow_joint": 1e-5}))
    b = PhysicalRobot(UR5E, ["tool@flange"], seed=5, noise_m=1e-5, torsion={"elbow_joint": 1e-5})
    q = a.sample_q(7)
    assert np.allclose(q, b.sample_q(7))
    assert np.allclose(a.reach(q), b.reach(q), atol=0)
    c = PhysicalRobot(UR5E, ["tool@flange"], PhysicalOptions(seed=5), noise_m=1e-5, torsion={"elbow_joint": 1e-5})
    assert np.allclose(c.reach(q), a.reach(q), atol=0)


def test_a_misspelt_setting_is_refused_with_the_right_name():
    with pytest.raises(TypeError, match="did you mean 'noise_m'"):
        PhysicalRobot(UR5E, ["tool@flange"], noise_mm=1e-5)
