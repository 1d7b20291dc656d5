"""Small numerically safe tensor helpers shared by the model and the losses.

Why a module of its own: the head's cosine attention, TTC's angles and ATC's cosines must agree on
what a zero-length vector means, and must all stay finite *in the backward pass* too. The usual
tools are not: ``torch.nn.functional.normalize`` has a gradient of ``1/eps = 1e12`` at the zero
vector, ``acos`` has an infinite one at +-1. Everything here uses the smoothed norm
``sqrt(|x|^2 + eps^2)`` whose gradient is ``x / sqrt(|x|^2 + eps^2)``, bounded by 1 everywhere.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from firp.core.contract import N_CATEGORIES

#: Default smoothing of norms. Vectors much shorter than this have (almost) no direction.
EPS = 1e-6
_TINY = 1e-12  # smoothing of norms of vectors of length <= 1 (1e-24 is still a normal float32)


def safe_norm(x: Tensor, dim: int = -1, eps: float = EPS, keepdim: bool = False) -> Tensor:
    """``sqrt(|x|^2 + eps^2)`` over ``dim``: equals ``|x|`` up to ``eps``, differentiable at 0."""
    return torch.sqrt(x.pow(2).sum(dim=dim, keepdim=keepdim) + eps * eps)


def safe_unit(x: Tensor, dim: int = -1, eps: float = EPS) -> Tensor:
    """``x / sqrt(|x|^2 + eps^2)``: the unit vector, fading smoothly to 0 for ``|x| << eps``.

    The Jacobian at ``x = 0`` is ``I / eps``: finite, but large for a tiny ``eps``, as the
    direction of a vanishing vector is inherently unstable. Clip gradients in training.
    """
    return x / safe_norm(x, dim=dim, eps=eps, keepdim=True)


def safe_cosine(a: Tensor, b: Tensor, dim: int = -1, eps: float = EPS) -> Tensor:
    """Cosine similarity, broadcasting; ``0`` where either vector is (close to) zero-length."""
    return (safe_unit(a, dim, eps) * safe_unit(b, dim, eps)).sum(dim=dim)


def safe_angle(a: Tensor, b: Tensor, dim: int = -1, eps: float = EPS) -> Tensor:
    """Angle in ``[0, pi]`` between ``a`` and ``b`` (Kahan's formula), finite value and gradient.

    ``theta = 2 atan2(|u - v|, |u + v|)`` with ``u, v`` the (safe) unit vectors: accurate near 0
    and pi, where ``acos(cos)`` loses precision and has an infinite derivative. A zero-length
    vector has no direction; it gets ``u = 0`` and hence ``theta = pi/2``, which is the angle that
    matches the cosine 0 of :func:`safe_cosine`, so TTC and ATC treat it alike. The outer norms
    are smoothed by a much smaller ``1e-12`` (``u, v`` have length <= 1), so parallel vectors get
    an angle of ~1e-12 rather than ~eps.
    """
    u = safe_unit(a, dim, eps)
    v = safe_unit(b, dim, eps)
    return 2.0 * torch.atan2(safe_norm(u - v, dim, _TINY), safe_norm(u + v, dim, _TINY))


def masked_mean(x: Tensor, mask: Tensor | None) -> Tensor:
    """Mean of ``x`` over the entries where ``mask`` (broadcast to ``x``) is true; 0 if none."""
    if mask is None:
        return x.mean()
    m = mask.to(x.dtype).expand_as(x)
    return (x * m).sum() / m.sum().clamp_min(1.0)


def mlp2(in_dim: int, hidden: int, out_dim: int) -> nn.Sequential:
    """The paper's MLP: two fully connected layers with a ReLU between them."""
    return nn.Sequential(nn.Linear(in_dim, hidden), nn.ReLU(), nn.Linear(hidden, out_dim))


def plan_categories(actions: Tensor) -> Tensor:
    """Category index per step from contract plans ``(..., T, 16)`` -> ``(..., T)`` long.

    The torch twin of :func:`firp.core.contract.split_plan`'s first output (argmax of the one-hot).
    """
    return actions[..., :N_CATEGORIES].argmax(dim=-1)


def last_valid_index(mask: Tensor | None, T: int, batch: int, device: torch.device) -> Tensor:
    """Index of the last valid step per sequence ``(B,)``; valid steps must form a prefix."""
    if mask is None:
        return torch.full((batch,), T - 1, dtype=torch.long, device=device)
    return (mask.long().sum(dim=1) - 1).clamp_min(0)
