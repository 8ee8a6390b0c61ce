"""Extreme learning machines (ELM): the model (seed 002, MMA-ELM; its tuning by swarm solvers is
:mod:`torchcal.elm.tune`).

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

import torch
from torch import Tensor

from torchcal.problems.elm import ACTIVATIONS, Scaler, as_matrix, activation_fn, fit_population, hidden_layer

__all__ = ["ELM", "ACTIVATIONS"]


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
            :func:`~torchcal.elm.tune.tune_elm` passes); both or neither.
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
        activation_fn(activation)
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
        X = as_matrix(X, "X", self.dtype, dev)
        Y = as_matrix(Y, "Y", self.dtype, dev)
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
        self.x_center_, self.x_scale_ = Scaler.inputs(X)
        self.y_mean_, self.y_scale_ = Scaler.outputs(Y)
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
        X = as_matrix(X, "X", self.dtype, self.V_.device)
        if X.shape[1] != self.n_features_in_:
            raise ValueError(f"X has {X.shape[1]} columns but this ELM was fitted on {self.n_features_in_}")
        return X

    def predict(self, X) -> Tensor:
        """``(N, n_in) -> (N, n_out)`` predictions in the units of the training ``Y``."""
        self._check_fitted()
        return (self.hidden(X) @ self.V_) * self.y_scale_ + self.y_mean_

    def rmse(self, X, Y) -> Tensor:
        """``(n_out,)`` root-mean-square error per output column, in ``Y``'s units."""
        Y = as_matrix(Y, "Y", self.dtype, self.V_.device if self.is_fitted else None)
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
