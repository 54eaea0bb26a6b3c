"""Searches on ring profiles: the symmetric centre, then depth, size and index from the patch's ring means.

A sphere's hologram averaged over the azimuth about its centre is exact from its radial
profiles (`azimuthal_mean_holograms`), and the data's ring means are one scatter-add: a
depth or size–index trial costs the rings (about half the patch edge), not the patch's
pixels. The illumination's linear terms average out over a ring.

**Searches**: about the patch's centre of symmetry (`symmetric_centres`), the ring means of
``I`` and ``I cos2φ`` (of the data less the neighbours' hologram) are exact functions of the
sphere's radial profiles, so the depth is scanned over ``±depth_window_um`` (steps that move
the outermost fringe by one radian), the size and index on a grid at the best depths, and
each start followed down its valley (`ring_search`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from napari_lbs._core.foundation import Steps
from napari_lbs._core.physics import mean_intensity, mie_coefficients, weighted_coefficients
from napari_lbs._core.refine._model import Model, scattered_terms
from napari_lbs._core.refine._patches import Patches
from napari_lbs._core.refine._settings import BOUNDS, RefineSettings

_CENTRE_REACH_PX = 3.0  # the symmetric centre is looked for this far around the guess
VALLEY_PRIOR = 16.0  # robust-cost units (half noise variances) per squared phase-delay period from the starting index
# size–index grid at each candidate depth: diameters around the start, and for each the
# index contrasts whose phase delay k0 d Δn steps through one period on each side
_GRID_DIAMETER_UM = tuple(0.4 * j for j in range(-9, 10))
_GRID_OUTER_DIAMETER_UM = tuple(0.4 * j for j in (*range(-20, -9), *range(10, 21)))  # where a best size lies on the grid's edge
_GRID_DELAY_PERIODS = tuple(j / 4 for j in range(-4, 5))


@dataclass
class Rings:
    """Ring means of a batch's patches about centres (rings one pixel wide, out to the patch's corners)."""

    data: torch.Tensor  # (B, R, 2) mean intensity and mean intensity × cos2φ
    weight: torch.Tensor  # (B, R) pixels per ring
    rho_um: torch.Tensor  # (B, R) their mean radius
    cos2: torch.Tensor  # (B, R) their mean cos2φ (0 on a whole ring)
    cos2_sq: torch.Tensor  # (B, R) their mean cos²2φ (1/2 on a whole ring)
    width_um: float

    def map(self, change) -> Rings:
        """The rings with ``change`` applied to every per-patch tensor (repeat, select)."""
        return Rings(change(self.data), change(self.weight), change(self.rho_um), change(self.cos2), change(self.cos2_sq), self.width_um)

    def model(self, moments: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Expected ring means (..., R) of ``I`` and ``I cos2φ`` from the model's moments (..., R, 2) (`azimuthal_mean_holograms`).

        The hologram is ``h0 + h2 cos2φ`` (``h2 = 2 ⟨I cos2φ⟩``), so over a ring's pixels, a
        whole ring or the arcs of a patch's corners, its means are ``h0 + h2 ⟨cos2φ⟩`` and
        ``h0 ⟨cos2φ⟩ + h2 ⟨cos²2φ⟩``.
        """
        h0, h2 = moments[..., 0], 2.0 * moments[..., 1]
        return h0 + h2 * self.cos2_like(h0), h0 * self.cos2_like(h0) + h2 * self.cos2_sq_like(h0)

    def cos2_like(self, like: torch.Tensor) -> torch.Tensor:
        return self.cos2.reshape(self.cos2.shape[0], *([1] * (like.dim() - 2)), -1)

    def cos2_sq_like(self, like: torch.Tensor) -> torch.Tensor:
        return self.cos2_sq.reshape(self.cos2_sq.shape[0], *([1] * (like.dim() - 2)), -1)


def symmetric_centres(residual: torch.Tensor, patches: Patches, guess_x: np.ndarray, guess_y: np.ndarray, *, pixel_um: float) -> tuple[np.ndarray, np.ndarray]:
    """Centres (µm) about which each patch is point-symmetric, near the guesses.

    A sphere's hologram is symmetric under ``(x, y) → (2c - x, 2c - y)`` (every term of the
    module docstring of `_lorenz_mie` is even in the azimuth), so the self-convolution of the
    patch peaks at ``2c`` (Cauchy–Schwarz). The patch is tapered about the current centre
    (neighbours and the border weigh less) and the peak found with sub-pixel parabolas,
    twice.
    """
    out_x, out_y = guess_x.copy(), guess_y.copy()
    # one copy to the host for the whole batch (the searches are numpy FFTs of each patch)
    residual_host, x_first, y_first = residual.cpu().numpy(), patches.x_um[:, 0].cpu().numpy(), patches.y_um[:, 0].cpu().numpy()
    for i, (rows, cols) in enumerate(patches.shape):
        if rows < 8 or cols < 8:
            continue
        image = residual_host[i, : rows * cols].reshape(rows, cols)
        x0, y0 = float(x_first[i]) / pixel_um, float(y_first[i]) / pixel_um
        guess = np.array([guess_x[i] / pixel_um - x0, guess_y[i] / pixel_um - y0])
        centre = guess.copy()
        yy, xx = np.mgrid[0:rows, 0:cols].astype(float)
        radius = 0.5 * min(rows, cols)
        for _ in range(2):
            rho = np.hypot(xx - centre[0], yy - centre[1]) / radius
            tapered = image * np.cos(0.5 * np.pi * np.minimum(rho, 1.0)) ** 2
            spectrum = np.fft.rfft2(tapered, s=(2 * rows, 2 * cols))
            conv = np.fft.irfft2(spectrum * spectrum, s=(2 * rows, 2 * cols))
            lo = np.floor(2 * (guess - _CENTRE_REACH_PX)).astype(int)
            hi = np.ceil(2 * (guess + _CENTRE_REACH_PX)).astype(int)
            lo = np.maximum(lo, 1)
            hi = np.minimum(hi, np.array([2 * cols - 2, 2 * rows - 2]))
            if np.any(hi < lo):
                break
            region = conv[lo[1] : hi[1] + 1, lo[0] : hi[0] + 1]
            my, mx = np.unravel_index(int(np.argmax(region)), region.shape)
            my, mx = my + lo[1], mx + lo[0]
            peak = np.array([mx, my], dtype=float)
            for axis, (minus, mid, plus) in enumerate(((conv[my, mx - 1], conv[my, mx], conv[my, mx + 1]), (conv[my - 1, mx], conv[my, mx], conv[my + 1, mx]))):
                curvature = minus - 2.0 * mid + plus
                if curvature < 0:
                    peak[axis] += float(np.clip(0.5 * (minus - plus) / curvature, -0.5, 0.5))
            centre = peak / 2.0
        out_x[i] = (centre[0] + x0) * pixel_um
        out_y[i] = (centre[1] + y0) * pixel_um
    return out_x, out_y


def cut_rings(patches: Patches, centre_x: torch.Tensor, centre_y: torch.Tensor, *, pixel_um: float) -> Rings:
    """Ring means (`Rings`) of each patch about its centre, every pixel of the patch in one ring."""
    dx = patches.x_um - centre_x[:, None]
    dy = patches.y_um - centre_y[:, None]
    rho2 = dx**2 + dy**2
    rho = torch.sqrt(rho2)
    cos2 = torch.where(rho2 > 0, (dx**2 - dy**2) / torch.clamp(rho2, min=1e-30), torch.zeros_like(rho2))
    keep = patches.mask
    width = pixel_um
    count = max(1, math.ceil(float((rho * keep).max()) / width) + 1)
    ring = torch.clamp((rho / width).long(), max=count - 1)
    zeros = torch.zeros((rho.shape[0], count), dtype=torch.float64, device=rho.device)
    sums = [zeros.scatter_add(1, ring, keep * values) for values in (torch.ones_like(rho), patches.data, patches.data * cos2, rho, cos2, cos2 * cos2)]
    weight = sums[0]
    safe = torch.clamp(weight, min=1.0)
    centres = (torch.arange(count, dtype=torch.float64, device=rho.device) + 0.5) * width
    rho_mean = torch.where(weight > 0, sums[3] / safe, centres.expand_as(weight))
    cos2_sq = torch.where(weight > 0, sums[5] / safe, torch.full_like(weight, 0.5))
    return Rings(torch.stack([sums[1] / safe, sums[2] / safe], dim=-1), weight, torch.clamp(rho_mean, min=1e-3), sums[4] / safe,
                  torch.clamp(cos2_sq, min=1e-3), width)


def _ring_fit_terms(rings: Rings, moments: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Weighted data and model of the rings: ``(√w0 D0, √w2 D2, √w0 M0, √w2 M2)``, each (..., R), ``w`` their inverse variances over σ²."""
    m0, m2 = rings.model(moments)
    shape = (rings.weight.shape[0], *([1] * (m0.dim() - 2)), -1)
    w0 = torch.sqrt(rings.weight).reshape(shape)
    w2 = torch.sqrt(rings.weight / rings.cos2_sq).reshape(shape)
    d0 = rings.data[..., 0].reshape(shape)
    d2 = rings.data[..., 1].reshape(shape)
    return w0 * d0, w2 * d2, w0 * m0, w2 * m2


def ring_costs(rings: Rings, z_um: torch.Tensor, spheres: torch.Tensor, scale: torch.Tensor, *, model: Model) -> torch.Tensor:
    """Cost (B, Z, S), in half noise variances, of S spheres (diameter, index contrast, κ) at each of Z depths per patch.

    Each with its best brightness ``c0`` (least squares): ``½ Σ_rings w (D - c0 M)² / σ²``
    over both ring means (`Rings.model`), ``w`` their inverse variances in units of the
    pixel noise σ², so differences are χ² differences of the patch.
    """
    k = 2.0 * math.pi * model.optics["medium_index"] / model.optics["wavelength_um"]
    medium = model.optics["medium_index"]
    count, depths = z_um.shape
    sets = spheres.shape[1]
    radii = rings.rho_um.shape[1]
    size = (k * spheres[..., 0] / 2.0).reshape(-1)
    relative = ((medium + spheres[..., 1]) + 1j * spheres[..., 2]).reshape(-1) / medium
    a, b = mie_coefficients(size, relative, terms=model.terms)
    a_eff, b_eff = (t.reshape(count, 1, sets, model.terms) for t in weighted_coefficients(a, b))
    per = max(1, int(_RING_BLOCK // max(1, depths * sets * radii)))
    out = []
    for first in range(0, count, per):
        part = slice(first, first + per)
        moments = mean_intensity(a_eff[part], b_eff[part], z_um[part], rings.rho_um[part, None, :].expand(-1, depths, -1), k=k,
                                  pixel_um=model.pixel_um, annulus_um=rings.width_um,
                                  lobe_diameter_um=spheres[part, :, 0].amax(dim=1)[:, None])  # (b, Z, S, R, 2)
        sub = rings.map(lambda t, part=part: t[part])
        d0, d2, m0, m2 = _ring_fit_terms(sub, moments)
        cross = (d0 * m0 + d2 * m2).sum(dim=-1)
        square = torch.clamp((m0 * m0 + m2 * m2).sum(dim=-1), min=1e-30)
        total = (d0 * d0 + d2 * d2).sum(dim=-1)
        out.append(0.5 * torch.clamp(total - cross**2 / square, min=0.0) / scale[part, None, None] ** 2)
    return torch.cat(out, dim=0)


_RING_BLOCK = 1.5e6  # ring samples per chunk of `ring_costs` (memory)


def _ring_residuals(rings: Rings, z_um: torch.Tensor, spheres: torch.Tensor, scale: torch.Tensor, *, model: Model) -> torch.Tensor:
    """Whitened ring residuals (B, R) of one sphere (diameter, index contrast, κ) per patch at its depth (B,), its brightness fitted."""
    k = 2.0 * math.pi * model.optics["medium_index"] / model.optics["wavelength_um"]
    medium = model.optics["medium_index"]
    count = z_um.shape[0]
    a, b = mie_coefficients(k * spheres[:, 0] / 2.0, ((medium + spheres[:, 1]) + 1j * spheres[:, 2]) / medium, terms=model.terms)
    a_eff, b_eff = (t.reshape(count, 1, model.terms) for t in weighted_coefficients(a, b))
    moments = mean_intensity(a_eff, b_eff, z_um, rings.rho_um, k=k, pixel_um=model.pixel_um, annulus_um=rings.width_um,
                              lobe_diameter_um=spheres[:, 0])[:, 0]  # (B, R, 2)
    d0, d2, m0, m2 = _ring_fit_terms(rings, moments)
    c0 = (d0 * m0 + d2 * m2).sum(dim=1) / torch.clamp((m0 * m0 + m2 * m2).sum(dim=1), min=1e-30)
    return torch.cat([d0 - c0[:, None] * m0, d2 - c0[:, None] * m2], dim=1) / scale[:, None]


def _ring_fit(rings: Rings, start: torch.Tensor, free: torch.Tensor, kappa: torch.Tensor, scale: torch.Tensor, low: torch.Tensor, high: torch.Tensor, *,
              model: Model, iterations: int, depth_reach_um: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Gauss–Newton of (z, d, Δn) (B, 3) on the ring residuals; returns them and their cost (half-variances).

    The depth and size trade off along a diagonal valley of the ring cost (a larger sphere
    farther away), which a grid cut along the axes misses: the fit follows it. The
    derivatives are secants over the ripple (`Model.jacobian`'s envelope: ``Δ(k a) = ±0.5``,
    ``Δ(m x) = ±0.5``; depth ±0.5 µm), so the fit follows the valley's envelope and the
    valley profile then picks among its ripples.
    """
    count = start.shape[0]
    params = start.clone()
    freef = free.to(torch.float64)
    k_m = 2.0 * math.pi * model.optics["medium_index"] / model.optics["wavelength_um"]

    def residuals(p: torch.Tensor, rows: int) -> torch.Tensor:
        grow = lambda t: t.repeat(rows // count, *([1] * (t.dim() - 1)))
        ring_rows = rings.map(grow)
        return _ring_residuals(ring_rows, p[:, 0], torch.stack([p[:, 1], p[:, 2], grow(kappa)], dim=-1), grow(scale), model=model)

    best = params.clone()
    best_cost = torch.full((count,), math.inf, dtype=torch.float64, device=start.device)
    for _ in range(iterations):
        steps = torch.stack([torch.full_like(params[:, 0], 0.5), torch.full_like(params[:, 0], 1.0 / k_m),
                             0.5 * model.optics["medium_index"] / (k_m * params[:, 1] / 2.0)], dim=-1)  # (B, 3), each way
        stacked = params.repeat(7, 1)
        for axis in range(3):
            stacked[(2 * axis + 1) * count : (2 * axis + 2) * count, axis] += steps[:, axis]
            stacked[(2 * axis + 2) * count : (2 * axis + 3) * count, axis] -= steps[:, axis]
        res = residuals(stacked, 7 * count).reshape(7, count, -1)
        # the stencil's mean residual and cost: the envelope, the ripple averaged out. A
        # stencil point past a bound of physics (a size or index below zero beside a sphere
        # of 0.05 µm) has no finite hologram: its NaN cost is never the best, its step none
        base = res.mean(dim=0)
        cost = 0.5 * (res**2).sum(dim=2).mean(dim=0)
        jac = torch.stack([(res[2 * axis + 1] - res[2 * axis + 2]) / (2.0 * steps[:, axis:axis + 1]) for axis in range(3)], dim=-1) * freef[:, None, :]
        better = cost < best_cost
        best_cost = torch.where(better, cost, best_cost)
        best = torch.where(better[:, None], params, best)
        normal = jac.transpose(1, 2) @ jac
        gradient = -(jac.transpose(1, 2) @ base[:, :, None])[:, :, 0]
        diagonal = torch.diagonal(normal, dim1=1, dim2=2).clamp(min=1e-30)
        normal = normal + torch.diag_embed(torch.where(free, _RING_DAMPING * diagonal, torch.ones_like(diagonal)))
        # Gauss–Newton on the envelope, every step taken (the ripple would reject good ones),
        # each at most a few secant widths; the best point visited is kept
        delta = torch.linalg.solve_ex(normal, gradient[:, :, None])[0][:, :, 0] * freef  # no host check (`levenberg_marquardt`)
        reach = _RING_REACH * steps
        reach[:, 0] = depth_reach_um
        delta = torch.maximum(torch.minimum(torch.nan_to_num(delta, nan=0.0, posinf=0.0, neginf=0.0), reach), -reach)
        params = torch.maximum(torch.minimum(params + delta, high), low)
    return best, best_cost


_RING_DAMPING = 1e-4
_RING_REACH = 4.0  # largest Gauss–Newton step of size and index, in secant widths (Δ(k a) = 2)


def ring_depth_step(rings: Rings, z_um: torch.Tensor, *, window_um: float, k: float, pixel_um: float) -> float:
    """Depth step (µm) that moves the outermost ring's fringe (phase k ρ²/2z) by one radian at the nearest depth scanned."""
    rho_max = float(torch.max(torch.where(rings.weight > 0, rings.rho_um, torch.zeros_like(rings.rho_um))))
    nearest = float(torch.clamp(z_um - window_um, min=0.1 * max(window_um, 1.0)).min())
    return max(2.0 * nearest**2 / (k * max(rho_max, pixel_um) ** 2), 0.5 * pixel_um)


def _parabola_vertex(costs: torch.Tensor, best: torch.Tensor) -> torch.Tensor:
    """Sub-sample offset (-0.5 … 0.5) of the minimum of (B, T) costs near their samples ``best`` (B,)."""
    last = costs.shape[1] - 1
    rows = torch.arange(costs.shape[0], device=costs.device)
    inner = torch.clamp(best, 1, max(last - 1, 1))
    if last < 2:
        return torch.zeros_like(costs[:, 0])
    minus, mid, plus = costs[rows, inner - 1], costs[rows, inner], costs[rows, inner + 1]
    curvature = minus - 2.0 * mid + plus
    vertex = torch.where(curvature > 0, 0.5 * (minus - plus) / torch.clamp(curvature, min=1e-30), torch.zeros_like(mid))
    return torch.clamp(vertex + (inner - best), -0.5, 0.5)


def ring_dof(rings: Rings) -> torch.Tensor:
    """(B,) degrees of freedom of a sphere's ring fit: both ring means of every ring with pixels, less the fitted c0, depth, delay and size (at least 1)."""
    return torch.clamp(2.0 * (rings.weight > 0).sum(dim=1).to(torch.float64) - 4.0, min=1.0)


def depth_prior(z_um: torch.Tensor, start_depth_um: torch.Tensor, prior_um: float) -> torch.Tensor:
    """Cost (half noise variances) of depths ``z_um`` (B, ...) under a Laplace prior of median ``|Δz|`` ``prior_um`` about the guesses ``start_depth_um`` (B,); zero where ``prior_um`` is 0."""
    if prior_um <= 0:
        return torch.zeros_like(z_um)
    return math.log(2.0) * (z_um - start_depth_um.reshape(-1, *([1] * (z_um.dim() - 1)))).abs() / prior_um


def ring_search(rings: Rings, params: torch.Tensor, free: torch.Tensor, scale: torch.Tensor, *, model: Model, window_um: float,
                 start_index: torch.Tensor, start_depth: torch.Tensor, depth_prior_um: float, settings: RefineSettings, steps: Steps) -> torch.Tensor:
    """Depth, diameter and index contrast (B, 3) from the ring profiles: depth scan, size–index grid, fine depth scan.

    The depth is scanned over ``±window_um`` in steps that move the outermost ring's fringe
    by one radian; its ``depth_candidates`` best local minima are refined by a scan a
    quarter step apart; at each, diameters ±3.6 µm (±8 µm where the best lies on that
    grid's edge) and index contrasts one phase-delay period on each side (quarter periods)
    are compared, the valleys away from the starting index paying `VALLEY_PRIOR` per
    period²; at the best, the depth is scanned finely again. With a ``depth_prior_um``, the
    guess itself starts a fit too, and depths away from the guesses ``start_depth`` (µm in
    the medium) pay `depth_prior` in the scan's ranking and the final choice, there in units
    of the rings' own scatter (the best fit's χ² per degree of freedom, at least 1).
    """
    k = 2.0 * math.pi * model.optics["medium_index"] / model.optics["wavelength_um"]
    wavelength = model.optics["wavelength_um"]
    count = params.shape[0]
    device = params.device
    z, d, n, kappa = params[:, 2].clone(), params[:, 3].clone(), params[:, 4].clone(), params[:, 5]
    step = ring_depth_step(rings, z, window_um=window_um, k=k, pixel_um=model.pixel_um or 1.0)
    fine = torch.arange(-6, 7, dtype=torch.float64, device=device) * (step / 4.0)

    def refine_depth(depths: torch.Tensor, spheres: torch.Tensor) -> torch.Tensor:  # (B, K) depths, (B, K, 3) spheres
        kk = depths.shape[1]
        trials = torch.clamp(depths[:, :, None] + fine, min=1.0).reshape(count * kk, -1)
        rows = lambda t: t.repeat_interleave(kk, dim=0)
        ring_rows = rings.map(rows)
        costs = ring_costs(ring_rows, trials, spheres.reshape(count * kk, 1, 3), rows(scale), model=model)[:, :, 0]
        best = torch.argmin(costs, dim=1)
        offset = _parabola_vertex(costs, best)
        chosen = trials[torch.arange(trials.shape[0], device=device), best] + offset * (step / 4.0)
        return torch.where(free[:, 2:3], chosen.reshape(count, kk), depths)

    here = torch.stack([d, n, kappa], dim=-1)[:, None, :]
    depths = z[:, None]
    if bool(free[:, 2].any()):
        offsets = torch.arange(-window_um, window_um + 0.5 * step, step, dtype=torch.float64, device=device)
        trials = torch.where(free[:, 2:3], torch.clamp(z[:, None] + offsets, min=1.0), z[:, None])
        costs = ring_costs(rings, trials, here, scale, model=model)[:, :, 0]
        steps.check()
        pick = _best(costs + depth_prior(trials, start_depth, depth_prior_um), settings.depth_candidates, local=True)
        depths = refine_depth(torch.gather(trials, 1, pick), here.expand(-1, pick.shape[1], -1))
    kk = depths.shape[1]
    candidates = torch.stack([depths, d[:, None].expand(-1, kk), n[:, None].expand(-1, kk)], dim=-1)  # (B, K, 3)
    if bool(free[:, 3].any() or free[:, 4].any()):
        delays = torch.tensor(_GRID_DELAY_PERIODS, dtype=torch.float64, device=device) * wavelength

        def grid(offsets_um) -> tuple[torch.Tensor, torch.Tensor]:
            """The spheres (B, S, 3) of the size–index grid at diameter offsets ``offsets_um`` and their costs (B, K, S), valley prior included."""
            d_steps = torch.tensor(offsets_um, dtype=torch.float64, device=device)
            diameters = torch.where(free[:, 3:4], torch.clamp(d[:, None] + d_steps, min=BOUNDS["diameter_um"][0]), d[:, None])  # (B, D)
            contrasts = torch.where(free[:, 4:5, None], ((d * n)[:, None, None] + delays) / diameters[:, :, None], n[:, None, None])  # (B, D, N)
            spheres = torch.stack([diameters[:, :, None].expand_as(contrasts), contrasts, kappa[:, None, None].expand_as(contrasts)], dim=-1).reshape(count, -1, 3)
            steps.check()
            costs = ring_costs(rings, depths, spheres, scale, model=model)  # (B, K, S)
            valleys = (spheres[:, :, 1] - start_index[:, None]) / (wavelength / spheres[:, :, 0])
            return spheres, costs + VALLEY_PRIOR * (valleys**2 * free[:, 4:5].to(torch.float64))[:, None, :]

        spheres, costs = grid(_GRID_DIAMETER_UM)
        best = torch.argmin(costs, dim=2)  # (B, K)
        chosen = torch.gather(spheres, 1, best[:, :, None].expand(-1, -1, 3))
        # a best size on the grid's edge lies beyond it (a network's guess for a size it never
        # saw is up to 8 µm off): the outer grid too, for the batch
        edge = free[:, 3:4] & ((chosen[:, :, 0] - d[:, None]).abs() >= max(_GRID_DIAMETER_UM) - 1e-9)
        if bool(edge.any()):
            model = model.with_terms(scattered_terms(float(d.max()) + max(_GRID_OUTER_DIAMETER_UM), **model.optics))
            outer_spheres, outer_costs = grid(_GRID_OUTER_DIAMETER_UM)
            outer_best = torch.argmin(outer_costs, dim=2)
            # only a candidate whose best size lay on the edge moves: a fit does not depend on its batch-mates
            better = edge & (torch.gather(outer_costs, 2, outer_best[:, :, None])[:, :, 0] < torch.gather(costs, 2, best[:, :, None])[:, :, 0])
            chosen = torch.where(better[:, :, None], torch.gather(outer_spheres, 1, outer_best[:, :, None].expand(-1, -1, 3)), chosen)
        candidates = torch.stack([depths, chosen[:, :, 0], chosen[:, :, 1]], dim=-1)
    if depth_prior_um > 0:  # the guess itself starts a fit too: the scan's minima may all be its neighbours' fringes
        candidates = torch.cat([candidates, torch.stack([z, d, n], dim=-1)[:, None, :]], dim=1)
        kk += 1
    # every candidate followed down its valley, then the best (the valley prior as above)
    grow = lambda t: t.repeat_interleave(kk, dim=0)
    flat_free = grow(free[:, 2:5])
    low = grow(torch.stack([torch.clamp(z - 1.5 * window_um, min=1.0), torch.full_like(z, BOUNDS["diameter_um"][0]),
                            torch.full_like(z, BOUNDS["index_contrast"][0])], dim=-1))
    high = grow(torch.stack([z + 1.5 * window_um, torch.full_like(z, BOUNDS["diameter_um"][1]), torch.full_like(z, BOUNDS["index_contrast"][1])], dim=-1))
    ring_rows = rings.map(grow)
    steps.check()
    fitted, cost = _ring_fit(ring_rows, candidates.reshape(count * kk, 3), flat_free, grow(kappa), grow(scale), low, high, model=model,
                             iterations=_RING_ITERATIONS, depth_reach_um=step / 2.0)
    valleys = (fitted[:, 2] - grow(start_index)) / (wavelength / fitted[:, 1])
    if depth_prior_um > 0:
        # the depth prior in units of the rings' own scatter: neighbours' fringes make the ring
        # means scatter by more than the pixel noise, by the best fit's χ² per degree of freedom
        excess = torch.clamp(cost.reshape(count, kk).amin(dim=1) / (0.5 * ring_dof(rings)), min=1.0)
        cost = cost + grow(excess) * depth_prior(fitted[:, 0], grow(start_depth), depth_prior_um) * flat_free[:, 0]
    cost = cost + VALLEY_PRIOR * valleys**2 * flat_free[:, 2].to(torch.float64)
    best = torch.argmin(cost.reshape(count, kk), dim=1)
    return fitted[torch.arange(count, device=device) * kk + best]


_RING_ITERATIONS = 8


def _best(costs: torch.Tensor, count: int, *, local: bool) -> torch.Tensor:
    """Indices (B, count) of the lowest costs, local minima along the last axis first when ``local``."""
    ranked = costs
    if local:
        padded = torch.nn.functional.pad(costs[:, None, :], (1, 1), mode="replicate")[:, 0]
        minima = (costs <= padded[:, :-2]) & (costs <= padded[:, 2:])
        ranked = torch.where(minima, costs, costs + costs.abs().max() + 1.0)
    return torch.argsort(ranked, dim=1)[:, : min(count, costs.shape[1])]
