"""Robust least squares of the patches: Huber weights, the noise scale, Levenberg–Marquardt, and the model without the particle.

**Fit**: Levenberg–Marquardt on Huber-weighted residuals (the noise scale from the
residuals' median absolute deviation), every patch of a batch at once, each with its own
damping. **Uncertainties**: the residuals' pixel-to-pixel correlation inflates the
curvature's variances (`residual_inflation`): what model error and neighbours leave is not
white.
"""

from __future__ import annotations

import torch

from napari_lbs._core.foundation import Steps
from napari_lbs._core.refine._model import Model
from napari_lbs._core.refine._patches import Patches
from napari_lbs._core.refine._settings import RefineSettings


def robust_scale(residual: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Per-patch noise scale: 1.4826 × median absolute residual over real pixels."""
    absolute = torch.where(mask > 0, residual.abs(), torch.full_like(residual, float("nan")))
    return torch.clamp(1.4826 * torch.nanmedian(absolute, dim=1).values, min=1e-6)


def huber(residual: torch.Tensor, scale: torch.Tensor, mask: torch.Tensor, threshold: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Huber weights and robust cost (in units of the scale², per patch)."""
    t = residual.abs() / scale[:, None]
    weight = torch.where(t <= threshold, torch.ones_like(t), threshold / torch.clamp(t, min=1e-12)) * mask
    rho = torch.where(t <= threshold, 0.5 * t**2, threshold * t - 0.5 * threshold**2) * mask
    return weight, rho.sum(dim=1)


def clamp(params: torch.Tensor, low: torch.Tensor, high: torch.Tensor) -> torch.Tensor:
    return torch.maximum(torch.minimum(params, high), low)


def levenberg_marquardt(model: Model, params: torch.Tensor, free: torch.Tensor, low: torch.Tensor, high: torch.Tensor, *, scale: torch.Tensor,
                         settings: RefineSettings, iterations: int, steps: Steps | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Robust Levenberg–Marquardt on every patch at once; returns the parameters and their robust cost.

    Each patch keeps its own damping; a rejected step is retried, more damped, on the
    patches that rejected it only, and a patch whose cost fell by less than
    `_LM_TOLERANCE` (or `_LM_RELATIVE` of itself) in an iteration has converged and leaves the batch.
    """
    count = params.shape[0]
    params = params.clone()
    damping = torch.full((count,), 1e-3, dtype=torch.float64, device=params.device)
    cost = torch.zeros(count, dtype=torch.float64, device=params.device)
    active = torch.arange(count, device=params.device)
    for _ in range(iterations):
        if steps is not None:
            steps.check()
        sub = model if active.numel() == count else model.select(active)
        data, mask = sub.patches.data, sub.patches.mask
        p, f, s = params[active], free[active], scale[active]
        freef = f.to(torch.float64)
        prediction, jac = sub.jacobian(p, f)
        residual = data - prediction
        weight, current = huber(residual, s, mask, settings.huber)
        before = current.clone()
        jac = jac * freef[:, None, :]
        jtw = jac.transpose(1, 2) * weight[:, None, :]
        normal = jtw @ jac
        gradient = (jtw @ residual[:, :, None])[:, :, 0]
        diagonal = torch.diagonal(normal, dim1=1, dim2=2).clamp(min=1e-30)
        # fixed parameters: a unit diagonal and no gradient keep them where they are
        normal = normal + torch.diag_embed(torch.where(f, torch.zeros_like(diagonal), torch.ones_like(diagonal)))
        rows = torch.arange(active.numel(), device=params.device)
        lam = damping[active]
        for _attempt in range(4):
            system = normal[rows] + torch.diag_embed(lam[rows, None] * torch.where(f[rows], diagonal[rows], torch.zeros_like(diagonal[rows])))
            # solve_ex: no check of the result on the host (a wait for the device); a singular
            # system gives a non-finite step, which its patch rejects without evaluating it
            # (Lorenz–Mie theory has no sphere of NaN size)
            delta = torch.linalg.solve_ex(system, gradient[rows, :, None])[0][:, :, 0]
            trial = clamp(p[rows] + delta * freef[rows], low[active][rows], high[active][rows])
            finite = torch.isfinite(trial).all(dim=1)
            trial = torch.where(finite[:, None], trial, p[rows])
            subset = sub if rows.numel() == active.numel() else sub.select(rows)
            _, trial_cost = huber(data[rows] - subset(trial), s[rows], mask[rows], settings.huber)
            better = (trial_cost < current[rows]) & finite
            p[rows[better]] = trial[better]
            current[rows[better]] = trial_cost[better]
            lam[rows] = torch.where(better, lam[rows] * 0.3, lam[rows] * 10.0).clamp(1e-7, 1e7)
            rows = rows[~better]
            if rows.numel() == 0:
                break
        params[active] = p
        cost[active] = current
        damping[active] = lam
        # converged: the cost fell by less than a tenth of a noise variance, or 1e-4 of itself
        active = active[before - current >= torch.clamp(_LM_RELATIVE * before, min=_LM_TOLERANCE)]
        if active.numel() == 0:
            break
    return params, cost


_LM_TOLERANCE = 0.05  # half noise variances (Δχ² = 0.1)
_LM_RELATIVE = 1e-4


def residual_inflation(residual: torch.Tensor, mask: torch.Tensor, shapes: list[tuple[int, int]]) -> torch.Tensor:
    """Variance inflation ``(1+ρx)/(1-ρx) · (1+ρy)/(1-ρy)`` from the residuals' lag-1 correlations (≥ 1)."""
    out = []
    host = residual.cpu()  # one copy for the batch: the per-patch sums below then never wait for a device
    for i, (rows, cols) in enumerate(shapes):
        if rows < 3 or cols < 3:
            out.append(1.0)
            continue
        r = host[i, : rows * cols].reshape(rows, cols)
        r = r - r.mean()
        var = float((r * r).mean())
        if var <= 0:
            out.append(1.0)
            continue
        factor = 1.0
        for a, b in ((r[:, 1:], r[:, :-1]), (r[1:, :], r[:-1, :])):
            rho = min(max(float((a * b).mean()) / var, 0.0), 0.9)
            factor *= (1 + rho) / (1 - rho)
        out.append(factor)
    return torch.tensor(out, dtype=torch.float64, device=residual.device)


def flat_model(patches: Patches, others: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The model without the particle, least squares: its residual, noise scale and illumination (B, P).

    Without ``others`` the illumination alone; with them (`Model`'s, (4, B, P)) the
    illumination times the neighbours' hologram ``1 + Re others[0]``.
    """
    plane = torch.stack([patches.mask, patches.u * patches.mask, patches.v * patches.mask], dim=-1)
    basis = plane if others is None else plane * (1.0 + others[0].real)[:, :, None]
    # the normal equations, not `torch.linalg.lstsq`: LAPACK's least squares rounds by the
    # buffers' memory alignment, so one patch would fit differently from call to call
    normal = basis.transpose(1, 2) @ basis
    empty = torch.diagonal(normal, dim1=1, dim2=2) == 0.0  # a column no pixel reaches: held at 0
    normal = normal + torch.diag_embed(empty.to(normal.dtype))
    solution = torch.linalg.solve_ex(normal, basis.transpose(1, 2) @ (patches.data * patches.mask)[:, :, None])[0]
    residual = (patches.data - (basis @ solution)[:, :, 0]) * patches.mask
    return residual, robust_scale(residual, patches.mask), (plane @ solution)[:, :, 0]

