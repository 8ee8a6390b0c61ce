"""ParamSet.select: a name is looked up, a glob pattern matched; the indices are fnmatch's."""
import fnmatch

import pytest

from torchcal import Robot
from torchcal.params import NoSuchParameter


@pytest.fixture(scope="module")
def params():
    return Robot.from_urdf("urdf/kuka_kr5_arc.urdf", markers=["smr@flange=0,0,0"]).params()


@pytest.mark.parametrize("patterns", [["joint_a2.dx"], ["*.dz"], ["joint_a[23].d?", "smr.dx"], ["joint_a1.*", "base.*"],
                                      ["joint_a2.dx", "joint_a2.dx", "*.rz"]])
def test_select_matches_fnmatch(params, patterns):
    ref = [i for i, n in enumerate(params.names) if any(fnmatch.fnmatchcase(n, p) for p in patterns)]
    assert ref, patterns  # the case means something
    assert params.select(patterns) == ref


def test_a_name_that_is_not_there_is_refused(params):
    with pytest.raises(NoSuchParameter, match="no parameter matches"):
        params.select(["joint_a2.dxx"])
