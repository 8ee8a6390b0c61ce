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

UR5E = Path(__file__).resolve().parents[1] / "urdf" / "ur5e.urdf"
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
