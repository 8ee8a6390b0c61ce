"""Shapes a parameter may take along a driver: each a column ``f(x)`` per row, scaled by one
coefficient, with knots and break points chosen from the training data, never by hand.

Tags (the strings a saved model carries):

* ``lin``: ``x − x̄`` (a rate);
* ``quad``: ``((x − x̄) / h)²``, ``h`` the half range (a bow); ``cube``: its cube (an S, a
  saturation's odd part);
* ``spl<k>``: ``((x − k) / h)²₊`` a quadratic spline piece from the knot ``k`` on (smooth);
* ``sin<n>`` / ``cos<n>``: harmonic ``n`` of an angle (periodic);
* ``step<k>``: ``1`` from ``x ≥ k`` on (a set-up changed at ``k`` and stayed);
* ``win<a>@<b>``: ``1`` for ``a ≤ x < b`` (a time or row driver: a set-up changed at ``a`` and
  changed back at ``b``, a tool swapped for a while);
* ``exp<τ>@<x₀>``: ``exp(−(x − x₀)₊ / τ)`` (a first-order settling from the session's start ``x₀``
  with time constant ``τ``: a tracker or a frame warming up, a creep dying away);
* ``psin<P>@<x₀>`` / ``pcos<P>@<x₀>``: ``sin`` / ``cos`` of ``2π (x − x₀) / P`` (a time driver: a
  frame or a part that cycles with the room, air conditioning or a machine nearby, with a period
  ``P`` nobody logged; both phases together are one cycle of any phase);
* ``odd2`` / ``odd3``: ``(x / h)·|x / h|`` / ``(x / h)³``, odd about zero, not about the mean (a torque
  driver: a stiffness that grows or softens with the load a joint carries, whichever its sign);
* ``hinge<k>``: ``(x − k)₊`` (a slope that changes at ``k``);
* ``sat<k>``: ``x`` clipped to ``±k`` (a torque driver: a stiffness that changes beyond ``±k``, a
  dead zone or a saturation about zero load);
* ``lvl=<level>``: ``1`` where a text column reads ``level`` (one value per level).

Knots of the smooth and piecewise shapes sit at quantiles of the training values; step breaks
at the midpoints between consecutive distinct training values (every place a step can be seen);
settling time constants on a geometric grid of the training span (:func:`settle_tags`); cycles on
a periodogram's grid of frequencies (:func:`period_frequencies`).
"""
from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["shape_column", "smooth_tags", "hinge_tags", "knee_tags", "harmonic_tags", "step_breaks", "settle_tags",
           "window_tag", "window_parts", "window_grid", "break_words", "WINDOW",
           "grid_tags", "screen_tags", "settle_parts", "period_parts", "period_tag", "period_frequencies",
           "cycle_columns", "cycle_label", "cycle_period", "UNIT", "PERIODIC", "HARMONICS", "KNOT_QUANTILES",
           "HINGE_QUANTILES", "SETTLE_STEPS", "MAX_CYCLES", "PERIOD_OVERSAMPLE"]

HARMONICS = 2                      # highest harmonic of an angle driver
KNOT_QUANTILES = (1 / 3, 2 / 3)    # knots of the quadratic spline, as quantiles of the training values
HINGE_QUANTILES = (0.2, 0.4, 0.6, 0.8)  # break points of the piecewise-linear shapes
# settling time constants: the training span over 2^(k/4), k = 2 … SETTLE_STEPS + 1 (span/1.4 to
# span/76, each 19 % from the next); a slower settling is a rate or a bow, a faster one a step
SETTLE_STEPS = 24
# cycles of a time driver: from one over the training span up to MAX_CYCLES (and at most a quarter
# of the distinct times: a cycle needs rows at each of its phases), PERIOD_OVERSAMPLE frequencies
# per 1/span, a periodogram's grid (between neighbours the phase drifts by 1/16 of a cycle over the
# whole span; the best one is refined further by the screening)
MAX_CYCLES = 16
PERIOD_OVERSAMPLE = 8
PERIODIC = ("psin", "pcos")
WINDOW = "win"
# a parameter's own column, 1 on every row: never a term of a model (a constant is the parameter
# itself), but what every shape multiplies, row by row, so that a search over many shapes of one
# parameter takes its column once
UNIT = "one"


def _num(tag: str, prefix: str) -> float:
    return float(tag[len(prefix):])


def shape_column(tag: str, x: Tensor, centre: float, half: float) -> Tensor:
    """``(N,)`` the shape ``tag`` of driver values ``x (N,)`` (``centre``: the training mean;
    ``half``: half the training range, > 0). Level tags take the 0/1 indicator as ``x``."""
    h = half if half > 0 else 1.0
    if tag == "lin":
        return x - centre
    if tag == "quad":
        return ((x - centre) / h) ** 2
    if tag == "cube":
        return ((x - centre) / h) ** 3
    if tag == "odd2":
        return (x / h) * (x / h).abs()
    if tag == "odd3":
        return (x / h) ** 3
    if tag.startswith("lvl="):
        return x
    if tag == UNIT:
        return torch.ones_like(x)
    if tag.startswith(PERIODIC):
        phase, period, x0 = period_parts(tag)
        return cycle_columns(x, [1.0 / period], x0)[:, 0 if phase == "sin" else 1]
    for p in ("sin", "cos"):
        if tag.startswith(p):
            n = int(tag[3:])
            return torch.sin(n * x) if p == "sin" else torch.cos(n * x)
    if tag.startswith("spl"):
        return (torch.clamp(x - _num(tag, "spl"), min=0) / h) ** 2
    if tag.startswith("step"):
        return (x >= _num(tag, "step")).to(x.dtype)
    if tag.startswith(WINDOW):
        a, b = window_parts(tag)
        return ((x >= a) & (x < b)).to(x.dtype)
    if tag.startswith("exp"):
        tau, x0 = settle_parts(tag)
        return torch.exp(-torch.clamp(x - x0, min=0) / tau)
    if tag.startswith("hinge"):
        return torch.clamp(x - _num(tag, "hinge"), min=0)
    if tag.startswith("sat"):
        k = _num(tag, "sat")
        return torch.clamp(x, min=-k, max=k)
    raise ValueError(f"unknown shape {tag!r}; shapes: lin, quad, cube, odd2, odd3, spl<k>, sin<n>, cos<n>, step<k>, "
                     "win<a>@<b>, exp<tau>@<x0>, psin<P>@<x0>, pcos<P>@<x0>, hinge<k>, sat<k>, lvl=<level>")


def _quantiles(x: Tensor, qs) -> list[float]:
    v = torch.quantile(x.double(), torch.tensor(list(qs), dtype=torch.float64, device=x.device))
    return [float(f"{float(a):.6g}") for a in v]


def smooth_tags(x: Tensor) -> list[str]:
    """A spline: the bow, the S and one quadratic piece from each knot (:data:`KNOT_QUANTILES`)."""
    return ["quad", "cube"] + [f"spl{k:.6g}" for k in dict.fromkeys(_quantiles(x, KNOT_QUANTILES))]


def hinge_tags(x: Tensor) -> list[str]:
    """Piecewise-linear pieces from break points at :data:`HINGE_QUANTILES`."""
    return [f"hinge{k:.6g}" for k in dict.fromkeys(_quantiles(x, HINGE_QUANTILES))]


def knee_tags(kind: str, x: Tensor, n: int = 39) -> list[str]:
    """Every knee a piecewise-linear shape can have on training values ``x``: hinges at ``n``
    evenly spaced quantiles, and for a torque clips at as many quantiles of ``|x|``."""
    qs = [(i + 1) / (n + 1) for i in range(n)]
    out = [f"hinge{k:.6g}" for k in dict.fromkeys(_quantiles(x, qs))]
    if kind == "torque":
        out += [f"sat{k:.6g}" for k in dict.fromkeys(_quantiles(x.abs(), qs)) if k > 0]
    return out


def harmonic_tags() -> list[str]:
    return [f"{f}{n}" for n in range(1, HARMONICS + 1) for f in ("sin", "cos")]


def step_breaks(x: Tensor, min_side: int = 3) -> list[float]:
    """Every break a step can sit at: midpoints between consecutive distinct training values,
    with at least ``min_side`` rows on each side (a step seen by fewer rows is an outlier)."""
    v = torch.unique(x.double())
    if v.numel() < 2 * min_side:
        return []
    mids = (v[:-1] + v[1:]) / 2
    counts = torch.tensor([int((x.double() < m).sum()) for m in mids.tolist()])
    ok = (counts >= min_side) & (counts <= x.numel() - min_side)
    return [float(f"{float(m):.10g}") for m in mids[ok]]


def window_tag(a: float, b: float) -> str:
    """The tag of the window from the break ``a`` to the break ``b``."""
    return f"{WINDOW}{a:.10g}@{b:.10g}"


def window_parts(tag: str) -> tuple[float, float]:
    """``win<a>@<b>`` -> ``(a, b)`` in the driver's unit."""
    a, _, b = tag[len(WINDOW):].partition("@")
    return float(a), float(b)


def break_words(key: str) -> str:
    """A break in words: ``row~step149.5`` -> ``row 149.5``, ``time~win20@60`` -> ``time 20 to 60``."""
    col, _, tag = key.partition("~")
    if tag.startswith(WINDOW):
        a, b = window_parts(tag)
        return f"{col} {a:.10g} to {b:.10g}"
    return f"{col} {tag[4:]}" if tag.startswith("step") else f"{col} {tag}"


def window_grid(x: Tensor, min_inside: int = 3) -> tuple[list[float], Tensor]:
    """The breaks of :func:`step_breaks` on training values ``x`` and a ``(B, B)`` mask of the windows
    ``[a, b)`` between two of them (``a`` before ``b``) that hold at least ``min_inside`` values (a
    change seen by fewer rows is an outlier)."""
    b = step_breaks(x)
    if not b:
        return b, torch.zeros(0, 0, dtype=torch.bool)
    at = torch.tensor(b, dtype=torch.float64, device=x.device)
    below = (x.double()[:, None] < at[None]).sum(0)  # values before each break
    return b, (below[None] - below[:, None]) >= min_inside


def settle_parts(tag: str) -> tuple[float, float]:
    """``exp<τ>@<x₀>`` -> ``(τ, x₀)`` in the driver's unit."""
    tau, _, x0 = tag[3:].partition("@")
    return float(tau), float(x0)


def settle_tags(x: Tensor, n: int = SETTLE_STEPS) -> list[str]:
    """First-order settlings from the first training value on, with time constants ``span / 2^(k/4)``,
    ``k = 2 … n + 1`` (none when the values do not vary)."""
    lo, hi = float(x.min()), float(x.max())
    if not hi > lo:
        return []
    return [f"exp{(hi - lo) / 2 ** (k / 4):.6g}@{lo:.10g}" for k in range(2, n + 2)]


def period_parts(tag: str) -> tuple[str, float, float]:
    """``psin<P>@<x₀>`` -> ``("sin", P, x₀)`` (``pcos``: ``"cos"``), in the driver's unit."""
    period, _, x0 = tag[4:].partition("@")
    return tag[1:4], float(period), float(x0)


def cycle_columns(x: Tensor, freqs: list[float], x0: float) -> Tensor:
    """``(len(x), 2F)``: the sine and cosine of ``2π f (x − x₀)`` for each frequency ``f`` of ``freqs``
    (cycles per driver unit), pairwise (the shapes ``psin`` and ``pcos``)."""
    a = (2 * torch.pi) * (x - x0)[:, None] * torch.tensor(freqs, dtype=x.dtype, device=x.device)[None]
    return torch.stack([torch.sin(a), torch.cos(a)], -1).flatten(1)


def cycle_label(tag: str) -> str:
    """``cyc<P>@<x₀>``: the label of the mode that holds both phases of the cycle of ``tag``."""
    return "cyc" + tag[4:]


def cycle_period(label: str) -> float:
    """The period of a ``cyc<P>@<x₀>`` mode label (:func:`cycle_label`)."""
    return float(label[3:].partition("@")[0])


def period_tag(phase: str, period: float, x0: float) -> str:
    """The tag of one phase (``"sin"`` or ``"cos"``) of a cycle of ``period`` from ``x0``."""
    return f"p{phase}{period:.8g}@{x0:.10g}"


def period_frequencies(x: Tensor) -> list[float]:
    """Frequencies (cycles per driver unit) of the cycles a time driver with training values ``x``
    is searched for (:data:`MAX_CYCLES`, :data:`PERIOD_OVERSAMPLE`); none when too few distinct
    values can show one."""
    lo, hi = float(x.min()), float(x.max())
    cycles = min(MAX_CYCLES, int(torch.unique(x.double()).numel()) // 4)
    if not hi > lo or cycles < 1:
        return []
    span = hi - lo
    return [k / (PERIOD_OVERSAMPLE * span) for k in range(PERIOD_OVERSAMPLE, cycles * PERIOD_OVERSAMPLE + 1)]


def grid_tags(kind: str, x: Tensor) -> list[str]:
    """Every shape on a grid a driver of ``kind`` (:func:`~torchcal.effects.drivers.driver_kind`) can
    take on its training values ``x``: for time and rows, a step at every break and a settling
    from the session's start (a frame that drifts until it settles); for the others, knees
    (:func:`knee_tags`)."""
    if kind in ("time", "row"):
        return [f"step{b:.10g}" for b in step_breaks(x)] + settle_tags(x)
    return knee_tags(kind, x)


def screen_tags(kind: str, revolute: bool) -> list[str]:
    """The low-order shapes a driver is screened with before its richer shapes are tried: a rate,
    a bow and an S (and the first harmonic of an angle)."""
    return ["lin", "quad", "cube"] + (["sin1", "cos1"] if kind == "q" and revolute else [])
