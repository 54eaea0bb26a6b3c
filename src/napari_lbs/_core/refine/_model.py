"""The forward model of a batch of patches: each sphere's Lorenz–Mie hologram, its neighbours' fields and the illumination, and its Jacobian.

The hologram of a sphere is the exact Lorenz–Mie one (`napari_lbs._core.physics`'s
`radial_profiles`, Lee et al. 2007), times a smooth illumination ``c0 + c1 u + c2 v`` over
the patch (the beam's envelope; ``u, v`` the patch coordinates in -1 … 1). The Jacobian is
by finite differences of the differentiable forward model, every perturbation in one
batch; its lateral columns are analytic.
"""

from __future__ import annotations

import math
from dataclasses import fields

import torch

from napari_lbs._core.physics import fields_from_profiles, holograms_from_fields, lateral_derivatives, radial_profiles, radial_step, term_count
from napari_lbs._core.refine._patches import Patches
from napari_lbs._core.refine._settings import PHYSICAL

_FIT_SAMPLES_PER_LOBE = 6  # radial samples per scattering lobe in the fit (see radial_step)
# Finite-difference steps of the Jacobian's depth-like columns (z µm, diameter µm, index, κ):
# far below every parameter's precision and far above round-off in complex128.
_JACOBIAN_STEPS = {2: 1e-3, 3: 1e-5, 4: 1e-7, 5: 1e-7}


class Model:
    """The patch model ``(c0 + c1 u + c2 v) · |x̂ + E(θ) + E_others|²`` of a batch, and its Jacobian.

    ``others``: None, or (4, B, P) complex: the neighbours' hologram minus 1 (real part of
    row 0) and their summed fields ``E_x, E_y, E_z`` (rows 1-3), fixed; the particle's own
    field adds to theirs (``2 Re(E · E_others*)``), so overlapping particles shadow and
    interfere as fields do.
    """

    def __init__(self, patches: Patches, others: torch.Tensor | None, *, wavelength_um: float, medium_index: float, pixel_um: float | None, terms: int) -> None:
        self.patches = patches
        self.others = others
        self.optics = {"wavelength_um": wavelength_um, "medium_index": medium_index}
        self.pixel_um = pixel_um
        self.terms = terms

    def _profiles(self, params: torch.Tensor, *, step: torch.Tensor | None = None) -> tuple[torch.Tensor, ...]:
        """``(profiles, step, dx, dy, z)`` of K stacked copies of the batch's parameters (K·B rows), which share the first copy's centre."""
        x, y, z, d, dn, kappa = params[:, :PHYSICAL].unbind(-1)
        p = self.patches
        count = p.x_um.shape[0]
        copies = params.shape[0] // count
        dx, dy = p.x_um - x[:count, None], p.y_um - y[:count, None]
        rho_max = float(torch.sqrt(dx**2 + dy**2).max())
        if step is None:
            step = radial_step(z[:count], d[:count], samples_per_lobe=_FIT_SAMPLES_PER_LOBE, **self.optics)
        # copies at the same depths share the partial-wave sums' angular and radial functions
        depths = z.reshape(copies, count)
        groups: list[list[int]] = []
        for copy in range(copies):
            group = next((g for g in groups if torch.equal(depths[g[0]], depths[copy])), None)
            if group is None:
                groups.append([copy])
            else:
                group.append(copy)
        parts = {}
        for group in groups:
            spheres = [t.reshape(copies, count)[group] for t in (d, dn, kappa)]
            profiles, _ = radial_profiles(depths[group[0]], *spheres, rho_max_um=rho_max, terms=self.terms, radial_step_um=step, **self.optics)
            parts.update({copy: profiles[:, j * count : (j + 1) * count] for j, copy in enumerate(group)})
        return torch.cat([parts[copy] for copy in range(copies)], dim=1), step, dx, dy, z

    def _holograms(self, profiles: torch.Tensor, step: torch.Tensor, dx: torch.Tensor, dy: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        fields = fields_from_profiles(profiles, step, dx, dy, z, **self.optics)
        own = holograms_from_fields(fields, dx, dy, z, pixel_um=self.pixel_um, **self.optics)
        if self.others is None:
            return own
        others = self.others.repeat(1, z.shape[0] // dx.shape[0], 1)
        cross = sum(f * o.conj() for f, o in zip(fields, others[1:], strict=True))
        return own + others[0].real + 2.0 * cross.real

    def sphere(self, params: torch.Tensor, *, step: torch.Tensor | None = None) -> torch.Tensor:
        """Holograms (K·B, P) of K stacked copies of the batch's parameters (K·B rows); the copies share the first one's centre."""
        return self._holograms(*self._profiles(params, step=step))

    def with_terms(self, terms: int) -> Model:
        """The same model summing at least ``terms`` partial waves (for larger spheres than it was made for)."""
        return self if terms <= self.terms else Model(self.patches, self.others, pixel_um=self.pixel_um, terms=terms, **self.optics)

    def select(self, rows: torch.Tensor) -> Model:
        """The model of some of the batch's patches (their rows)."""
        p = self.patches
        patches = Patches(*(getattr(p, f.name)[rows] for f in fields(Patches) if f.name != "shape"), shape=[p.shape[i] for i in rows.tolist()])
        others = None if self.others is None else self.others[:, rows]
        return Model(patches, others, pixel_um=self.pixel_um, terms=self.terms, **self.optics)

    def illumination(self, params: torch.Tensor) -> torch.Tensor:
        c = params[:, PHYSICAL:]
        return c[:, :1] + c[:, 1:2] * self.patches.u + c[:, 2:3] * self.patches.v

    def __call__(self, params: torch.Tensor) -> torch.Tensor:
        return self.illumination(params) * self.sphere(params)

    def jacobian(self, params: torch.Tensor, free: torch.Tensor, *, envelope: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
        """``(model, J)``: (B, P) and (B, P, 9); columns of parameters fixed everywhere are zero.

        The depth, size, index and absorption columns are finite differences of the
        differentiable model with every perturbation stacked in one batch: its partial-wave
        recurrences then run once for all of them (forward-mode differentiation pays their
        per-operation overhead once per parameter: measured 60 times slower), and the
        perturbed copies share the pixels' interpolation weights. The lateral columns are
        analytic (`lateral_derivatives`).

        With ``envelope`` the diameter and index columns are central differences over a
        size parameter (``Δ(k a) = ±0.5``, ``Δ(m x) = ±0.5``): a transparent sphere's
        hologram ripples with its size and index (morphology-dependent resonances, spaced
        ``Δ(k a) ≈ 0.2`` at k a ≈ 150, measured), so the local curvature promises a
        precision that only the ripple supports; the secant over the ripple measures the
        envelope's.
        """
        count = params.shape[0]
        k_m = 2.0 * math.pi * self.optics["medium_index"] / self.optics["wavelength_um"]
        depth_like = [k for k in range(2, PHYSICAL) if bool(free[:, k].any())]
        steps = {k: torch.full((count,), _JACOBIAN_STEPS[k], dtype=torch.float64, device=params.device) for k in depth_like}
        central = [k for k in (3, 4) if envelope and k in depth_like]
        if 3 in central:
            steps[3] = torch.full_like(steps[3], 1.0 / k_m)  # Δ(k a) = 0.5 each way
        if 4 in central:
            steps[4] = 0.5 * self.optics["medium_index"] / (k_m * params[:, 3] / 2.0)  # Δ(m x) = 0.5 each way
        signs = [(k, 1.0) for k in depth_like] + [(k, -1.0) for k in central]
        stacked = params.repeat(1 + len(signs), 1)
        for slot, (k, sign) in enumerate(signs, start=1):
            stacked[slot * count : (slot + 1) * count, k] += sign * steps[k]
        # one radial grid per particle for all its perturbations: the differences see the model, not a moved grid
        step = radial_step(params[:, 2], params[:, 3], samples_per_lobe=_FIT_SAMPLES_PER_LOBE, **self.optics)
        profiles, step, dx, dy, z = self._profiles(stacked, step=step)
        holograms = self._holograms(profiles, step, dx, dy, z).reshape(1 + len(signs), count, -1)
        base = holograms[0]
        gain = self.illumination(params)
        columns = [torch.zeros_like(base)] * PHYSICAL
        if bool(free[:, :2].any()):
            others = None if self.others is None else tuple(self.others[1:])
            along_x, along_y = lateral_derivatives(profiles[:, :count], step, dx, dy, z[:count], others=others, pixel_um=self.pixel_um, **self.optics)
            # the pattern moves with the particle: moving the points by +h is moving the particle by -h
            columns[0], columns[1] = -along_x * gain, -along_y * gain
        for slot, (k, sign) in enumerate(signs, start=1):
            if sign < 0:
                continue
            lower = holograms[1 + len(depth_like) + central.index(k)] if k in central else base
            width = steps[k] * (2.0 if k in central else 1.0)
            columns[k] = (holograms[slot] - lower) * (gain / width[:, None])
        p = self.patches
        return gain * base, torch.stack(columns + [base, base * p.u, base * p.v], dim=-1)



def scattered_terms(diameter_um: float, *, wavelength_um: float, medium_index: float) -> int:
    """Partial waves for spheres up to ``diameter_um``: Wiscombe's count for one 15 % larger.

    A fit moves a sphere's size by a few per cent past its start; at the count's own size the
    coefficients left out change the hologram by less than 2e-9, 2 µm beyond it by up to 4e-3
    (measured, 30-44 µm polystyrene in water). The |m x| floor of `term_count` concerns the
    internal field, not the scattered one.
    """
    return term_count(math.pi * medium_index / wavelength_um * diameter_um * 1.15, 1.0)
