"""Screening a large family before its selection: which (parameter, driver) pairs explain anything
at the low-order level, and which step breaks fit best, so that only those are expanded into every
shape and judged by the cross-validated rule.

The space of :class:`~torchcal.effects.anydriver.ParameterDrivers` is parameters × drivers ×
shapes: thousands of columns on a 6-joint arm. Around the current model the residual ``r`` is
linear in every column; beyond what the model's own free parameters explain (projected off their
Jacobian, with the fit's IRLS weights), a pair's low-order columns (a rate and a bow, the first
harmonic of an angle, the levels of a text column) explain ``‖P r‖²``, which on pure noise of
per-axis σ is χ² with as many degrees of freedom as columns. A pair is kept when that is
improbable at the level :data:`ALPHA` shared among all pairs (Bonferroni), the strongest
:data:`MAX_PAIRS` at most; a driver none of whose pairs passes is not expanded at all. For a time
or row driver, every break a step can sit at and every time constant of a settling are scored the
same way, one column each, and the best :data:`~torchcal.effects.anydriver.MAX_STEPS` are offered;
so are the knees of the
piecewise-linear shapes of the other drivers (hinges, and clips of a torque, on a fine grid).

A time or row driver is also scanned for a set-up that changed during the session: a step at every
break, and a window between every two (a change and its return: a tool swapped for a while), which
the low-order shapes see only in part (a window's middle is half a bow, and once a bow is taken
nothing low-order is left of it). Per pair each column explains what it explains (χ² with 1 degree
of freedom on noise), all of them from the step columns' products (a window is the difference of two
steps); the best, judged at the level shared by the steps and windows (Bonferroni), is one more test.
A kept pair is offered its best windows (:data:`MAX_WINDOWS`) beside its best steps. A long session's
breaks are thinned for the scan (:data:`SCAN_BREAKS`), the best windows' ends refined on every break.

A time driver is also searched for a cycle (a frame that swings with the air conditioning), which
no low-order shape sees: per pair, each frequency of a periodogram's grid explains what its sine and
cosine together explain (χ² with 2 degrees of freedom on noise), and the best frequency, judged at
the level shared by the grid (Bonferroni), is one more test of the screening. A kept pair is offered
its best cycle, the frequency refined between the grid's neighbours.

Screening only prunes: what is kept is still chosen by the cross-validated rule, at the Bonferroni
threshold of the whole space (every shape of every pair), so a pair kept by chance is not accepted
by chance.
"""
from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from torchcal.effects.anydriver import MAX_STEPS
from torchcal.effects.anydriver_space import breaks, cycles, expanded, space_size
from torchcal.effects.drivers import driver_kind, driver_values
from torchcal.effects.shapes import PERIOD_OVERSAMPLE, UNIT, cycle_columns, period_tag, window_grid, window_tag
from torchcal.measure.stats import chi2_sf

__all__ = ["screen_family", "fitted_payload", "step_window_power", "break_sums", "ALPHA", "MAX_PAIRS", "MAX_WINDOWS", "CHUNK"]

ALPHA = 1e-3     # family-wise level of the screening (pure noise keeps a pair this rarely)
MAX_PAIRS = 6    # pairs expanded into every shape, strongest first
CHUNK = 1024     # columns projected at once (memory: 3 n_obs × CHUNK values)
MAX_WINDOWS = 4  # windows (a change and its return) offered per kept pair with a time or row driver
# the window scan's breaks at most: beyond, every k-th (a window's cost grows with the square of its
# breaks), and the best windows' ends refined on every break between their neighbours
SCAN_BREAKS = 256


def fitted_payload(effects: list, params) -> tuple[list[float], str, dict[str, list[float]]] | None:
    """The payload (mass moments ``m, m·sx, m·sy, m·sz``), its link and the loads logged row by row
    (load -> its mass moments per unit) that an accepted effect fitted, from the model's parameter
    values ``params``; None when none did."""
    def moments(prefix: str) -> list[float]:
        return [float(params.values[params.names.index(f"{prefix}.{k}")]) for k in ("m", "mx", "my", "mz")]
    for e in effects:
        names = [f"{e.name}.payload.{k}" for k in ("m", "mx", "my", "mz")]
        if all(n in params.names for n in names) and getattr(e, "tool_link", None):
            loads = {c: moments(f"{e.name}.load~{c}") for c in getattr(e, "loads", ())
                     if f"{e.name}.load~{c}.m" in params.names}
            return moments(f"{e.name}.payload"), e.tool_link, loads
    return None


def _projector(Jb: Tensor, w3: Tensor) -> Tensor:
    """Orthonormal basis ``(3 n_obs, r)`` of the weighted base Jacobian's columns."""
    A = Jb * w3[:, None]
    U, S, _ = torch.linalg.svd(A, full_matrices=False)
    keep = S > S.max() * 1e-10 if S.numel() else S.bool()
    return U[:, keep]


def _explained(C: Tensor, r: Tensor, Q: Tensor) -> tuple[float, int]:
    """Residual power ``‖P r‖²`` the columns ``C`` explain beyond ``Q``, and their rank."""
    C = C - Q @ (Q.T @ C)
    n = C.norm(dim=0)
    if float(n.max()) <= 0:
        return 0.0, 0
    U, S, _ = torch.linalg.svd(C / n.clamp(min=1e-300), full_matrices=False)
    U = U[:, S > S.max() * 1e-6]
    return float(((U.T @ r) ** 2).sum()), U.shape[1]


def _pair_stats(eff, columns: Callable, Q: Tensor, rp: Tensor, w3: Tensor, sigma: float) -> list[tuple]:
    """(p-value, pair) of every (parameter, driver) pair of ``eff``'s screening terms."""
    by_pair: dict[tuple[str, str], list[int]] = {}
    for i, (p, d, _) in enumerate(eff.terms):
        by_pair.setdefault((p, d), []).append(i)
    pairs = list(by_pair)
    out = []
    for s in range(0, len(pairs), max(CHUNK // 4, 1)):
        chunk = pairs[s:s + max(CHUNK // 4, 1)]
        sub = eff._copy(terms=[eff.terms[i] for pr in chunk for i in by_pair[pr]])
        C = columns(sub) * w3[:, None]
        o = 0
        for pr in chunk:
            g = len(by_pair[pr])
            e, rank = _explained(C[:, o:o + g], rp, Q)
            o += g
            if rank:
                out.append((chi2_sf(e / sigma ** 2, rank), pr))
    return out


# the best cycle's frequency refined between its grid neighbours: this many steps each side, twice
REFINE = 16


def _cycle_power(g: Tensor, shapes: Tensor, Q: Tensor, rp: Tensor) -> Tensor:
    """``(F,)`` the residual power each frequency's cycle (its sine and cosine together) explains
    beyond ``Q``, for a parameter whose own column is ``g (3 n_obs,)`` (a term's column is that
    column times its shape, observation by observation; ``shapes``: ``(3 n_obs, 2F)``)."""
    C = g[:, None] * shapes
    C = C - Q @ (Q.T @ C)
    S, K = C[:, 0::2], C[:, 1::2]
    ss, cc, sc = (S * S).sum(0), (K * K).sum(0), (S * K).sum(0)
    bs, bc = S.T @ rp, K.T @ rp
    det = ss * cc - sc * sc
    ok = det > 1e-12 * (ss * cc).clamp(min=1e-300)
    e = (cc * bs * bs - 2 * sc * bs * bc + ss * bc * bc) / det.clamp(min=1e-300)
    return torch.where(ok, e, torch.zeros_like(e))


class _Units:
    """Each (parameter, driver) pair's own column (its unit shape, weighted by the IRLS factors): what
    every shape of the pair multiplies, observation by observation. Taken once for every pair with a
    time or row driver, which the cycle search and the session-change scan both read."""

    def __init__(self, eff, columns: Callable, w3: Tensor):
        pairs = [pr for pr in dict.fromkeys((p, d) for p, d, _ in eff.terms) if driver_kind(pr[1]) in ("time", "row")]
        self.index = {pr: i for i, pr in enumerate(pairs)}
        self.G = (columns(eff._copy(terms=[(p, d, UNIT) for p, d in pairs])) * w3[:, None]) if pairs else None

    def __call__(self, pair: tuple[str, str]) -> Tensor:
        """``(3 n_obs,)`` the pair's own column."""
        return self.G[:, self.index[pair]]


class _Cycles:
    """The cycle search of a screening: each time driver's frequencies, its values per observation
    and its cycles' shapes, computed once (each pair's own column: :class:`_Units`)."""

    def __init__(self, eff, data, rows: Tensor, units: _Units):
        self.grid = {}  # time driver -> (frequencies, first training value)
        for d in dict.fromkeys(d for _, d, _ in eff.terms):
            if (g := cycles(eff, d, data))[0]:
                self.grid[d] = g
        self.pairs = [pr for pr in units.index if pr[1] in self.grid]
        self.units = units
        self.x = {d: driver_values(eff.robot, d, data.q, data.covariates)[rows] for d in self.grid}
        # every pair of a driver is searched over the same grid: its shapes, taken once
        self.shapes = {d: self._shapes(d, f) for d, (f, _) in self.grid.items()}

    def _shapes(self, driver: str, freqs: list[float]) -> Tensor:
        """``(3 n_obs, 2F)`` each frequency's sine and cosine per observation component."""
        return cycle_columns(self.x[driver], freqs, self.grid[driver][1]).repeat_interleave(3, dim=0)

    def power(self, pair: tuple[str, str], Q: Tensor, rp: Tensor, freqs: list[float] | None = None) -> Tensor:
        """``(F,)`` what each cycle explains for ``pair`` (its driver's grid, or ``freqs``)."""
        shapes = self.shapes[pair[1]] if freqs is None else self._shapes(pair[1], freqs)
        return _cycle_power(self.units(pair), shapes, Q, rp)

    def stats(self, Q: Tensor, rp: Tensor, sigma: float) -> list[tuple]:
        """(p-value, pair) of the best cycle of every pair with a time driver, the p-value of 2 degrees
        of freedom multiplied by the frequencies searched (their Bonferroni)."""
        out = []
        for pr in self.pairs:
            e = float(self.power(pr, Q, rp).max())
            out.append((min(1.0, len(self.grid[pr[1]][0]) * chi2_sf(e / sigma ** 2, 2)), pr))
        return out

    def best(self, pair: tuple[str, str], Q: Tensor, rp: Tensor) -> list[str]:
        """Both phases of the cycle that explains the most for ``pair`` (none for a driver other than
        time): the grid's best frequency, refined twice on a grid :data:`REFINE` times finer about it."""
        if pair not in self.pairs:
            return []
        freqs, x0 = self.grid[pair[1]]
        f = freqs[int(self.power(pair, Q, rp).argmax())]
        df = freqs[1] - freqs[0] if len(freqs) > 1 else f / PERIOD_OVERSAMPLE
        for _ in range(2):
            df /= REFINE
            fine = [f + k * df for k in range(-REFINE, REFINE + 1) if f + k * df > 0]
            f = fine[int(self.power(pair, Q, rp, fine).argmax())]
        return [period_tag(ph, 1.0 / f, x0) for ph in ("sin", "cos")]


def break_sums(x: Tensor, at: Tensor) -> Callable[[Tensor], Tensor]:
    """``v (n, …) -> (B, …)``: the sums of ``v`` over the components whose driver value ``x (n,)`` is
    at or beyond each break ``at (B,)`` (increasing), by one cumulative sum in the driver's order; a
    missing value is in no step."""
    order = torch.argsort(torch.nan_to_num(x, nan=-torch.inf))
    pos = torch.searchsorted(torch.nan_to_num(x[order], nan=-torch.inf).contiguous(), at.contiguous())

    def from_break(v: Tensor) -> Tensor:
        c = torch.cat([v.new_zeros((1,) + v.shape[1:]), torch.cumsum(v[order], 0)])
        return c[-1] - c[pos]
    return from_break


def step_window_power(g: Tensor, x: Tensor, at: Tensor, ok: Tensor, Q: Tensor, rp: Tensor) -> tuple[Tensor, Tensor]:
    """What each step ``(B,)`` and each window ``(B, B)`` (from the break of its row to that of its
    column; 0 where ``ok`` is false) explains beyond ``Q (3 n_obs, r)`` (orthonormal) of the residual
    ``rp (3 n_obs,)`` (orthogonal to ``Q``), for a parameter whose own column is ``g (3 n_obs,)``, the
    driver's value ``x (3 n_obs,)`` at each residual component and the breaks ``at (B,)`` (increasing):
    a step's column is ``g`` where ``x ≥`` its break.

    A window is the difference of two steps, so every window's projected column products come from the
    steps': with ``X`` the step columns and ``M = QᵀX``, they are ``XᵀX − MᵀM``. ``XᵀX``, ``M`` and ``Xᵀr``
    are sums from a break on: cumulative sums over the components in the driver's order. The cost is
    ``B² r`` for ``MᵀM``, not that of the ``B²/2`` windows' columns."""
    from_break = break_sums(x, at)
    M = from_break(g[:, None] * Q).T  # (r, B)
    tail = from_break(g * g)
    u = from_break(g * rp)
    later = torch.arange(at.numel(), device=g.device)
    G = tail[torch.maximum(later[:, None], later[None])] - M.T @ M
    d = G.diagonal()
    step = torch.where(d > 0, u * u / d.clamp(min=1e-300), torch.zeros_like(d))
    den = d[:, None] + d[None] - 2 * G
    win = torch.where(ok & (den > 1e-12 * d.max().clamp(min=1e-300)),
                      (u[:, None] - u[None]) ** 2 / den.clamp(min=1e-300), torch.zeros_like(den))
    return step, win


class _Windows:
    """The session-change scan of a screening: each time or row driver's breaks, its value at each
    residual component and which windows between two breaks hold enough rows, computed once (each
    pair's own column: :class:`_Units`)."""

    def __init__(self, eff, data, rows: Tensor, units: _Units):
        self.grid = {}  # driver -> (breaks scanned, value per residual component, windows scanned (B, B) bool)
        self.fine = {}  # driver -> (every break, every window that holds enough rows), where the scan thins them
        for d in dict.fromkeys(d for _, d, _ in eff.terms):
            if driver_kind(d) not in ("time", "row"):
                continue
            x = driver_values(eff.robot, d, data.q, data.covariates)
            b, ok = window_grid(x[torch.isfinite(x)])
            if not b:
                continue
            if len(b) > SCAN_BREAKS:
                self.fine[d] = (b, ok)
                keep = torch.linspace(0, len(b) - 1, SCAN_BREAKS).round().long()
                b, ok = [b[int(i)] for i in keep], ok[keep][:, keep]
            self.grid[d] = (b, x[rows].repeat_interleave(3), ok)
        self.pairs = [pr for pr in units.index if pr[1] in self.grid]
        self.units = units

    def power(self, pair: tuple[str, str], Q: Tensor, rp: Tensor, b: list[float] | None = None,
              ok: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """What each step and each window explains for ``pair`` (:func:`step_window_power`), on the
        scanned breaks (or ``b`` with the windows ``ok``)."""
        bs, x, oks = self.grid[pair[1]]
        b, ok = (bs, oks) if b is None else (b, ok)
        return step_window_power(self.units(pair), x, torch.tensor(b, dtype=x.dtype, device=x.device),
                                 ok, Q, rp)

    def _refined(self, pair: tuple[str, str], a: float, b: float, Q: Tensor, rp: Tensor) -> tuple[float, float]:
        """The window ``[a, b)`` of a thinned scan with its ends moved to the best of every break between
        their scanned neighbours."""
        if pair[1] not in self.fine:
            return a, b
        fine, ok = self.fine[pair[1]]
        scanned = self.grid[pair[1]][0]

        def near(v: float) -> list[int]:  # every break between the scanned neighbours of v
            k = scanned.index(v)
            lo, hi = scanned[max(k - 1, 0)], scanned[min(k + 1, len(scanned) - 1)]
            return [i for i, f in enumerate(fine) if lo <= f <= hi]
        idx = sorted(set(near(a)) | set(near(b)))
        _, win = self.power(pair, Q, rp, [fine[i] for i in idx], ok[idx][:, idx])
        i, j = divmod(int(win.argmax()), len(idx))
        return (fine[idx[i]], fine[idx[j]]) if float(win.max()) > 0 else (a, b)

    def stats(self, Q: Tensor, rp: Tensor, sigma: float) -> list[tuple]:
        """(p-value, pair) of the best step or window of every pair with a time or row driver, the
        p-value of 1 degree of freedom multiplied by the steps and windows searched (their Bonferroni)."""
        out = []
        for pr in self.pairs:
            step, win = self.power(pr, Q, rp)
            n = step.numel() + int(self.grid[pr[1]][2].sum())
            out.append((min(1.0, n * chi2_sf(float(torch.maximum(step.max(), win.max())) / sigma ** 2, 1)), pr))
        return out

    def best(self, pair: tuple[str, str], Q: Tensor, rp: Tensor) -> list[str]:
        """The :data:`MAX_WINDOWS` windows that explain the most for ``pair`` (none for a driver other
        than time or the row order)."""
        if pair not in self.pairs:
            return []
        b = self.grid[pair[1]][0]
        _, win = self.power(pair, Q, rp)
        top = win.flatten().argsort(descending=True)[:MAX_WINDOWS]
        B = len(b)
        ends = [self._refined(pair, b[int(i) // B], b[int(i) % B], Q, rp) for i in top if float(win.flatten()[i]) > 0]
        return list(dict.fromkeys(window_tag(a, c) for a, c in ends))


def _best_steps(eff, pair: tuple[str, str], data, columns: Callable, Q: Tensor, rp: Tensor,
                w3: Tensor) -> list[float]:
    """The :data:`MAX_STEPS` steps, settlings or knees of ``pair``'s driver that explain the most, one column each."""
    p, d = pair
    grid = breaks(eff, d, data, eff.torques(data.q, data.covariates) if d.startswith("torque:") else None)
    if not grid:
        return []
    score = []
    for s in range(0, len(grid), CHUNK):
        b = grid[s:s + CHUNK]
        C = columns(eff._copy(terms=[(p, d, t) for t in b])) * w3[:, None]
        C = C - Q @ (Q.T @ C)
        n2 = (C * C).sum(0)
        score.append(torch.where(n2 > 0, (C.T @ rp) ** 2 / n2.clamp(min=1e-300), torch.zeros_like(n2)))
    top = torch.cat(score).argsort(descending=True)[:MAX_STEPS]
    return [grid[int(i)] for i in top]


def screen_family(eff, data, columns: Callable, r: Tensor, Jb: Tensor, w: Tensor, sigma: float,
                  c: float | None = None, say=None, rows: Tensor | None = None):
    """``eff`` (a bound :class:`~torchcal.effects.anydriver.ParameterDrivers`, terms = its
    screening shapes) expanded into every shape of the pairs that pass the screening (module
    docstring), with :attr:`n_searched` the size of the whole space; None when no pair passes.

    Args:
        columns: ``effect -> (3 n_obs, T)`` its terms' columns in the observations' residuals.
        r: ``(n_obs, 3)`` current residuals (m); ``Jb``: ``(3 n_obs, kb)`` the current model's
            Jacobian; ``w``: ``(n_obs,)`` IRLS weights; ``sigma``: per-axis noise (m); ``c``: the
            Huber threshold (m), to which each observation's residual is shortened (None: none).
        rows: ``(n_obs,)`` each observation's data row (default: one observation per row).
    """
    w3 = w.repeat_interleave(3)
    Q = _projector(Jb, w3)
    if c is not None:  # Huber's pseudo-observations: a gross error weighs no more than the threshold
        n = r.norm(dim=-1, keepdim=True)
        r = r * torch.where(n > c, c / n.clamp(min=1e-300), torch.ones_like(n))
    rw = r.reshape(-1) * w3
    rp = rw - Q @ (Q.T @ rw)
    rows = torch.arange(len(data), device=r.device) if rows is None else rows
    units = _Units(eff, columns, w3)
    cyc = _Cycles(eff, data, rows, units)
    win = _Windows(eff, data, rows, units)
    stats = _pair_stats(eff, columns, Q, rp, w3, sigma) + cyc.stats(Q, rp, sigma) + win.stats(Q, rp, sigma)
    if not stats:
        return None
    level = ALPHA / len(stats)
    kept = list(dict.fromkeys(pr for pv, pr in sorted(stats, key=lambda t: t[0]) if pv < level))[:MAX_PAIRS]
    if say is not None:
        say(f"{eff.name}: {len(kept)} of {len({pr for _, pr in stats})} (parameter, driver) pairs pass the screening"
            + (f": {', '.join(f'{p} ~ {d}' for p, d in kept)}" if kept else ""))
    if not kept:
        return None
    # expanded in the order of plainness, so that aliases tie to the plainest reading (a joint's
    # zero before the yaw of its origin that turns the same way)
    offs = set(eff._offset_params())
    kept.sort(key=lambda pr: (pr[0] not in offs, pr[0].startswith("base."), pr[0]))
    steps = {pr: _best_steps(eff, pr, data, columns, Q, rp, w3) + cyc.best(pr, Q, rp) + win.best(pr, Q, rp)
             for pr in kept}
    out = expanded(eff, kept, data, steps)
    out.n_searched = space_size(eff, list(dict.fromkeys(pr for _, pr in stats)), data)
    return out
