"""Extreme learning machines (ELM) and their tuning by swarm solvers (seed 002, MMA-ELM).

An ELM is a one-hidden-layer network ``y = V · g(W x + b)`` whose input weights ``W`` and biases
``b`` are drawn at random (``W`` in [-1, 1], ``b`` in [0, 1]) and whose output weights ``V`` are
solved in one step by the Moore–Penrose pseudo-inverse of the hidden-layer matrix (optionally
with a ridge term). Seed 002 replaces the random draw by a search: a swarm solver (the modified
mayfly algorithm, or any solver of :mod:`torchcal.optim` by name) tunes ``W`` and ``b`` to
minimise the RMSE on a validation split, with ``V`` always solved by pseudo-inverse.

Everything is batched over a *population* of ``(W, b)``: the hidden matrices of a whole swarm are
one ``(P, N, H)`` tensor and their output weights one batched least-squares call, so a solver
generation costs one call, not ``P``.

Shapes: ``X (N, n_in)``, ``Y (N, n_out)``; population ``W (P, n_in, H)``, ``b (P, H)``,
``V (P, H, n_out)``; a flat search vector ``x (P, n_in·H + H)`` holds ``W`` row-major
(``W[i, h]`` at ``i·H + h``) followed by ``b``.

Scaling: inputs are mapped to [-1, 1] per column by the training minimum and maximum (so ``W``'s
range [-1, 1] means the same thing for joints in rad, prismatic joints in m and temperatures in
°C); outputs are standardised per column (mean 0, std 1), so the fitness RMSE weighs mm-sized
position errors and mrad-sized angle errors alike. Predictions are returned in the units of
``Y``.
"""
from __future__ import annotations

import math
from typing import Callable

import torch
from torch import Tensor

from torchcal.optim import FunctionProblem, Result, get_solver

__all__ = ["ELM", "ACTIVATIONS", "hidden_layer", "solve_output_weights", "fit_population",
           "ELMProblem", "tune_elm"]

ACTIVATIONS: dict[str, Callable[[Tensor], Tensor]] = {
    "sigmoid": torch.sigmoid,
    "tanh": torch.tanh,
    "sin": torch.sin,
    "relu": torch.relu,
}
"""Hidden-layer activations by name (seed 002 uses ``"sigmoid"``)."""


def _activation(name: str) -> Callable[[Tensor], Tensor]:
    try:
        return ACTIVATIONS[name]
    except KeyError:
        raise ValueError(f"unknown activation {name!r}; choose one of {sorted(ACTIVATIONS)}") from None


def hidden_layer(X: Tensor, W: Tensor, b: Tensor, activation: str = "sigmoid") -> Tensor:
    """Hidden-layer outputs ``g(X W + b)``.

    Args:
        X: ``(N, n_in)`` scaled inputs (or ``(P, N, n_in)``).
        W: ``(n_in, H)`` or ``(P, n_in, H)`` input weights.
        b: ``(H,)`` or ``(P, H)`` biases.
    Returns:
        ``(N, H)`` or ``(P, N, H)``.
    """
    return _activation(activation)(X @ W + b[..., None, :])


def solve_output_weights(H: Tensor, Y: Tensor, ridge: float = 0.0) -> Tensor:
    """Output weights ``V`` minimising ``|H V - Y|² + ridge |V|²``, batched over leading axes.

    Args:
        H: ``(..., N, H)`` hidden-layer matrices (a population stacks them on axis 0).
        Y: ``(N, n_out)`` targets shared by the population, or ``(..., N, n_out)``.
        ridge: ``0`` gives the Moore–Penrose solution ``V = H⁺ Y`` (minimum norm when ``H`` is
            rank deficient), as seed 002 prescribes; ``> 0`` a ridge (Tikhonov) solution.
    Returns:
        ``(..., H, n_out)``.

    Why these solvers: with ``ridge = 0`` the normal equations would square the condition
    number of ``H`` (sigmoid features are strongly correlated; cond(H) of 1e3–1e8 is common), so
    the pseudo-inverse comes from a rank-revealing factorisation instead: LAPACK ``gelsd``
    (SVD, minimum-norm solution, i.e. exactly ``pinv(H) Y`` with the usual ``eps·max(N, H)``
    cut-off), batched by torch. ``gelsy`` (pivoted QR) is about twice as fast on CPU but, with
    MKL, not bit-reproducible from run to run (its result depends on buffer alignment), and a
    seed must give the same network every time. On GPUs torch's batched ``lstsq`` only offers
    ``gels`` (full rank assumed), so the pseudo-inverse goes through a batched SVD
    (``torch.linalg.pinv``). With ``ridge > 0`` the eigenvalues of ``HᵀH + ridge I`` are bounded
    below by ``ridge``, so the normal equations are safe and a batched Cholesky is the cheapest
    route (about 4x faster than ``gelsd`` on CPU).
    """
    if Y.ndim == H.ndim - 1 or Y.shape[:-2] != H.shape[:-2]:
        Y = Y.expand(*H.shape[:-2], *Y.shape[-2:])
    if ridge > 0:
        eye = torch.eye(H.shape[-1], dtype=H.dtype, device=H.device)
        Ht = H.transpose(-1, -2)
        L = torch.linalg.cholesky(Ht @ H + ridge * eye)
        return torch.cholesky_solve(Ht @ Y, L)
    if ridge < 0:
        raise ValueError(f"ridge must be >= 0, got {ridge}")
    if H.device.type == "cpu":
        return torch.linalg.lstsq(H, Y, driver="gelsd").solution
    return torch.linalg.pinv(H) @ Y


def fit_population(Xs: Tensor, Ys: Tensor, W: Tensor, b: Tensor, activation: str = "sigmoid",
                   ridge: float = 0.0) -> Tensor:
    """Output weights of a whole population of ELMs in one batched solve.

    Args:
        Xs: ``(N, n_in)`` scaled training inputs; Ys: ``(N, n_out)`` scaled targets.
        W: ``(P, n_in, H)``; b: ``(P, H)``.
    Returns:
        ``V (P, H, n_out)``.
    """
    return solve_output_weights(hidden_layer(Xs, W, b, activation), Ys, ridge)


def _as_2d(a, name: str, dtype, device) -> Tensor:
    t = torch.as_tensor(a, dtype=dtype, device=device)
    if t.ndim == 1:
        t = t[:, None]
    if t.ndim != 2:
        raise ValueError(f"{name} must be a 2-D array (n_samples, n_columns), got shape {tuple(t.shape)}")
    if t.shape[0] == 0:
        raise ValueError(f"{name} has no rows")
    if not bool(torch.isfinite(t).all()):
        bad = torch.nonzero(~torch.isfinite(t))[0].tolist()
        raise ValueError(f"{name} has NaN or inf (first at row {bad[0]}, column {bad[1]}); drop or fill those rows")
    return t


class _Scaler:
    """Input min-max scaling to [-1, 1] and output standardisation, fitted on training data."""

    @staticmethod
    def inputs(X: Tensor) -> tuple[Tensor, Tensor]:
        lo, hi = X.amin(0), X.amax(0)
        half = (hi - lo) / 2
        # a constant column (e.g. a covariate that never changed) maps to 0, not to NaN
        return (hi + lo) / 2, torch.where(half > 0, half, torch.ones_like(half))

    @staticmethod
    def outputs(Y: Tensor) -> tuple[Tensor, Tensor]:
        mu = Y.mean(0)
        sd = Y.std(0, correction=0) if Y.shape[0] > 1 else torch.zeros_like(mu)
        return mu, torch.where(sd > 0, sd, torch.ones_like(sd))


class ELM:
    """Extreme learning machine regressor (scikit-learn conventions: ``fit`` / ``predict``).

    ``y = V · g(W x̃ + b)`` with ``x̃`` the inputs scaled to [-1, 1] per column (training min and
    max) and ``y`` standardised per column inside; :meth:`predict` returns ``Y``'s units.

    Args:
        n_hidden: hidden neurons ``H``.
        activation: ``"sigmoid"`` (seed 002), ``"tanh"``, ``"sin"`` or ``"relu"``.
        ridge: ``0`` = Moore–Penrose pseudo-inverse (seed 002); ``> 0`` minimises
            ``|H V - Y|² + ridge |V|²`` on the standardised targets.
        seed: seeds the private generator that draws ``W ~ U(-1, 1)``, ``b ~ U(0, 1)``.
        input_weights, biases: ``(n_in, H)`` and ``(H,)`` to use instead of a random draw (what
            :func:`tune_elm` passes); both or neither.
        dtype, device: of all tensors (float64 and CPU by default).

    Learned attributes (after :meth:`fit`): ``W_ (n_in, H)``, ``b_ (H,)``, ``V_ (H, n_out)``,
    ``x_center_, x_scale_ (n_in,)``, ``y_mean_, y_scale_ (n_out,)``, ``n_features_in_``,
    ``n_outputs_``.
    """

    def __init__(self, n_hidden: int = 40, activation: str = "sigmoid", ridge: float = 0.0,
                 seed: int | None = 0, *, input_weights: Tensor | None = None,
                 biases: Tensor | None = None, dtype: torch.dtype = torch.float64,
                 device: torch.device | str | None = None):
        if int(n_hidden) < 1:
            raise ValueError(f"n_hidden must be >= 1, got {n_hidden}")
        _activation(activation)
        if not float(ridge) >= 0:
            raise ValueError(f"ridge must be >= 0, got {ridge}")
        if (input_weights is None) != (biases is None):
            raise ValueError("give both input_weights and biases, or neither (then they are drawn at random)")
        self.n_hidden = int(n_hidden)
        self.activation = activation
        self.ridge = float(ridge)
        self.seed = seed
        self.input_weights = input_weights
        self.biases = biases
        self.dtype = dtype
        self.device = torch.device(device) if device is not None else None

    # -- scikit-learn plumbing --------------------------------------------------------------
    def get_params(self, deep: bool = True) -> dict:
        return {"n_hidden": self.n_hidden, "activation": self.activation, "ridge": self.ridge,
                "seed": self.seed, "input_weights": self.input_weights, "biases": self.biases,
                "dtype": self.dtype, "device": self.device}

    def set_params(self, **params) -> "ELM":
        for k, v in params.items():
            if k not in self.get_params():
                raise ValueError(f"ELM has no parameter {k!r}; valid: {sorted(self.get_params())}")
            setattr(self, k, v)
        return self

    def __repr__(self) -> str:
        return f"ELM(n_hidden={self.n_hidden}, activation={self.activation!r}, ridge={self.ridge:g}, seed={self.seed})"

    @property
    def is_fitted(self) -> bool:
        return hasattr(self, "V_")

    def _check_fitted(self) -> None:
        if not self.is_fitted:
            raise RuntimeError("this ELM is not fitted yet; call fit(X, Y) first")

    # -- the model --------------------------------------------------------------------------
    def _draw(self, n_in: int, device) -> tuple[Tensor, Tensor]:
        g = torch.Generator(device="cpu")
        g.manual_seed(0 if self.seed is None else int(self.seed))
        # drawn on the CPU so a seed gives the same network on every device
        W = torch.rand(n_in, self.n_hidden, generator=g, dtype=torch.float64) * 2 - 1
        b = torch.rand(self.n_hidden, generator=g, dtype=torch.float64)
        return W.to(self.dtype).to(device), b.to(self.dtype).to(device)

    def fit(self, X, Y) -> "ELM":
        """Fit the output weights (and the scaling) to training data.

        Args:
            X: ``(N, n_in)`` inputs (e.g. commanded joint angles in rad, then covariates).
            Y: ``(N, n_out)`` targets (e.g. pose errors in m and rad) or ``(N,)``.
        Returns:
            ``self``.
        """
        dev = self.device if self.device is not None else (X.device if isinstance(X, Tensor) else "cpu")
        X = _as_2d(X, "X", self.dtype, dev)
        Y = _as_2d(Y, "Y", self.dtype, dev)
        if X.shape[0] != Y.shape[0]:
            raise ValueError(f"X and Y have different numbers of rows: {X.shape[0]} and {Y.shape[0]}")
        n_in = X.shape[1]
        if self.input_weights is None:
            W, b = self._draw(n_in, X.device)
        else:
            W = torch.as_tensor(self.input_weights, dtype=self.dtype, device=X.device)
            b = torch.as_tensor(self.biases, dtype=self.dtype, device=X.device)
            if W.shape != (n_in, self.n_hidden) or b.shape != (self.n_hidden,):
                raise ValueError(f"input_weights must be ({n_in}, {self.n_hidden}) and biases ({self.n_hidden},) "
                                 f"for {n_in} input columns and n_hidden={self.n_hidden}; got "
                                 f"{tuple(W.shape)} and {tuple(b.shape)}")
        self.x_center_, self.x_scale_ = _Scaler.inputs(X)
        self.y_mean_, self.y_scale_ = _Scaler.outputs(Y)
        Xs = (X - self.x_center_) / self.x_scale_
        Ys = (Y - self.y_mean_) / self.y_scale_
        # the population code path with P = 1, so a single fit and a swarm member agree exactly
        V = fit_population(Xs, Ys, W[None], b[None], self.activation, self.ridge)[0]
        # LAPACK hands back column-major V; BLAS may round a product differently for another
        # memory layout, so store every tensor row-major, as a loaded model has it
        self.V_ = V.contiguous()
        self.W_, self.b_ = W.contiguous().clone(), b.contiguous().clone()
        self.n_features_in_, self.n_outputs_ = n_in, Y.shape[1]
        return self

    def hidden(self, X) -> Tensor:
        """``(N, n_in)`` raw inputs ``-> (N, H)`` hidden-layer outputs."""
        self._check_fitted()
        X = self._check_X(X)
        return hidden_layer((X - self.x_center_) / self.x_scale_, self.W_, self.b_, self.activation)

    def _check_X(self, X) -> Tensor:
        X = _as_2d(X, "X", self.dtype, self.V_.device)
        if X.shape[1] != self.n_features_in_:
            raise ValueError(f"X has {X.shape[1]} columns but this ELM was fitted on {self.n_features_in_}")
        return X

    def predict(self, X) -> Tensor:
        """``(N, n_in) -> (N, n_out)`` predictions in the units of the training ``Y``."""
        self._check_fitted()
        return (self.hidden(X) @ self.V_) * self.y_scale_ + self.y_mean_

    def rmse(self, X, Y) -> Tensor:
        """``(n_out,)`` root-mean-square error per output column, in ``Y``'s units."""
        Y = _as_2d(Y, "Y", self.dtype, self.V_.device if self.is_fitted else None)
        d = self.predict(X) - Y
        return torch.sqrt((d * d).mean(0))

    # -- persistence --------------------------------------------------------------------------
    def config(self) -> dict:
        """JSON-serialisable hyper-parameters and sizes (tensors go to :meth:`state_dict`)."""
        self._check_fitted()
        return {"type": "ELM", "n_hidden": self.n_hidden, "activation": self.activation,
                "ridge": self.ridge, "seed": self.seed, "n_features_in": self.n_features_in_,
                "n_outputs": self.n_outputs_}

    def state_dict(self) -> dict[str, Tensor]:
        """The fitted tensors: ``W, b, V, x_center, x_scale, y_mean, y_scale``."""
        self._check_fitted()
        return {"W": self.W_, "b": self.b_, "V": self.V_, "x_center": self.x_center_,
                "x_scale": self.x_scale_, "y_mean": self.y_mean_, "y_scale": self.y_scale_}

    @classmethod
    def from_state_dict(cls, config: dict, tensors: dict[str, Tensor]) -> "ELM":
        """Rebuild a fitted ELM from :meth:`config` and :meth:`state_dict` (bit-exact)."""
        need = {"W", "b", "V", "x_center", "x_scale", "y_mean", "y_scale"}
        missing = need - set(tensors)
        if missing:
            raise ValueError(f"ELM state is missing {sorted(missing)}")
        W = tensors["W"]
        m = cls(config["n_hidden"], config.get("activation", "sigmoid"), config.get("ridge", 0.0),
                config.get("seed"), input_weights=W, biases=tensors["b"], dtype=W.dtype, device=W.device)
        m.W_, m.b_, m.V_ = W, tensors["b"], tensors["V"]
        m.x_center_, m.x_scale_ = tensors["x_center"], tensors["x_scale"]
        m.y_mean_, m.y_scale_ = tensors["y_mean"], tensors["y_scale"]
        m.n_features_in_, m.n_outputs_ = int(W.shape[0]), int(m.V_.shape[1])
        if m.W_.shape[1] != m.n_hidden or m.V_.shape[0] != m.n_hidden:
            raise ValueError(f"ELM state does not match n_hidden={m.n_hidden}: W {tuple(W.shape)}, "
                             f"V {tuple(m.V_.shape)}")
        return m


class ELMProblem(FunctionProblem):
    """Seed 002's search problem: ``W`` and ``b`` of an ELM, fitness = validation RMSE.

    The search vector is ``x = [W (row-major), b]`` of dimension ``n_in·H + H`` with bounds
    ``[low, high]`` (seed 002: [-1, 1] for both ``W`` and ``b``). For each candidate the output
    weights are solved on the training split (pseudo-inverse, or ridge) and the fitness is the
    RMSE of the standardised predictions on the validation split, over all outputs (patent
    eq. 6; standardised so that outputs in m and rad weigh alike). The fitness of a population
    ``(P, k)`` is one batched solve.

    Scaling (inputs to [-1, 1], outputs standardised) is fitted on the training split only.
    """

    def __init__(self, X_train, Y_train, X_val, Y_val, n_hidden: int = 40,
                 activation: str = "sigmoid", ridge: float = 0.0, low: float = -1.0,
                 high: float = 1.0, dtype: torch.dtype = torch.float64, chunk: int = 256):
        dev = X_train.device if isinstance(X_train, Tensor) else "cpu"
        Xt, Yt = _as_2d(X_train, "X_train", dtype, dev), _as_2d(Y_train, "Y_train", dtype, dev)
        Xv, Yv = _as_2d(X_val, "X_val", dtype, dev), _as_2d(Y_val, "Y_val", dtype, dev)
        if Xt.shape[0] != Yt.shape[0] or Xv.shape[0] != Yv.shape[0]:
            raise ValueError(f"rows differ: X_train {Xt.shape[0]} vs Y_train {Yt.shape[0]}, "
                             f"X_val {Xv.shape[0]} vs Y_val {Yv.shape[0]}")
        if Xt.shape[1] != Xv.shape[1] or Yt.shape[1] != Yv.shape[1]:
            raise ValueError(f"training and validation columns differ: X {Xt.shape[1]} vs {Xv.shape[1]}, "
                             f"Y {Yt.shape[1]} vs {Yv.shape[1]}")
        _activation(activation)
        self.n_in, self.n_hidden, self.n_out = Xt.shape[1], int(n_hidden), Yt.shape[1]
        self.activation, self.ridge, self.chunk = activation, float(ridge), int(chunk)
        self.x_center, self.x_scale = _Scaler.inputs(Xt)
        self.y_mean, self.y_scale = _Scaler.outputs(Yt)
        self.Xt = (Xt - self.x_center) / self.x_scale
        self.Yt = (Yt - self.y_mean) / self.y_scale
        self.Xv = (Xv - self.x_center) / self.x_scale
        self.Yv = (Yv - self.y_mean) / self.y_scale
        self.raw = (Xt, Yt, Xv, Yv)
        k = self.n_in * self.n_hidden + self.n_hidden
        lo = torch.full((k,), float(low), dtype=dtype, device=dev)
        hi = torch.full((k,), float(high), dtype=dtype, device=dev)
        super().__init__(self._fitness, lo, hi)

    def decode(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """``(P, k)`` search vectors -> ``W (P, n_in, H)``, ``b (P, H)`` (or unbatched for ``(k,)``)."""
        nW = self.n_in * self.n_hidden
        W = x[..., :nW].reshape(*x.shape[:-1], self.n_in, self.n_hidden)
        return W, x[..., nW:]

    def encode(self, W: Tensor, b: Tensor) -> Tensor:
        """Inverse of :meth:`decode`."""
        return torch.cat([W.reshape(*W.shape[:-2], -1), b], -1)

    def _fitness(self, X: Tensor) -> Tensor:
        out = []
        # chunks bound the memory of P x N x H hidden matrices for very large populations
        for Xc in X.split(self.chunk):
            W, b = self.decode(Xc)
            V = fit_population(self.Xt, self.Yt, W, b, self.activation, self.ridge)
            pred = hidden_layer(self.Xv, W, b, self.activation) @ V  # (P, Nv, n_out)
            d = pred - self.Yv
            out.append(torch.sqrt((d * d).mean((-1, -2))))
        return torch.cat(out)


def _random_search(problem: ELMProblem, n_evals: int, seed: int, batch: int = 64) -> Result:
    """Uniform random search in the bounds: the baseline every tuner must beat at equal
    evaluations (``W, b`` drawn in the search bounds, best validation RMSE kept)."""
    import time

    t0 = time.perf_counter()
    g = torch.Generator(device=problem.device).manual_seed(int(seed))
    best_x, best_f, hist, done = None, math.inf, [], 0
    while done < n_evals:
        m = min(batch, n_evals - done)
        X = problem.lower + (problem.upper - problem.lower) * torch.rand(
            m, problem.dim, generator=g, dtype=problem.dtype, device=problem.device)
        f = problem.fitness(X)
        f = torch.where(torch.isnan(f), torch.full_like(f, math.inf), f)
        j = int(torch.argmin(f))
        if float(f[j]) < best_f:
            best_f, best_x = float(f[j]), X[j].clone()
        hist.append(best_f)
        done += m
    return Result(x=best_x, fun=best_f, history=hist, n_evals=done, n_iter=len(hist),
                  wall_time_s=time.perf_counter() - t0, message=f"{done} random candidates",
                  method="random")


def tune_elm(X_train, Y_train, X_val, Y_val, method: str = "mma", n_hidden: int = 40, *,
             activation: str = "sigmoid", ridge: float = 0.0, options: dict | None = None,
             seed: int = 0, progress: bool = False, refit: str = "train") -> tuple[ELM, Result]:
    """Tune an ELM's ``W`` and ``b`` with a swarm solver (seed 002's MMA-ELM and its relatives).

    Args:
        X_train, Y_train: ``(N, n_in)``, ``(N, n_out)`` data the output weights are solved on.
        X_val, Y_val: validation split; the fitness is its RMSE (standardised outputs).
        method: any solver of :mod:`torchcal.optim` by name (``"mma"`` = seed 002, ``"ma"``,
            ``"pso"``, ``"ga"``, ...) or ``"random"`` (uniform random search; ``options`` then
            takes ``n_evals``, default 2000).
        n_hidden: hidden neurons; the search dimension is ``n_in·n_hidden + n_hidden``.
        options: solver options (e.g. ``{"pop_size": 20, "max_iter": 100}``).
        refit: ``"train"`` keeps ``V`` solved on the training split (what the fitness saw);
            ``"all"`` re-solves ``V`` on training + validation data with the tuned ``W, b``
            (and scaling from both).
    Returns:
        ``(elm, result)``: the fitted :class:`ELM` with the best ``W, b``, and the solver's
        :class:`~torchcal.optim.Result` (``fun`` = best validation RMSE, standardised units).
    """
    if refit not in ("train", "all"):
        raise ValueError(f"refit must be 'train' or 'all', got {refit!r}")
    prob = ELMProblem(X_train, Y_train, X_val, Y_val, n_hidden, activation, ridge)
    opts = dict(options or {})
    if method.lower() == "random":
        res = _random_search(prob, int(opts.pop("n_evals", 2000)), seed, int(opts.pop("batch", 64)))
        if opts:
            raise ValueError(f"random search takes n_evals and batch, not {sorted(opts)}")
    else:
        res = get_solver(method, seed=seed, progress=progress, **opts).minimize(prob)
    W, b = prob.decode(res.x)
    elm = ELM(n_hidden, activation, ridge, seed=None, input_weights=W.clone(), biases=b.clone(),
              dtype=prob.dtype, device=prob.device)
    Xt, Yt, Xv, Yv = prob.raw
    if refit == "all":
        elm.fit(torch.cat([Xt, Xv]), torch.cat([Yt, Yv]))
    else:
        elm.fit(Xt, Yt)
    return elm, res
