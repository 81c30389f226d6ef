"""Curve fits for the thesis report: least squares, leave-one-out model choice (pure numpy).

Models of ``y`` against ``x``:

``const``   ``y = a``                       (O(1))
``log``     ``y = a + b log2 x``            (O(log N))
``linear``  ``y = a + b x``                 (O(N))
``exp``     ``y = a e^(b x)``               (fitted as ``ln y = ln a + b x``; needs y > 0)
``power``   ``y = a x^b``                   (fitted as ``ln y = ln a + b ln x``; ``b`` is the growth order:
            1 for linear growth, rising without bound for exponential growth)

:func:`choose` fits each candidate to every point but one and predicts the one left out
(leave-one-out cross-validation); the model with the smallest root-mean-square prediction
error is chosen, the simpler one on a tie within 5 %.  With three points a two-parameter
model is fitted to two and must extrapolate, so a curve is only chosen over a constant when
the data really bend that way.
"""

from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np

MODELS = ("const", "log", "linear", "exp", "power")
_PARAMS = {"const": 1, "log": 2, "linear": 2, "exp": 2, "power": 2}
FORMULA = {"const": "y = a", "log": "y = a + b log2(x)", "linear": "y = a + b x", "exp": "y = a exp(b x)",
           "power": "y = a x^b"}


def _design(model: str, x: np.ndarray) -> np.ndarray:
    if model == "const":
        return np.ones((len(x), 1))
    if model == "log":
        return np.column_stack([np.ones(len(x)), np.log2(x)])
    if model == "power":
        return np.column_stack([np.ones(len(x)), np.log(x)])
    return np.column_stack([np.ones(len(x)), x])


def fit(model: str, xs: Sequence[float], ys: Sequence[float]) -> dict[str, Any]:
    """Least-squares fit of one model.

    Returns
    -------
    dict
        ``{"model", "formula", "a", "b", "r2", "n", "slope_se"}`` (``b`` None for ``const``;
        ``slope_se`` the standard error of ``b`` when there are more points than parameters).

    Examples
    --------
    >>> f = fit("linear", [1, 2, 3], [2, 4, 6])
    >>> round(f["a"], 9), round(f["b"], 9), f["r2"]
    (0.0, 2.0, 1.0)
    """
    x = np.asarray(xs, float)
    y = np.asarray(ys, float)
    if model not in MODELS:
        raise ValueError(f"model must be one of {MODELS}, got {model!r}")
    if len(x) < _PARAMS[model]:
        raise ValueError(f"{model} needs at least {_PARAMS[model]} points, got {len(x)}")
    yt = y
    if model in ("exp", "power"):
        if np.any(y <= 0):
            raise ValueError(f"the {model} model needs y > 0")
        yt = np.log(y)
    if model in ("log", "power") and np.any(x <= 0):
        raise ValueError(f"the {model} model needs x > 0")
    A = _design(model, x)
    coef, *_ = np.linalg.lstsq(A, yt, rcond=None)
    pred = predict({"model": model, "a": float(np.exp(coef[0])) if model in ("exp", "power") else float(coef[0]),
                    "b": float(coef[1]) if len(coef) > 1 else None}, x)
    ss_res = float(np.sum((y - pred) ** 2))
    ss_tot = float(np.sum((y - y.mean()) ** 2))
    r2 = 1.0 if ss_tot == 0 and ss_res == 0 else (0.0 if ss_tot == 0 else 1.0 - ss_res / ss_tot)
    se = None
    if len(coef) > 1 and len(x) > 2:
        resid = yt - A @ coef
        s2 = float(resid @ resid) / (len(x) - 2)
        cov = s2 * np.linalg.pinv(A.T @ A)
        se = float(math.sqrt(max(cov[1, 1], 0.0)))
    return {"model": model, "formula": FORMULA[model],
            "a": float(np.exp(coef[0])) if model in ("exp", "power") else float(coef[0]),
            "b": float(coef[1]) if len(coef) > 1 else None, "r2": r2, "n": int(len(x)), "slope_se": se}


def predict(f: dict[str, Any], xs) -> np.ndarray:
    """The fitted curve at ``xs``."""
    x = np.asarray(xs, float)
    m, a, b = f["model"], f["a"], f.get("b")
    if m == "const":
        return np.full(x.shape, a)
    if m == "log":
        return a + b * np.log2(x)
    if m == "linear":
        return a + b * x
    if m == "power":
        return a * x**b
    return a * np.exp(b * x)


def loo_rmse(model: str, xs: Sequence[float], ys: Sequence[float]) -> float | None:
    """Root-mean-square leave-one-out prediction error (None when the model cannot be fitted)."""
    x = np.asarray(xs, float)
    y = np.asarray(ys, float)
    if len(x) < _PARAMS[model] + 1:
        return None
    errs = []
    for i in range(len(x)):
        keep = np.arange(len(x)) != i
        if len(set(x[keep].tolist())) < _PARAMS[model]:
            return None
        try:
            f = fit(model, x[keep], y[keep])
        except ValueError:
            return None
        errs.append(float(predict(f, x[i:i + 1])[0] - y[i]))
    return float(math.sqrt(sum(e * e for e in errs) / len(errs)))


def growth_order(xs: Sequence[float], ys: Sequence[float]) -> dict[str, Any] | None:
    """The exponent ``b`` of ``y = a x^b`` with its standard error, and whether growth is faster than linear.

    ``superlinear`` is true when ``b - 2 se > 1`` (needs three points or more; y > 0).

    Examples
    --------
    >>> g = growth_order([1, 2, 4, 8], [3, 6.2, 11.8, 24.1])
    >>> round(g["b"], 1), g["superlinear"]
    (1.0, False)
    >>> growth_order([1, 2, 4, 8], [1, 2.7, 20, 3000])["superlinear"]
    True
    """
    pts = [(x, y) for x, y in zip(xs, ys) if x > 0 and y is not None and y > 0]
    if len(pts) < 3:
        return None
    f = fit("power", [p[0] for p in pts], [p[1] for p in pts])
    se = f["slope_se"] or 0.0
    return {"formula": f["formula"], "a": f["a"], "b": f["b"], "b_se": se, "r2": f["r2"], "n": f["n"],
            "superlinear": bool(f["b"] - 2 * se > 1.0)}


def choose(xs: Sequence[float], ys: Sequence[float], models: Sequence[str] = MODELS[:4]) -> dict[str, Any]:
    """Fit every model, choose by leave-one-out error.

    Returns
    -------
    dict
        ``{"chosen", "fits": {model: fit + "loo_rmse"}}``.

    Examples
    --------
    >>> choose([1, 2, 4, 8], [5.0, 5.1, 4.9, 5.0])["chosen"]
    'const'
    >>> choose([1, 2, 4, 8, 16], [1, 2, 3, 4, 5], ("const", "log", "linear"))["chosen"]
    'log'
    """
    fits: dict[str, Any] = {}
    for m in models:
        try:
            f = fit(m, xs, ys)
        except ValueError:
            continue
        f["loo_rmse"] = loo_rmse(m, xs, ys)
        fits[m] = f
    ranked = sorted((f["loo_rmse"], _PARAMS[m], MODELS.index(m), m) for m, f in fits.items()
                    if f["loo_rmse"] is not None)
    chosen = None
    if ranked:
        best = ranked[0][0]
        # the simplest model within 5 % of the best error
        chosen = min((r for r in ranked if r[0] <= best * 1.05 + 1e-12), key=lambda r: (r[1], r[2]))[3]
    return {"chosen": chosen, "fits": fits}
