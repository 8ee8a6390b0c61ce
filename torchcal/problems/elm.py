"""The extreme learning machine's maths and its tuning as a :class:`~torchcal.problems.base.Problem`:
a random hidden layer, output weights in closed form (ridge least squares), batched over a
population of hidden layers; the hidden weights and biases are the parameters and the validation
error is the fitness, so the same swarm solvers that identify geometry (MMA, PSO, GA, ...) tune it."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor

from torchcal.options import Options
from torchcal.problems.base import FunctionProblem

__all__ = ["ACTIVATIONS", "ELMProblem", "ELMProblemOptions", "Scaler", "as_matrix", "activation_fn", "fit_population",
           "hidden_layer", "solve_output_weights"]


ACTIVATIONS: dict[str, Callable[[Tensor], Tensor]] = {
    "sigmoid": torch.sigmoid,
    "tanh": torch.tanh,
    "sin": torch.sin,
    "relu": torch.relu,
}


def activation_fn(name: str) -> Callable[[Tensor], Tensor]:
    """The activation named ``name`` (a key of :data:`ACTIVATIONS`); a clear error for any other."""
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
    return activation_fn(activation)(X @ W + b[..., None, :])


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


def as_matrix(a, name: str, dtype, device) -> Tensor:
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


class Scaler:
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


@dataclass(frozen=True)
class ELMProblemOptions(Options):
    """Settings of :class:`ELMProblem`: hidden neurons, activation, ridge of the output solve (0: the
    pseudo-inverse), the bounds ``[low, high]`` of ``W`` and ``b``, the dtype and the population chunk
    solved at once."""

    n_hidden: int = 40
    activation: str = "sigmoid"
    ridge: float = 0.0
    low: float = -1.0
    high: float = 1.0
    dtype: torch.dtype = torch.float64
    chunk: int = 256


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

    def __init__(self, X_train, Y_train, X_val, Y_val, settings: ELMProblemOptions | None = None, **options):
        o = ELMProblemOptions.build(settings, **options)
        n_hidden, activation, ridge, low, high, dtype, chunk = (o.n_hidden, o.activation, o.ridge, o.low, o.high,
                                                                o.dtype, o.chunk)
        dev = X_train.device if isinstance(X_train, Tensor) else "cpu"
        Xt, Yt = as_matrix(X_train, "X_train", dtype, dev), as_matrix(Y_train, "Y_train", dtype, dev)
        Xv, Yv = as_matrix(X_val, "X_val", dtype, dev), as_matrix(Y_val, "Y_val", dtype, dev)
        if Xt.shape[0] != Yt.shape[0] or Xv.shape[0] != Yv.shape[0]:
            raise ValueError(f"rows differ: X_train {Xt.shape[0]} vs Y_train {Yt.shape[0]}, "
                             f"X_val {Xv.shape[0]} vs Y_val {Yv.shape[0]}")
        if Xt.shape[1] != Xv.shape[1] or Yt.shape[1] != Yv.shape[1]:
            raise ValueError(f"training and validation columns differ: X {Xt.shape[1]} vs {Xv.shape[1]}, "
                             f"Y {Yt.shape[1]} vs {Yv.shape[1]}")
        activation_fn(activation)
        self.n_in, self.n_hidden, self.n_out = Xt.shape[1], int(n_hidden), Yt.shape[1]
        self.activation, self.ridge, self.chunk = activation, float(ridge), int(chunk)
        self.x_center, self.x_scale = Scaler.inputs(Xt)
        self.y_mean, self.y_scale = Scaler.outputs(Yt)
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
