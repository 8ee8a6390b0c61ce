"""The independent robot simulator (torchcal.sim.physsim) against independent references.

* forward kinematics: yourdfpy's scene graph (UR5e, the synthetic humanoid, a tree with a mimic
  joint and a prismatic joint);
* gravity moments: central finite differences of the potential energy, with COMs from yourdfpy;
* torsion, backlash and cyclic errors: yourdfpy at the deflected joint values;
* base tilt, lateral compliance and thermal growth: physical signs, linearity and lengths.
"""
from __future__ import annotations

import io
import json
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
import yourdfpy
from scipy.spatial.transform import Rotation

from torchcal.measure.io import save_measurements
from torchcal.sim.physsim import PhysicalRobot, warmup_temperature
from torchcal.sim.sample import Sample
from torchcal.sim.humanoid import humanoid_urdf

UR5E = Path(__file__).resolve().parents[2] / "urdf" / "ur5e.urdf"
G = np.array([0.0, 0.0, -9.81])
PAYLOAD = dict(payload_kg=3.0, payload_com_m=(0.02, -0.01, 0.06), payload_link="flange")


def _udf(text_or_path) -> yourdfpy.URDF:
    src = io.StringIO(text_or_path) if isinstance(text_or_path, str) else str(text_or_path)
    return yourdfpy.URDF.load(src, build_scene_graph=True, load_meshes=False,
                              build_collision_scene_graph=False, load_collision_meshes=False)


def _ideal(urdf, markers, **kw) -> PhysicalRobot:
    """No errors, instrument frame = base frame."""
    return PhysicalRobot(urdf, markers, geometric_errors=False, instrument_frame=np.eye(4), noise_m=0.0, **kw)


def _ref_points(u, names, q, points) -> np.ndarray:
    """(N, len(points), 3) base-frame positions of (link, xyz) points from yourdfpy."""
    out = np.empty((len(q), len(points), 3))
    for n, row in enumerate(q):
        u.update_cfg(dict(zip(names, row)))
        for m, (link, xyz) in enumerate(points):
            T = u.get_transform(link, u.base_link)
            out[n, m] = T[:3, :3] @ np.asarray(xyz, float) + T[:3, 3]
    return out


def _mass_points(u, payload_link=None, payload_kg=0.0, payload_com=(0, 0, 0)):
    pts = [(ln.name, ln.inertial.mass, ln.inertial.origin[:3, 3]) for ln in u.robot.links
           if ln.inertial is not None and ln.inertial.mass]
    if payload_kg:
        pts.append((payload_link, payload_kg, np.asarray(payload_com, float)))
    return pts


def _potential(u, names, q, pts) -> float:
    """V = -sum m_i g^T c_i (J), COMs from yourdfpy."""
    c = _ref_points(u, names, q[None], [(ln, x) for ln, _, x in pts])[0]
    return -sum(m * G @ ci for (_, m, _), ci in zip(pts, c))


def _ref_torques(u, names, q, pts, h=1e-6) -> np.ndarray:
    """(N, dof) gravity torques -dV/dq by central differences."""
    tau = np.empty_like(q)
    for n, row in enumerate(q):
        for j in range(len(names)):
            e = np.zeros(len(names))
            e[j] = h
            tau[n, j] = -(_potential(u, names, row + e, pts) - _potential(u, names, row - e, pts)) / (2 * h)
    return tau


@pytest.mark.parametrize("which", ["ur5e", "humanoid", "tree"])
def test_reach_matches_yourdfpy(which, tree_urdf):
    if which == "ur5e":
        urdf, pts = UR5E, [("flange", (0, 0, 0)), ("link3", (0.1, 0.02, -0.03)), ("link5", (0, 0, 0))]
    elif which == "humanoid":
        urdf, pts = humanoid_urdf(), [("l_hand", (0, 0, 0)), ("r_hand", (0.01, 0.02, 0.03)),
                                      ("head_link", (0, 0, 0)), ("chest_link", (0.1, 0, 0.3))]
    else:
        urdf, pts = tree_urdf, [("tool", (0, 0, 0)), ("finger_b", (0.01, 0.02, 0.03)), ("finger_a", (0, 0, 0))]
    markers = [f"m{k}@{ln}={x[0]},{x[1]},{x[2]}" for k, (ln, x) in enumerate(pts)]
    r = _ideal(urdf if isinstance(urdf, str) else urdf, markers)
    if which == "humanoid":
        assert r.dof == 19
    q = r.sample_q(25, margin=0.0)
    ref = _ref_points(_udf(urdf), r.joint_names, q, pts)
    np.testing.assert_allclose(r.reach(q), ref, atol=1e-10, rtol=0)


def _perturbed_urdf(text: str, truth: dict) -> str:
    """The URDF with every joint origin replaced by O_nom . Trans(d) . Rz Ry Rx from the truth."""
    root = ET.fromstring(text)
    for j in root.findall("joint"):
        o = j.find("origin")
        if o is None:
            o = ET.SubElement(j, "origin")
        xyz = np.array([float(v) for v in o.get("xyz", "0 0 0").split()])
        R = Rotation.from_euler("xyz", [float(v) for v in o.get("rpy", "0 0 0").split()])  # extrinsic: Rz Ry Rx
        e = truth["joint_origin_error"][j.get("name")]
        dR = Rotation.from_euler("xyz", [e["droll_rad"], e["dpitch_rad"], e["dyaw_rad"]])
        t = xyz + R.apply([e["dx_m"], e["dy_m"], e["dz_m"]])
        o.set("xyz", " ".join(repr(float(v)) for v in t))
        o.set("rpy", " ".join(repr(float(v)) for v in (R * dR).as_euler("xyz")))
    return ET.tostring(root, encoding="unicode")


@pytest.mark.parametrize("which", ["ur5e", "tree"])
def test_drawn_errors_match_truth_through_yourdfpy(which, tree_urdf):
    """Rebuild the true robot from truth() alone (perturbed URDF, zero offsets added to q, true
    marker offsets, instrument frame) and evaluate it with yourdfpy."""
    text = UR5E.read_text() if which == "ur5e" else tree_urdf
    markers = ["flange", "p@link4=0.1,0.02,0.05"] if which == "ur5e" else ["tool", "p@finger_b=0.01,0.02,0.03"]
    r = PhysicalRobot(text, markers, seed=11, length_error_m=2e-3, angle_error_rad=5e-3, marker_error_m=1e-3,
                      noise_m=0.0)
    t = json.loads(json.dumps(r.truth()))
    q = r.sample_q(10)
    off = np.array([{**t["zero_offset_rad"], **t["zero_offset_m"]}[n] for n in r.joint_names])
    assert np.all(off != 0)
    pts = [(t["marker_link"][m], t["marker_offset_true_m"][m]) for m in r.marker_names]
    p_base = _ref_points(_udf(_perturbed_urdf(text, t)), r.joint_names, q + off, pts)
    T = np.array(t["base_in_instrument_4x4_m"])
    ref = p_base @ T[:3, :3].T + T[:3, 3]
    np.testing.assert_allclose(r.measure(q).positions, ref, atol=1e-10, rtol=0)
    # the errors matter: the nominal robot is mm away
    nominal = _ref_points(_udf(text), r.joint_names, q, [(t["marker_link"][m], t["marker_offset_declared_m"][m])
                                                           for m in r.marker_names]) @ T[:3, :3].T + T[:3, 3]
    assert np.abs(ref - nominal).max() > 1e-3


def test_gravity_torque_is_minus_potential_gradient():
    r = _ideal(UR5E, ["flange"], **PAYLOAD)
    u = _udf(UR5E)
    q = r.sample_q(4)
    pts = _mass_points(u, "flange", PAYLOAD["payload_kg"], PAYLOAD["payload_com_m"])
    ref = _ref_torques(u, r.joint_names, q, pts)
    W = r.gravity_wrenches(q)
    tau = np.stack([W["joints"][n]["tau_Nm"] for n in r.joint_names], 1)
    np.testing.assert_allclose(tau, ref, atol=1e-6, rtol=0)
    # M . axis with the axis taken from yourdfpy: the projection is on the right axis
    for n, row in enumerate(q):
        u.update_cfg(dict(zip(r.joint_names, row)))
        for k, name in enumerate(r.joint_names):
            j = u.joint_map[name]
            a = u.get_transform(j.child, u.base_link)[:3, :3] @ j.axis
            assert W["joints"][name]["M_Nm"][n] @ a == pytest.approx(ref[n, k], abs=1e-6)
    # base: total weight and sum c x m g
    mtot = sum(m for _, m, _ in pts)
    np.testing.assert_allclose(W["base"]["F_N"], np.tile(mtot * G, (len(q), 1)), atol=1e-12)
    c = np.stack([_ref_points(u, r.joint_names, row[None], [(ln, x) for ln, _, x in pts])[0] for row in q])
    Mb = sum(np.cross(c[:, i], m * G) for i, (_, m, _) in enumerate(pts))
    np.testing.assert_allclose(W["base"]["M_Nm"], Mb, atol=1e-10)


def test_torsion_equals_rigid_robot_at_deflected_angles():
    k = {"shoulder_lift_joint": 2e-4, "elbow_joint": 3e-4, "wrist_1_joint": 1e-3, "wrist_2_joint": 5e-4}
    r = _ideal(UR5E, ["flange", "tcp@flange=0.0,0.05,0.1"], torsion=k, **PAYLOAD)
    u = _udf(UR5E)
    q = r.sample_q(5)
    tau = _ref_torques(u, r.joint_names, q, _mass_points(u, "flange", PAYLOAD["payload_kg"],
                                                          PAYLOAD["payload_com_m"]))
    kv = np.array([k.get(n, 0.0) for n in r.joint_names])
    ref = _ref_points(u, r.joint_names, q + kv * tau, [("flange", (0, 0, 0)), ("flange", (0, 0.05, 0.1))])
    got = r.reach(q)
    np.testing.assert_allclose(got, ref, atol=1e-9, rtol=0)
    assert np.abs(got - _ideal(UR5E, ["flange", "tcp@flange=0.0,0.05,0.1"], **PAYLOAD).reach(q)).max() > 1e-4


def test_base_tilt_makes_a_stretched_arm_sag_linearly():
    q = np.array([[np.pi, 0, 0, 0, 0, 0]])  # UR5e zero pose points along -x; pan by pi: along +x
    rigid = _ideal(UR5E, ["flange"], payload_kg=10.0).reach(q)[0, 0]
    assert rigid[0] > 0.8 and abs(rigid[2] - 0.0628) < 1e-9
    d = [_ideal(UR5E, ["flange"], payload_kg=10.0, base_tilt=(c, c)).reach(q)[0, 0] - rigid for c in (1e-7, 2e-7)]
    assert d[0][2] < -1e-5 and d[1][2] < 0
    assert d[1][2] == pytest.approx(2 * d[0][2], rel=1e-4)  # linear to first order
    np.testing.assert_allclose(d[1], 2 * d[0], atol=1e-8)
    # first order: d = omega x p_tip, omega = c (Mx, My, 0), moments from the masses alone
    u = _udf(UR5E)
    pts = _mass_points(u, "flange", 10.0)
    c = _ref_points(u, [j for j in u.actuated_joint_names], q, [(ln, x) for ln, _, x in pts])[0]
    Mb = sum(np.cross(ci, m * G) for (_, m, _), ci in zip(pts, c))
    assert Mb[1] > 0
    np.testing.assert_allclose(d[0], np.cross(1e-7 * np.array([Mb[0], Mb[1], 0]), rigid), rtol=0, atol=1e-9)


def test_lateral_deflection_perpendicular_to_axis_linear_and_moment_driven():
    markers = ["flange", "a@flange=0.1,0,0", "b@flange=0,0.1,0", "c@flange=0,0,0.1"]
    q = np.array([[0.3, -0.4, 0.7, -0.2, 0.5, 0.1]])
    rigid = _ideal(UR5E, markers, **PAYLOAD)
    p0 = rigid.reach(q)[0]
    u = _udf(UR5E)
    u.update_cfg(dict(zip(rigid.joint_names, q[0])))
    Tj = u.get_transform("link3", u.base_link)  # child frame of elbow_joint
    axis, o = Tj[:3, :3] @ u.joint_map["elbow_joint"].axis, Tj[:3, 3]
    pts = _mass_points(u, "flange", PAYLOAD["payload_kg"], PAYLOAD["payload_com_m"])
    below = {"link3", "link4", "link5", "link6", "flange"}
    cs = [(m, u.get_transform(ln, u.base_link)) for ln, m, x in pts if ln in below]
    xs = [x for ln, m, x in pts if ln in below]
    M = sum(np.cross(T[:3, :3] @ x + T[:3, 3] - o, m * G) for (m, T), x in zip(cs, xs))
    cvec = np.array([3e-6, 5e-6, 0.0])
    omega_ref = Tj[:3, :3] @ (cvec * (Tj[:3, :3].T @ M))
    ds = []
    for scale in (1.0, 2.0):
        r = _ideal(UR5E, markers, lateral={"elbow_joint": scale * cvec}, **PAYLOAD)
        d = r.reach(q)[0] - p0
        # the downstream part turned rigidly about o: recover that rotation exactly (Kabsch)
        U, _, Vt = np.linalg.svd((p0 - o).T @ (r.reach(q)[0] - o))
        R = Vt.T @ np.diag([1, 1, np.linalg.det(Vt.T @ U.T)]) @ U.T
        omega = Rotation.from_matrix(R).as_rotvec()
        assert abs(omega @ axis) < 1e-9 * np.linalg.norm(omega)  # perpendicular to the joint axis
        np.testing.assert_allclose(omega, scale * omega_ref, rtol=1e-9, atol=1e-15)
        np.testing.assert_allclose(d, np.cross(omega, p0 - o), atol=1e-8)  # moved perpendicular to omega
        ds.append(d)
    assert np.linalg.norm(ds[0]) > 1e-5
    np.testing.assert_allclose(ds[1], 2 * ds[0], rtol=2e-3, atol=1e-10)
    still = _ideal(UR5E, markers, lateral={"elbow_joint": cvec}, gravity=(0, 0, 0), **PAYLOAD)
    np.testing.assert_allclose(still.reach(q)[0], p0, atol=1e-15)


def test_thermal_growth_of_one_link():
    alpha, dT = 2.3e-5, 25.0
    r = _ideal(UR5E, ["link2", "link3", "flange"], thermal={"elbow_joint": alpha})
    q = r.sample_q(6)
    cold = r.reach(q, temperature=r.t_ref_c)
    hot = r.reach(q, temperature=np.full(len(q), r.t_ref_c + dT))
    L = lambda p: np.linalg.norm(p[:, 1] - p[:, 0], axis=1)  # noqa: E731
    np.testing.assert_allclose(L(cold), 0.425, atol=1e-12)
    np.testing.assert_allclose(L(hot) - L(cold), alpha * dT * 0.425, atol=1e-13)
    s = r.measure(q, temperature=warmup_temperature(len(q), 8.0, seed=1))
    assert "temperature" in s.covariates and np.all(np.diff(warmup_temperature(200, 8.0, 0, noise_k=0)) > 0)


def test_backlash_and_cyclic_against_yourdfpy():
    half = {"shoulder_lift_joint": 2e-3, "wrist_3_joint": 1e-3}
    cyc = {"elbow_joint": [(1, 1e-3, 0.3), (2, 5e-4, -1.0)]}
    r = _ideal(UR5E, ["flange", "t@flange=0.05,0,0.1"], backlash=half, cyclic=cyc)
    q = r.sample_q(8)
    q[3] = q[2]  # no motion: keeps the previous direction
    s = r.measure(q)
    assert sorted(s.covariates) == sorted(f"dir.{n}" for n in r.joint_names)
    D = np.stack([s.covariates[f"dir.{n}"] for n in r.joint_names], 1)
    assert set(np.unique(D)) <= {-1.0, 1.0}
    np.testing.assert_array_equal(D[1:3], np.sign(np.diff(q[:3], axis=0)))
    np.testing.assert_array_equal(D[3], D[2])
    qr = q.copy()
    for k, n in enumerate(r.joint_names):
        qr[:, k] += half.get(n, 0.0) * D[:, k] + sum(a * np.sin(h * q[:, k] + ph) for h, a, ph in cyc.get(n, []))
    ref = _ref_points(_udf(UR5E), r.joint_names, qr, [("flange", (0, 0, 0)), ("flange", (0.05, 0, 0.1))])
    np.testing.assert_allclose(s.positions, ref, atol=1e-10, rtol=0)


def test_outliers_are_counted_sized_listed_and_hidden(tmp_path):
    r = PhysicalRobot(humanoid_urdf(), ["l_hand", "r_hand", "head_link"], noise_m=0.0, seed=3)
    q = r.sample_q(200)
    s = r.measure(q, outlier_fraction=0.07, outlier_mm=(5, 20))
    shift = s.positions - r.reach(q)
    moved = np.flatnonzero(np.abs(shift).max(axis=(1, 2)) > 0)
    assert len(s.outlier_rows) == round(0.07 * 200) == len(moved)
    np.testing.assert_array_equal(moved, s.outlier_rows)
    size = np.linalg.norm(shift[moved], axis=-1)
    assert size.min() >= 5e-3 - 1e-12 and size.max() <= 20e-3 + 1e-12
    whole = ~s.outlier_per_marker
    assert whole.any() and (~whole).any()
    np.testing.assert_allclose(shift[moved][whole], np.repeat(shift[moved][whole][:, :1], 3, 1), atol=1e-15)
    m = s.to_measurements()
    assert m.covariates == {} and m.positions.shape == (200, 3, 3)
    save_measurements(tmp_path / "m.csv", m)
    header = (tmp_path / "m.csv").read_text().splitlines()[0]
    assert "outlier" not in header.lower() and len(header.split(",")) == 19 + 9
    sub = s.subset(np.arange(0, 200, 2))
    assert set(sub.outlier_rows * 2) == {int(x) for x in s.outlier_rows if x % 2 == 0}


def test_same_seed_same_robot_and_data():
    kw = dict(torsion={"l_elbow_joint": 1e-4}, backlash={"torso_pitch_joint": 1e-3}, base_tilt=(1e-7, 1e-7),
              payload_kg=1.0, marker_error_m=1e-3)

    def run(seed):
        r = PhysicalRobot(humanoid_urdf(), ["l_hand", "p@head_link=0.1,0,0.05"], seed=seed, **kw)
        q = r.sample_q(50)
        return r.truth(), r.measure(q, outlier_fraction=0.1)

    (t1, s1), (t2, s2), (t3, s3) = run(7), run(7), run(8)
    assert json.dumps(t1, sort_keys=True) == json.dumps(t2, sort_keys=True)
    np.testing.assert_array_equal(s1.positions, s2.positions)
    np.testing.assert_array_equal(s1.q, s2.q)
    np.testing.assert_array_equal(s1.outlier_rows, s2.outlier_rows)
    assert t1 != t3 and not np.allclose(s1.positions, s3.positions)
    assert abs(np.linalg.norm(np.array(t1["instrument_in_base_4x4_m"])[:3, 3]) - 3.0) < 1e-12


def test_many_poses_are_fast():
    import time
    r = PhysicalRobot(humanoid_urdf(), ["l_hand", "r_hand", "head_link"], torsion={"l_elbow_joint": 1e-4},
                      lateral={"l_shoulder_pitch_joint": (1e-5, 0, 1e-5)}, base_tilt=(1e-7, 1e-7),
                      thermal={"l_elbow_joint": 2e-5}, backlash={"l_elbow_joint": 1e-3})
    q = r.sample_q(3000)
    t = time.perf_counter()
    s = r.measure(q, temperature=warmup_temperature(3000, 5.0, 0), outlier_fraction=0.02)
    assert time.perf_counter() - t < 2.0 and isinstance(s, Sample) and s.positions.shape == (3000, 3, 3)


# ---------------------------------------------------------------- joint-space terms, covariates, poses
IIWA = Path(__file__).resolve().parents[2] / "urdf" / "kuka_iiwa14.urdf"
TOOL = ["tool@flange=0.06,0.0,0.08"]


def test_iiwa_has_inertials():
    from torchcal.sim.physsim_urdf import parse_urdf
    _, _, bodies = parse_urdf(IIWA.read_text())
    assert [ln for ln, b in bodies.items() if b and b[0][0] > 0] == [f"link{i}" for i in range(1, 8)]


def test_coupling_is_the_rigid_robot_with_the_joint_shifted():
    """a7 turns c rad per rad of a6: the sim's own rigid FK, yourdfpy and pytorch-kinematics at
    the shifted angles."""
    c = 2e-3
    r = _ideal(IIWA, TOOL, joint_terms={"iiwa_joint_7": [("iiwa_joint_6", "linear", c)]})
    q = r.sample_q(20)
    shifted = q.copy()
    shifted[:, 6] += c * q[:, 5]
    got = r.reach(q)
    np.testing.assert_allclose(got, _ideal(IIWA, TOOL).reach(shifted), atol=1e-15, rtol=0)
    ref = _ref_points(_udf(IIWA), r.joint_names, shifted, [("flange", (0.06, 0.0, 0.08))])
    np.testing.assert_allclose(got, ref, atol=1e-10, rtol=0)
    assert np.abs(got - _ideal(IIWA, TOOL).reach(q)).max() > 1e-4  # 2 mrad x up to 2 rad x 6 cm
    pk = pytest.importorskip("pytorch_kinematics")
    import torch
    chain = pk.build_chain_from_urdf(IIWA.read_text()).to(dtype=torch.float64)
    assert chain.get_joint_parameter_names() == r.joint_names
    T = chain.forward_kinematics(torch.from_numpy(shifted[:1]))["flange"].get_matrix()[0].numpy()
    # pytorch-kinematics reads origin rpy in float32: ~4e-8 m (see test_fk_reference)
    np.testing.assert_allclose(got[0, 0], T[:3, :3] @ [0.06, 0.0, 0.08] + T[:3, 3], atol=1e-7, rtol=0)


def test_harmonic_and_covariate_terms():
    r0 = _ideal(IIWA, TOOL)
    q = r0.sample_q(15)
    # an own-angle harmonic as a joint term is the existing cyclic error
    term = _ideal(IIWA, TOOL, joint_terms={"iiwa_joint_4": [("iiwa_joint_4", "sin", 1e-4, 2, -1.0)]})
    cyc = _ideal(IIWA, TOOL, cyclic={"iiwa_joint_4": [(2, 1e-4, -1.0)]})
    np.testing.assert_allclose(term.reach(q), cyc.reach(q), atol=1e-15, rtol=0)
    # cos of another joint, and a covariate column read linearly from its reference
    T = 20.0 + 10 * np.linspace(0, 1, len(q))
    r = _ideal(IIWA, TOOL, joint_terms={"iiwa_joint_2": [("iiwa_joint_1", "cos", 3e-4, 1, 0.2),
                                                          ("temp_motor_a2", "linear", 2e-5, 1, 0.0, 20.0)]})
    shifted = q.copy()
    shifted[:, 1] += 3e-4 * np.cos(q[:, 0] + 0.2) + 2e-5 * (T - 20.0)
    np.testing.assert_allclose(r.reach(q, covariates={"temp_motor_a2": T}), r0.reach(shifted), atol=1e-15, rtol=0)
    s = r.measure(q, covariates={"temp_motor_a2": T, "temp_ambient": np.full(len(q), 21.0)})
    assert list(s.covariates) == ["temp_motor_a2", "temp_ambient"]
    with pytest.raises(ValueError, match="temp_motor_a2"):
        r.measure(q)
    with pytest.raises(ValueError, match="sin/cos terms need a joint"):
        _ideal(IIWA, TOOL, joint_terms={"iiwa_joint_2": [("temp", "sin", 1e-4)]})
    with pytest.raises(ValueError, match="not a commanded joint"):
        _ideal(IIWA, TOOL, joint_terms={"nope": [("iiwa_joint_1", "linear", 1e-4)]})
    words = r.truth()["joint_terms_in_words"]
    assert words[1] == "iiwa_joint_2 turns 0.02 mrad per K of temp_motor_a2 from 20 (covariate)"


def test_thermal_reads_only_its_named_column():
    alpha = 2.3e-5
    kw = dict(thermal={"elbow_joint": (alpha, "temp_motor_a3")})
    r = _ideal(UR5E, ["link2", "link3"], **kw)
    q = r.sample_q(8)
    motor = 25.0 + np.arange(len(q), dtype=float)
    amb = [np.full(len(q), 21.0), np.linspace(15, 30, len(q))]
    runs = [_ideal(UR5E, ["link2", "link3"], **kw).measure(q, temperature=a + 3, covariates={"temp_ambient": a,
                                                                                              "temp_motor_a3": motor})
            for a in amb]
    np.testing.assert_array_equal(runs[0].positions, runs[1].positions)  # the irrelevant columns change nothing
    assert list(runs[0].covariates) == ["temperature", "temp_ambient", "temp_motor_a3"]
    L = np.linalg.norm(runs[0].positions[:, 1] - runs[0].positions[:, 0], axis=1)
    np.testing.assert_allclose(L, 0.425 * (1 + alpha * (motor - r.t_ref_c)), atol=1e-13, rtol=0)
    s = r.measure(q, covariates={"temp_motor_a3": motor})
    assert "temperature" not in s.covariates  # only recorded when something reads it or it is given
    assert r.truth()["thermal_column"] == {"elbow_joint": "temp_motor_a3"}


def _angles(qa, qb):
    return 2 * np.arccos(np.clip(np.abs(np.sum(qa * qb, -1)), 0, 1))


def test_orientation_is_the_link_frame_times_the_marker_rotation_in_the_instrument_frame():
    rpy = (0.1, -0.2, 0.3)
    mk = ["tool@flange=0.01,0.02,0.05", "elbow@link3"]
    r = PhysicalRobot(UR5E, mk, seed=4, geometric_errors=False, noise_m=0.0, marker_rpy={"tool": rpy},
                      pose_markers=["tool"])
    q = r.sample_q(12)
    s = r.measure(q)
    u = _udf(UR5E)
    Ti = r.instrument_in_base
    ref = []
    for row in q:
        u.update_cfg(dict(zip(r.joint_names, row)))
        R = Ti[:3, :3].T @ u.get_transform("flange", u.base_link)[:3, :3] @ Rotation.from_euler("xyz", rpy).as_matrix()
        ref.append(Rotation.from_matrix(R).as_quat()[[3, 0, 1, 2]])
    ref = np.array(ref)
    assert np.all(np.isnan(s.quaternions[:, 1])) and s.quaternions.shape == (12, 2, 4)
    assert np.all(s.quaternions[:, 0, 0] >= 0)
    np.testing.assert_allclose(_angles(s.quaternions[:, 0], ref), 0, atol=1e-7)  # rad
    np.testing.assert_allclose(s.quaternions[:, 0], s.true_quaternions[:, 0], atol=0)


def test_orientation_noise_fraction_and_unchanged_positions():
    kw = dict(seed=5, marker_rotation_error_rad=5e-3)
    plain = PhysicalRobot(UR5E, ["t@flange"], **kw)
    posed = PhysicalRobot(UR5E, ["t@flange"], pose_markers=True, rot_noise_rad=2e-3, **kw)
    q = plain.sample_q(400)
    posed.sample_q(400)
    a, b = plain.measure(q), posed.measure(q, orientation_fraction=0.3)
    np.testing.assert_array_equal(a.positions, b.positions)  # orientation draws come last
    assert a.quaternions is None
    seen = ~np.isnan(b.quaternions[:, 0, 0])
    assert seen.sum() == 120 and np.isnan(b.quaternions[~seen]).all()
    ang = _angles(b.quaternions[seen, 0], b.true_quaternions[seen, 0])
    assert abs(ang.mean() / (2e-3 * 1.596) - 1) < 0.1  # mean |n| of a 3-D Gaussian: 1.596 sigma
    R_true = np.array(posed.truth()["marker_rotation_true_3x3"]["t"])
    assert 1e-3 < Rotation.from_matrix(R_true).magnitude() < 2e-2 and posed.error_support()["marker_rotations"] == ["t"]
    with pytest.raises(ValueError, match="orientation_fraction"):
        posed.measure(q[:3], orientation_fraction=1.5)


def test_true_marker_point_apart_from_a_guess_on_the_last_axis():
    from torchcal.sim.humanoid import arm9_urdf
    true = (0.05, 0.03, -0.02)
    guess = _ideal(arm9_urdf(), ["grip@gripper_link"])
    real = _ideal(arm9_urdf(), ["grip@gripper_link"], marker_true_m={"grip": true})
    q = guess.sample_q(6)
    q2 = q.copy()
    q2[:, -1] += 1.0  # turn the last joint alone
    np.testing.assert_allclose(guess.reach(q2), guess.reach(q), atol=1e-14)  # the guess is on its axis
    moved = np.linalg.norm(real.reach(q2) - real.reach(q), axis=-1)
    np.testing.assert_allclose(moved, 2 * np.hypot(0.05, 0.03) * np.sin(0.5), atol=1e-12)  # chord at 5.8 cm
    t = real.truth()
    assert t["marker_offset_declared_m"]["grip"] == [0.0, 0.0, 0.0] and t["marker_offset_true_m"]["grip"] == list(true)
    assert real.error_support()["marker_offsets"] == ["grip"]


def test_ur10_description():
    from torchcal.sim.ur10 import UR10_DH, ur10_urdf
    text = ur10_urdf()
    r = _ideal(text, ["flange"])
    d = UR10_DH
    np.testing.assert_allclose(r.reach(np.zeros((1, 6)))[0, 0], [d["a2"] + d["a3"], -(d["d4"] + d["d6"]),
                                                                  d["d1"] - d["d5"]], atol=1e-12)
    q = r.sample_q(10)
    np.testing.assert_allclose(r.reach(q), _ref_points(_udf(text), r.joint_names, q, [("flange", (0, 0, 0))]),
                               atol=1e-10, rtol=0)
    masses = [ln.inertial.mass for ln in _udf(text).robot.links if ln.inertial is not None]
    assert masses == [7.1, 12.7, 4.27, 2.0, 2.0, 0.365]


def test_covariate_series():
    from torchcal.sim.covariates import campaign_time, covariate_columns, motor_temperature
    m = motor_temperature(500, 1, ambient_c=22.0, rise_k=18.0, noise_k=0.0)
    assert 22.0 <= m.min() and m.max() <= 40.0 and m.std() > 2.0
    t = campaign_time(200, 2)
    assert t[0] == 0 and np.all(np.diff(t) > 0) and np.diff(t).max() > 500  # a pause
    spec = {"temp_ambient": ("ambient", {}), "time": ("time", {})}
    a = covariate_columns(spec, 50, 3)
    b = covariate_columns({**spec, "temp_skin": ("skin", {})}, 50, 3)
    assert all(np.array_equal(a[k], b[k]) for k in a)  # adding a column leaves the others
    with pytest.raises(ValueError, match="unknown series"):
        covariate_columns({"x": ("nope", {})}, 5, 0)


NEW_CASES = ["wrist_coupling", "thermal_second_column", "twist_seat_7dof", "harmonics_twist", "clean_covariates",
             "arm9_mocap", "pose6d", "pose6d_partial"]


@pytest.mark.parametrize("name", NEW_CASES)
def test_new_cases_are_reproducible_from_the_seed(name):
    from torchcal.sim.cases import make_case
    a, b, c = make_case(name, 2), make_case(name, 2), make_case(name, 3)
    for part in ("train", "test"):
        sa, sb = getattr(a, part), getattr(b, part)
        for f in ("q", "positions", "true_positions", "quaternions"):
            x, y = getattr(sa, f), getattr(sb, f)
            assert (x is None and y is None) or np.array_equal(x, y, equal_nan=True), (part, f)
        assert list(sa.covariates) == list(sb.covariates)
        assert all(np.array_equal(sa.covariates[k], sb.covariates[k]) for k in sa.covariates)
    assert json.dumps(a.real.truth(), sort_keys=True) == json.dumps(b.real.truth(), sort_keys=True)
    assert not np.allclose(a.train.positions, c.train.positions)


def test_geometry_cases_as_the_issue_sets_them():
    from torchcal.sim.cases import make_case
    arm = make_case("arm9_mocap")
    assert (arm.real.dof, len(arm.train), len(arm.test), arm.markers) == (9, 45, 16, ["grip@gripper_link"])
    sup = arm.error_support
    assert len(sup["joint_origins"]) == 10 and len(sup["zero_offsets"]) == 9 and sup["marker_offsets"] == ["grip"]
    assert 0.4 < arm.floor_mm < 0.6  # 0.3 mm per axis
    pose = make_case("pose6d")
    assert (pose.real.dof, len(pose.train), len(pose.test)) == (6, 17, 6) and pose.error_support["marker_rotations"]
    assert not np.isnan(pose.train.quaternions).any() and 2.0 < pose.rot_floor_mrad < 4.5
    half = make_case("pose6d_partial")
    assert np.isnan(half.train.quaternions[:, 0, 0]).sum() == 9


def test_csv_round_trip_with_quaternions_and_covariates(tmp_path):
    from torchcal import Robot
    from torchcal.measure.io import load_measurements
    from torchcal.sim.cases import make_case
    for name in ("pose6d_partial", "clean_covariates", "wrist_coupling"):
        c = make_case(name)
        path = tmp_path / f"{name}.csv"
        c.train.save_csv(path)
        m = load_measurements(path, Robot.from_urdf(c.urdf, markers=c.markers))
        np.testing.assert_array_equal(m.q.numpy(), c.train.q)
        np.testing.assert_array_equal(m.positions.numpy(), c.train.positions)
        assert list(m.covariates) == list(c.train.covariates)
        for k, v in c.train.covariates.items():
            np.testing.assert_array_equal(m.covariates[k].numpy(), v)
        if c.train.quaternions is None:
            assert m.quaternions is None
            continue
        got, want = m.quaternions.numpy(), c.train.quaternions
        np.testing.assert_array_equal(np.isnan(got), np.isnan(want))  # rows without orientation stay NaN
        seen = ~np.isnan(want[..., 0])
        np.testing.assert_allclose(got[seen], want[seen], atol=1e-15)


def test_effect_beyond_geometry_of_a_constant_offset_is_nil():
    """A constant 1 mrad on joint 2 (a term on a constant column) is a zero offset: the geometric
    fit absorbs it to first order, whereas the cyclic error stays."""
    from torchcal.sim.effect_size import displacement_um
    base = PhysicalRobot(IIWA, TOOL, seed=1)
    const = PhysicalRobot(IIWA, TOOL, seed=1, joint_terms={"iiwa_joint_2": [("c", "linear", 1e-3)]})
    cyc = PhysicalRobot(IIWA, TOOL, seed=1, cyclic={"iiwa_joint_4": [(2, 1e-4, 0.0)]})
    q = base.sample_q(60)
    st = dict(covariates={"c": 1.0})
    d = displacement_um(const, base, q[30:], st, q[:30], st)
    assert d["rms_um"] > 300 and d["beyond_geometry_rms_um"] < 1.0
    d = displacement_um(cyc, base, q[30:], {}, q[:30], {})
    assert d["beyond_geometry_rms_um"] > 0.2 * d["rms_um"] > 5
