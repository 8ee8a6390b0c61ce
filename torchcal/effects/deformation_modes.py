"""The catalogue of elastic deformation modes a robot offers (:class:`~torchcal.effects.deformation.GravityDeformation`
chooses among them): where each mode sits, what it turns or shifts, and which component of the gravity
wrench drives it."""
from __future__ import annotations

import torch

__all__ = ["catalog"]

_AXES = "xyz"


def catalog(robot, joints: list[str]) -> list[dict]:
    """Every mode this robot offers: label, frame index (0 = base, j+1 = robot.joints[j]),
    'rot'/'shift', the projector ``P`` (frame axes) that picks the driving wrench component(s),
    the actuated column a twist acts on, a sign-bearing direction for single-axis modes, words.

    Plane modes (``base.tilt``, ``<joint>.bend``) have one compliance for both directions of a
    plane: a floor or a round bearing is as soft one way as the other, and one parameter then
    says what two per-axis ones would."""
    dt = dict(dtype=robot.dtype, device=robot.device)
    eye = torch.eye(3, **dt)
    outer = lambda d: d[:, None] * d[None, :]  # noqa: E731
    # gravity is along base z: no twist about z, and the base force does not vary
    cat = [dict(label="base.tilt", frame=0, kind="rot", P=eye - outer(eye[2]), dir=None, dof=None,
                words="the base tilts on its floor or mount (alike about x and y)")]
    cat += [dict(label=f"base.tilt_{a}", frame=0, kind="rot", P=outer(eye[i]), dir=eye[i], dof=None,
                 words=f"the base tilts about {a}") for i, a in enumerate("xy")]
    by_joint = {jt.name: (j, jt) for j, jt in enumerate(robot.joints)}
    for name in joints:
        j, jt = by_joint[name]
        a = torch.as_tensor(jt.axis, **dt)
        order = sorted(range(3), key=lambda i: abs(float(a[i])))  # frame axes least along the axis first
        u = eye[order[0]] - (eye[order[0]] @ a) * a
        u = u / u.norm()
        v = eye[order[1]] - (eye[order[1]] @ a) * a - (eye[order[1]] @ u) * u
        v = v / v.norm()
        if jt.type in ("revolute", "continuous"):
            cat.append(dict(label=f"{name}.twist", frame=j + 1, kind="rot", P=outer(a), dir=a,
                            dof=robot.joint_names.index(name),
                            words=f"{name} twists about its axis (joint compliance)"))
        else:
            cat.append(dict(label=f"{name}.roll", frame=j + 1, kind="rot", P=outer(a), dir=a, dof=None,
                            words=f"{name} rolls about its sliding axis"))
        cat.append(dict(label=f"{name}.bend", frame=j + 1, kind="rot", P=eye - outer(a), dir=None, dof=None,
                        words=f"{name} bends sideways (alike about both axes across it)"))
        for i, d in ((order[0], u), (order[1], v)):
            cat.append(dict(label=f"{name}.bend_{_AXES[i]}", frame=j + 1, kind="rot", P=outer(d), dir=d,
                            dof=None, words=f"{name} bends about its {_AXES[i]} axis"))
        if jt.type in ("revolute", "continuous"):
            # the same across the axis, in the frame before the joint turns: a bearing seat in
            # the parent link, whose soft direction does not turn with the joint
            for i, d in ((order[0], u), (order[1], v)):
                cat.append(dict(label=f"{name}.seat_{_AXES[i]}", frame=j + 1, kind="rot", P=outer(d), dir=d,
                                dof=None, seat=robot.joint_names.index(name), axis=a,
                                words=f"the seat of {name} bends about its {_AXES[i]} axis (joint frame "
                                      "before the joint turns)"))
        for i in range(3):
            cat.append(dict(label=f"{name}.shift_{_AXES[i]}", frame=j + 1, kind="shift", P=outer(eye[i]),
                            dir=eye[i], dof=None,
                            words=f"{name} gives way along its {_AXES[i]} axis under the gravity force"))
    # kinds from the commonest to the rarest, each from the base outwards: where the data
    # cannot tell two modes apart (co-located shoulder frames: one joint's twist is another's
    # bend), the selection takes the earlier, and gear compliance beats bearing bending
    rank = lambda c: (0 if c["frame"] == 0 else 1 if c["dof"] is not None else  # noqa: E731
                      2 if c["dir"] is None else 3 if c["kind"] == "rot" and "seat" not in c else
                      4 if c["kind"] == "rot" else 5)
    return sorted(cat, key=rank)
