"""The figures reports embed: errors before and after (histogram, per axis, cumulative, against
reach), the evidence for an effect's modes, a fleet's parameter spread, a pose plan's coverage.

Every figure lays itself out with matplotlib's constrained layout, keeps its labels apart
(checked by :func:`~torchcal.report.plotting.overlapping_labels` in the tests), shows each
quantity in its display unit and returns the figure after writing it."""
from __future__ import annotations

import textwrap

import numpy as np

from torchcal.report.plotting import figure, save, subplots

__all__ = ["error_figure", "evidence_figure", "fleet_figure", "plan_figure", "readable_axis", "joint_rank",
           "leftover_figure"]

_LOG_SPAN = 30.0  # stages this far apart only show together on a logarithmic axis


def readable_axis(label: str, values) -> tuple[str, float]:
    """A plot axis ``"what [unit]"`` in a unit that suits its values: small angles in mrad or µrad
    (a joint angle stays in rad), small lengths in mm or µm, a relative growth in µm/m, seconds in
    hours for spans over two hours."""
    v = np.abs(np.asarray(values, dtype=float))
    big = float(np.nanmax(v)) if v.size and np.isfinite(v).any() else 0.0
    span = float(np.nanmax(values) - np.nanmin(values)) if v.size and np.isfinite(v).any() else 0.0
    rules = {"[rad]": [(1e-4, "[µrad]", 1e6), (0.1, "[mrad]", 1e3)], "[m]": [(1e-4, "[µm]", 1e6), (0.1, "[mm]", 1e3)],
             "[1]": [(float("inf"), "[µm/m]", 1e6)]}
    for u, options in rules.items():
        if label.endswith(u):
            for below, new, f in options:
                if big < below:
                    return label[: -len(u)] + new, f
    if label.endswith("[s]") and span > 7200:
        return label[:-3] + "[h]", 1 / 3600
    return label, 1.0


def _plain_log(ax, which: str) -> None:
    """A logarithmic axis labelled in plain text (``0.01, 0.1, 1``; 1, 2 and 5 per decade on a
    span of few decades): the default mathtext labels and the minor ticks between cost more than
    the rest of a figure's text. Call it once the data are drawn."""
    from matplotlib.ticker import LogLocator, NullLocator

    getattr(ax, f"set_{which}scale")("log")
    axis = getattr(ax, f"{which}axis")
    lo, hi = sorted(getattr(ax, f"get_{which}lim")())
    few = hi < 300 * max(lo, 1e-300)  # 2.5 decades: room for three labels in each
    axis.set_major_locator(LogLocator(base=10.0, subs=(1.0, 2.0, 5.0) if few else (1.0,), numticks=12))
    axis.set_major_formatter(lambda v, _: f"{v:g}")
    axis.set_minor_locator(NullLocator())


def _bins(e_all: np.ndarray):
    hi = float(e_all.max())
    lo = float(np.percentile(e_all[e_all > 0], 1)) if (e_all > 0).any() else hi
    log = hi > _LOG_SPAN * max(lo, 1e-12)
    return (np.geomspace(max(lo, 1e-6) * 0.8, hi * 1.05, 50) if log else np.linspace(0, hi * 1.02 + 1e-12, 40)), log


def error_figure(stages: list[tuple[str, dict]], path, title: str = "Position error", split: str = "train",
                 noise_floor_mm: float | None = None):
    """Four panels a person checks a calibration with, for several stages (``(label, details)``,
    details from :func:`~torchcal.measure.details.error_details`): the error histogram; the
    per-axis errors of every stage, before beside after; the cumulative distribution with each
    stage's 95th percentile and the noise floor; the error against the marker's distance from the
    robot base. Returns the figure (None when there is nothing to draw)."""
    data = [(lab, {k: d[k].detach().double().cpu().numpy() * (1e3 if k in ("e", "xyz") else 1.0)
                   for k in ("e", "xyz", "dist")}) for lab, d in stages if d["e"].numel()]
    if not data:
        return None
    fig, ax = subplots(2, 2, figsize=(12, 8.5), dpi=100)
    bins, log = _bins(np.concatenate([d["e"] for _, d in data]))
    colors = [f"C{i}" for i in range(len(data))]
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    keys = []  # one legend for the four panels, below them: it covers no data
    for (lab, d), c in zip(data, colors):
        p95 = float(np.percentile(d["e"], 95))
        ax[0, 0].hist(d["e"], bins=bins, alpha=0.55, color=c)
        xs = np.sort(d["e"])
        ax[1, 0].plot(xs, np.arange(1, len(xs) + 1) / len(xs), color=c)
        ax[1, 0].axvline(p95, ls=":", lw=1, color=c)
        ax[1, 1].scatter(d["dist"], d["e"], s=5, alpha=0.5, color=c)
        keys.append(Patch(facecolor=c, alpha=0.55, label=f"{lab}: mean {d['e'].mean():.3f} mm, p95 {p95:.3f} mm"))
    if log:
        for a, which in ((ax[0, 0], "x"), (ax[1, 0], "x"), (ax[1, 1], "y")):
            _plain_log(a, which)
    if noise_floor_mm is not None:
        ax[1, 0].axvline(noise_floor_mm, color="k", lw=1.2)
        keys.append(Line2D([], [], color="k", lw=1.2, label=f"noise floor {noise_floor_mm:.3f} mm"))
    _per_axis(ax[0, 1], data, colors)
    ax[0, 0].set(xlabel="Euclidean error of each observation [mm]", ylabel="observations", title="error histogram")
    ax[1, 0].set(xlabel="Euclidean position error [mm]", ylabel="fraction of observations",
                 title="cumulative distribution, 95th percentile dotted")
    ax[1, 1].set(xlabel="marker distance from the robot base [m]", ylabel="Euclidean position error [mm]",
                 title="error against reach")
    fig.suptitle(f"{title} ({split})")
    fig.legend(handles=keys, loc="outside lower center", ncols=2, fontsize=8, frameon=False)
    return save(fig, path)


def _per_axis(a, data, colors) -> None:
    """Box plots of the x, y and z errors, the stages side by side within each axis."""
    k = len(data)
    width = 0.8 / k
    for s, ((lab, d), c) in enumerate(zip(data, colors)):
        cols = [x[np.isfinite(x)] for x in d["xyz"].T]
        pos = [i + (s - (k - 1) / 2) * width for i in range(3)]
        b = a.boxplot(cols, positions=pos, widths=width * 0.85, patch_artist=True, showfliers=True,
                      flierprops={"markersize": 2})
        for patch in b["boxes"]:
            patch.set(facecolor=c, alpha=0.55)
    first = np.concatenate([x[np.isfinite(x)] for x in data[0][1]["xyz"].T])
    last = np.concatenate([x[np.isfinite(x)] for x in data[-1][1]["xyz"].T])
    if first.size and last.size:
        small = max(float(np.percentile(np.abs(last), 95)), 1e-6)
        big = float(np.abs(first).max())
        if big > _LOG_SPAN * small:  # before and after on one readable axis
            a.set_yscale("symlog", linthresh=small, linscale=1.5)
            # ticks a decade apart, the smallest at least half-way up the linear part: none crowd zero
            k0, k1 = int(np.floor(np.log10(small))), int(np.ceil(np.log10(big)))
            if 10.0 ** k0 < small / 2:
                k0 += 1
            a.set_yticks(sorted([0.0] + [s * 10.0 ** k for k in range(k0, k1 + 1) for s in (-1, 1)]))
            a.yaxis.set_major_formatter(lambda v, _: f"{v:g}")
            from matplotlib.ticker import NullLocator

            a.yaxis.set_minor_locator(NullLocator())
    a.set_xticks([0, 1, 2], ["x", "y", "z"])
    a.axhline(0, color="k", lw=0.6)
    # the stages' colours are the figure's legend, above the panels: none covers the z boxes
    a.set(ylabel="error per axis, model − measured [mm]", title="per axis, every stage (instrument frame)")


def joint_rank(label: str, order: list[str]) -> tuple[int, str]:
    """Sort key of a mode label (``joint.mode``) in the robot's joint order ``order``."""
    head = label.split(".")[0]
    return (order.index(head) + 1 if head in order else (0 if head in ("base", "uniform") else len(order) + 1)), label


def evidence_figure(name: str, ev: dict, path, joint_order: list[str]):
    """Per mode (panels in joint order, ``joint_order``: the robot's joints): the partial
    residual against the mode's physical signature with the fitted mode overlaid; a mode without
    an independent signature says so in its panel. Returns the figure (None when empty)."""
    if not ev:
        return None
    keys = sorted(ev, key=lambda k: joint_rank(k, joint_order))
    cols = min(3, len(keys))
    rows = (len(keys) + cols - 1) // cols
    fig, axes = subplots(rows, cols, figsize=(4.4 * cols, 3.7 * rows), dpi=100, squeeze=False)
    for ax, k in zip(axes.flat, keys):
        e = ev[k]
        xl, fx = readable_axis(e["xlabel"], e["x"])
        yl, fy = readable_axis(e["ylabel"], list(e["residual"]) + list(e["fitted"]))
        x = np.asarray(e["x"]) * fx
        ax.scatter(x, np.asarray(e["residual"]) * fy, s=6, alpha=0.5, label="partial residual")
        ax.scatter(x, np.asarray(e["fitted"]) * fy, s=4, alpha=0.9, label="fitted")
        ax.set_xlabel(textwrap.fill(xl, 48), fontsize=8)
        ax.set_ylabel(yl, fontsize=8)
        ax.tick_params(labelsize=7)
        head = f"{k} (r = {e['r']:.2f})" + ("" if e.get("independent", True) else "\nno independent signature")
        ax.set_title(textwrap.fill(head, 44) if "\n" not in head else head, fontsize=9)
    for ax in list(axes.flat)[len(keys):]:
        ax.axis("off")
    axes[0][0].legend(fontsize=7)
    notes = sorted({e["note"] for e in ev.values() if e.get("note")})
    width = min(110, int(14 * 4.4 * cols))  # characters of a 10 pt line across the figure
    fig.suptitle("\n".join([f"evidence for {name}"] + [textwrap.fill(n, width) for n in notes]), fontsize=10)
    return save(fig, path)


def fleet_figure(rows: list[dict], path, z_threshold: float, title: str):
    """Each parameter's spread over the fleet, one row per parameter: every robot's distance from
    its siblings in their standard deviations (z), the flag bound, and the flagged robots marked
    and named. ``rows``: ``{name, z (n,), robots (n,), flagged: set, z_needed}``."""
    if not rows:
        return None
    n = len(rows)
    fig, ax = subplots(figsize=(10, max(3.0, 0.28 * n + 1.6)), dpi=100)
    # the x range holds every robot and every bound drawn: a bound beyond the edge would make a robot
    # near the edge look flagged
    lim = max([z_threshold * 1.6] + [float(np.nanmax(np.abs(r["z"]))) * 1.1 for r in rows if len(r["z"])]
              + [float(r["z_needed"]) * 1.1 for r in rows if r.get("z_needed") is not None])
    named = 0
    for i, r in enumerate(rows):
        z = np.asarray(r["z"], dtype=float)
        y = n - 1 - i
        hit = np.array([rb in r["flagged"] for rb in r["robots"]], dtype=bool)
        ax.scatter(z[~hit], np.full((~hit).sum(), y), s=10, color="0.45", alpha=0.7, zorder=2)
        ax.scatter(z[hit], np.full(hit.sum(), y), s=40, color="C3", marker="D", zorder=3,
                   label="flagged robot" if named == 0 and hit.any() else None)
        for j in np.nonzero(hit)[0]:
            ax.annotate(r["robots"][j], (z[j], y), xytext=(6 if z[j] >= 0 else -6, 4), textcoords="offset points",
                        ha="left" if z[j] >= 0 else "right", fontsize=7, color="C3")
            named += 1
        if r.get("z_needed") is not None:
            ax.plot([-r["z_needed"], r["z_needed"]], [y, y], "|", color="C1", ms=9, mew=1.5,
                    label="flag bound of the parameter" if i == 0 else None)
    for s in (-z_threshold, z_threshold):
        ax.axvline(s, color="C1", ls="--", lw=0.8)
    ax.set_yticks(range(n), [r["name"] for r in reversed(rows)], fontsize=7)
    ax.set_xlim(-lim, lim)
    ax.set_ylim(-0.8, n - 0.2)
    ax.set_xlabel("distance from the robot's siblings in their standard deviations (z)")
    ax.set_title(title, fontsize=10)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)
    return save(fig, path)


def plan_figure(q: np.ndarray, limits: tuple[np.ndarray, np.ndarray], joint_names: list[str], points: np.ndarray,
                path, box: list[float] | None = None, title: str = "pose plan"):
    """What a plan covers: per joint (in joint order) its range and the selected values; the
    markers' positions in the robot base frame from above and from the side, with the working
    volume when one was given. ``q (S, dof)`` rad / m, ``points (S, M, 3)`` m."""
    dof = q.shape[1]
    fig = figure((13, max(4.2, 0.42 * dof + 1.8)), dpi=100)
    gs = fig.add_gridspec(1, 3, width_ratios=[1.3, 1, 1])
    a = fig.add_subplot(gs[0])
    lo, hi = limits
    for j in range(dof):
        y = dof - 1 - j
        span = max(float(hi[j] - lo[j]), 1e-12)
        a.plot([0, 1], [y, y], color="0.8", lw=8, solid_capstyle="butt")
        a.plot((q[:, j] - lo[j]) / span, np.full(q.shape[0], y), "|", color="C0", ms=12)
        used = float(q[:, j].max() - q[:, j].min()) / span
        a.text(1.02, y, f"{100 * used:.0f} %", va="center", fontsize=7)
    a.set_yticks(range(dof), list(reversed(joint_names)), fontsize=8)
    a.set_xlim(0, 1.12)
    a.set_xticks([0, 0.5, 1], ["lower limit", "middle", "upper limit"], fontsize=8)
    a.set_title("joint ranges: selected values, share of the range spanned", fontsize=9)
    pts = points.reshape(-1, 3)
    for k, (i, j, name) in enumerate(((0, 1, "from above: x, y"), (0, 2, "from the side: x, z"))):
        b = fig.add_subplot(gs[k + 1])
        b.scatter(pts[:, i], pts[:, j], s=8, color="C0", alpha=0.7)
        if box is not None:
            x0, x1, y0, y1 = box[2 * i], box[2 * i + 1], box[2 * j], box[2 * j + 1]
            b.plot([x0, x1, x1, x0, x0], [y0, y0, y1, y1, y0], color="C1", lw=1, label="working volume")
            b.legend(fontsize=7)
        b.set_aspect("equal", adjustable="datalim")
        b.set(xlabel=f"{'xyz'[i]} [m]", ylabel=f"{'xyz'[j]} [m]")
        b.set_title(f"marker positions {name} (robot base)", fontsize=9)
    fig.suptitle(title, fontsize=10)
    return save(fig, path)


def leftover_figure(associations: list, path):
    """What the residual still follows: for each of the strongest signals, the residual component it
    explains best against it (mm), titled with its share of the residual variance (R²)."""
    if not associations:
        return None
    fig, axes = subplots(1, len(associations), figsize=(max(3.4 * len(associations), 5.0), 3.4), dpi=110,
                         squeeze=False)
    for ax, a in zip(axes[0], associations):
        ax.scatter(a.x, [v * 1e3 for v in a.y], s=6, alpha=0.6)
        # a signal's name can be long (a covariate, joint.mode): wrapped to its panel's width
        ax.set_xlabel(textwrap.fill(a.signal, 34), fontsize=8)
        ax.set_ylabel(f"residual {a.axis} [mm]", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.set_title(f"R² = {a.r2:.3f}", fontsize=9)
    fig.suptitle("what the residual still follows", fontsize=10)
    return save(fig, path)
