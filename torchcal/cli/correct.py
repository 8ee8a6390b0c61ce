"""``torchcal correct``: corrected joint commands for a CSV of targets, from a saved model.

Targets CSV (header row, one target per row):

* ``x, y, z``: target position (m), in the robot's base frame (``--frame base``, the default) or
  in the instrument frame the model was calibrated in (``--frame instrument``) (required);
* ``qw, qx, qy, qz``: target orientation as a unit quaternion (optional; all four or none;
  without them the targets are positions only);
* a column per joint (the model's joint names, rad / m): IK start for that target (optional;
  choose the branch, e.g. elbow up). Without them IK starts mid-range with random restarts;
* a column per covariate the model needs (``model.required_covariates``, e.g. ``temperature``); a
  level of a text column (``tool=probe``) may come from the text column itself (``tool``, one level
  per row, as the training file had it), and a level of a column of codes (``tool_id=2``) from the
  numeric column (``tool_id``).

Output CSV: the target columns, the corrected command per joint (``nan`` where the target failed), ``converged`` (1/0),
``reason`` (``ok``, ``unreachable``, ``joint_limits``, ``singular``, ``not_converged``,
``max_outer``), ``predicted_error_mm`` and, for pose targets, ``predicted_rot_error_mrad``.
Numbers are written with full float64 precision (``repr``). The command exits with status 3
when any target fails (``--allow-failures``: 0), and never overwrites a file (``--force``), least
of all the targets file.
"""
from __future__ import annotations

import argparse
import csv
import io
import math
import sys

import torch
from torch import Tensor

from torchcal.cli.common import add_common, inputs_of, int_at_least, positive_float
from torchcal.deploy.correct import Corrector
from torchcal.measure.io import UnitsError, read_csv
from torchcal.measure.levels import LEVEL_SEP, code_indicator
from torchcal.outputs import atomic_write_text, check_out_file
from torchcal.deploy.persist import load
from torchcal.kinematics.transforms import matrix_to_quat, quat_to_matrix

__all__ = ["add_correct_parser", "correct_main", "read_targets", "write_corrections"]

_POS, _QUAT = ("x", "y", "z"), ("qw", "qx", "qy", "qz")


def read_targets(path, robot, covariates: list[str] | None = None):
    """Read a targets CSV (see the module docstring).

    Returns:
        ``(targets, q0, cov, has_quat)``: ``targets (N, 4, 4)`` or ``(N, 3)`` (m), ``q0 (N, dof)``
        or ``None``, ``cov`` dict ``name -> (N,)`` or ``None``, and whether orientations were given.
    """
    header, rows = read_csv(path, "targets file")
    if not rows:
        raise ValueError(f"{path}: needs a header row (x,y,z[,qw,qx,qy,qz]) and at least one target row")
    col = {h: i for i, h in enumerate(header)}
    lines = rows.lines  # the file's line of each row (blank lines are no rows)
    missing = [c for c in _POS if c not in col]
    if missing:
        raise ValueError(f"{path}: missing column(s) {missing}; the targets need x,y,z in metres "
                         f"(and optionally qw,qx,qy,qz); found {header}")
    nq = [c for c in _QUAT if c in col]
    if nq and len(nq) != 4:
        raise ValueError(f"{path}: give all four quaternion columns qw,qx,qy,qz or none; found {nq}")

    def num(name: str) -> Tensor:
        vals = []
        for i, r in zip(lines, rows):
            cell = r[col[name]].strip()
            try:
                v = float(cell)
            except ValueError:
                raise ValueError(f"{path}, line {i}, column {name!r}: {cell!r} is not a number") from None
            if not math.isfinite(v):
                raise ValueError(f"{path}, line {i}, column {name!r}: {cell!r} is not finite")
            vals.append(v)
        return torch.tensor(vals, dtype=robot.dtype, device=robot.device)

    def level(name: str, value: str) -> Tensor:
        """The level ``value`` of the text column ``name``, or of a numeric column of codes (``2`` or ``2.0``)."""
        cells = [r[col[name]].strip() for r in rows]
        try:
            return code_indicator(torch.tensor([float(c) for c in cells], dtype=robot.dtype, device=robot.device),
                                  value)
        except ValueError:  # text
            return torch.tensor([float(c == value) for c in cells], dtype=robot.dtype, device=robot.device)

    p = torch.stack([num(c) for c in _POS], -1)
    if float(p.abs().max()) > 50:
        raise UnitsError(f"{path}: target positions reach {float(p.abs().max()):.4g}, which looks like "
                         "millimetres; torchcal expects metres: divide by 1000")
    has_quat = bool(nq)
    if has_quat:
        qt = torch.stack([num(c) for c in _QUAT], -1)
        n = qt.norm(dim=-1)
        if bool(((n - 1).abs() > 1e-3).any()):
            i = int(torch.nonzero((n - 1).abs() > 1e-3)[0])
            raise ValueError(f"{path}, line {lines[i]}: quaternion norm {float(n[i]):.4f}, expected 1 "
                             "(qw,qx,qy,qz of a unit quaternion)")
        T = torch.eye(4, dtype=robot.dtype, device=robot.device).repeat(p.shape[0], 1, 1)
        T[:, :3, :3] = quat_to_matrix(qt)
        T[:, :3, 3] = p
        targets = T
    else:
        targets = p
    js = [j for j in robot.joint_names if j in col]
    if js and len(js) != robot.dof:
        raise ValueError(f"{path}: IK start columns must name every joint {robot.joint_names}; found only {js}")
    q0 = torch.stack([num(j) for j in robot.joint_names], -1) if js else None
    cov = None
    if covariates:
        # a level of a text column the model reads (``tool=probe``) comes from the text column itself
        # (``tool``), as the training file gave it, or from its own 0/1 column
        text = {c: c.split(LEVEL_SEP, 1) for c in covariates if c not in col and LEVEL_SEP in c}
        miss = [c for c in covariates if c not in col and (c not in text or text[c][0] not in col)]
        if miss:
            raise ValueError(f"{path}: the model needs covariate column(s) {miss}"
                             + ("; a level (<column>=<level>) may come from its text column <column>"
                                if any(LEVEL_SEP in c for c in miss) else ""))
        cov = {c: (level(*text[c]) if c in text else num(c)) for c in covariates}
    return targets, q0, cov, has_quat


def write_corrections(path, targets: Tensor, res, robot) -> None:
    """Write targets, corrected commands and status (see the module docstring)."""
    pose = targets.ndim == 3
    header = list(_POS) + (list(_QUAT) if pose else []) + list(robot.joint_names) + \
        ["converged", "reason", "predicted_error_mm"] + (["predicted_rot_error_mrad"] if pose else [])
    p = targets[:, :3, 3] if pose else targets
    qt = matrix_to_quat(targets[:, :3, :3]) if pose else None
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(header)
    for i in range(p.shape[0]):
        row = [repr(float(v)) for v in p[i]]
        if pose:
            row += [repr(float(v)) for v in qt[i]]
        # a failed target's commands are not sent anywhere: no real-looking values in their place
        row += [repr(float(v)) if bool(res.converged[i]) else "nan" for v in res.q[i]]
        row += [int(bool(res.converged[i])), res.reason[i], repr(float(res.predicted_error_mm[i]))]
        if pose:
            row.append(repr(float(res.predicted_rot_error_mrad[i])))
        w.writerow(row)
    atomic_write_text(path, buf.getvalue())


def add_correct_parser(sub) -> argparse.ArgumentParser:
    """Add the ``correct`` sub-command to an ``argparse`` sub-parser set (``ap.add_subparsers()``)."""
    c = sub.add_parser("correct", help="corrected joint commands for target poses, from a saved model",
                       description="Corrected joint commands for a CSV of targets (x,y,z in m, optional "
                                   "qw,qx,qy,qz, optional per-joint IK start columns), using a model saved "
                                   "by torchcal.save.")
    c.add_argument("--model", required=True, help="model directory (model.json, tensors.safetensors, robot.urdf)")
    c.add_argument("--targets", required=True,
                   help="targets CSV: x,y,z (m) [, qw,qx,qy,qz] [, joint columns = IK start]")
    c.add_argument("--out", required=True, help="output CSV: targets, corrected joint commands, status")
    c.add_argument("--frame", choices=Corrector.FRAMES, default="base",
                   help="frame of the targets: the robot's base frame (default) or the instrument frame the model "
                        "was calibrated in")
    c.add_argument("--tol-mm", type=positive_float, default=1e-3, help="tolerance on the predicted position error (mm)")
    c.add_argument("--tol-mrad", type=positive_float, default=1e-3,
                   help="tolerance on the predicted rotation error (mrad)")
    c.add_argument("--max-outer", type=int_at_least(1), default=10, help="correction rounds at most")
    c.add_argument("--allow-failures", action="store_true",
                   help="exit with status 0 even when some targets fail (default: status 3)")
    add_common(c, units=False)
    c.set_defaults(func=correct_main)
    return c


def correct_main(a: argparse.Namespace, argv: list[str] | None = None) -> int:
    """Run ``torchcal correct`` with parsed arguments (see :func:`add_correct_parser`)."""
    check_out_file(a.out, a.force, inputs=inputs_of(a))
    torch.set_num_threads(a.threads)
    model = load(a.model)
    targets, q0, cov, _ = read_targets(a.targets, model.robot, model.required_covariates)
    res = Corrector(model, tol_mm=a.tol_mm, tol_mrad=a.tol_mrad, max_outer=a.max_outer,
                    frame=a.frame).correct(targets, q0, cov)
    write_corrections(a.out, targets, res, model.robot)
    n, ok = len(res.reason), int(res.converged.sum())
    fails = {k: v for k, v in res.summary().items() if k != "ok"}
    print(f"{model.robot.name}: corrected {ok}/{n} targets ({a.frame} frame)"
          + (f"; failed: {fails}" if fails else "") + f"; wrote {a.out}")
    if ok < n and not a.allow_failures:
        print(f"torchcal correct: {n - ok} target(s) failed (rows with converged = 0 in {a.out}); "
              "pass --allow-failures to exit with status 0 anyway", file=sys.stderr)
        return 3
    return 0
