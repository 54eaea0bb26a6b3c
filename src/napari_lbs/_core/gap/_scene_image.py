"""The hologram of a frame's fitted particles, whole and in depth groups, and the blurs that act on it by depth.

The scene diagnosis judges every effect around this image (`_nested`): a source's size blurs
each depth group by its own depth (`Scene.coherent_blur`), a spectrum's width washes each
group's fringes out with their order and depth (`Scene.spectral_blur`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from napari_lbs._core.physics import gaussian_blur

__all__ = ["Scene"]


@dataclass(frozen=True)
class Scene:
    """The hologram of the frame's fitted particles, whole and in depth groups.

    Attributes
    ----------
    image : (rows, cols) array
        Every particle rendered together (unobstructed light 1).
    depths_um : tuple of float
        Each group's mean depth (µm, the config's convention).
    groups : (groups, rows, cols) array
        Each group's particles rendered alone, less 1: what a depth-dependent effect acts on.
    pixel_um : float
        Pixel pitch (µm).
    """

    image: np.ndarray = field(repr=False)
    depths_um: tuple[float, ...] = ()
    groups: np.ndarray | None = field(default=None, repr=False)
    pixel_um: float = 1.0

    @classmethod
    def of(cls, scene) -> "Scene":
        """``scene`` as a `Scene`; an array is a scene without depth groups."""
        return scene if isinstance(scene, Scene) else cls(np.asarray(scene, np.float64))

    def coherent_blur(self, theta_mrad: float) -> np.ndarray:
        """The scene with each depth group blurred by σ = θ·z (a source of angular size θ)."""
        image = self.image.astype(np.float32)
        if theta_mrad <= 0 or self.groups is None:
            return image
        image = image.copy()
        for depth, group in zip(self.depths_um, self.groups, strict=True):
            sigma_px = theta_mrad * 1e-3 * depth / self.pixel_um
            image += gaussian_blur(group, sigma_px) - group
        return image

    def spectral_blur(self, bandwidth_nm: float) -> np.ndarray:
        """The scene with each depth group's fringes washed out by a spectrum of full width ``bandwidth_nm`` at half maximum.

        A Gaussian spectrum of standard deviation σ_λ averages each group's fringes over the
        wavelengths, which in Fresnel's transfer function ``exp(iπλzf²)`` is the factor
        ``exp(−½ (π σ_λ z f²)²)`` on the group's spectrum (f in cycles per µm, z the group's
        depth in the config's convention): a fringe fades with its order, f⁴, and with depth,
        where a sensor's blur takes f² from every depth alike (`superpose` simulates with
        the same law).
        """
        image = self.image.astype(np.float32)
        if bandwidth_nm <= 0 or self.groups is None:
            return image
        image = image.copy()
        f2 = np.fft.fftfreq(image.shape[0], self.pixel_um)[:, None] ** 2 + np.fft.fftfreq(image.shape[1], self.pixel_um)[None, :] ** 2
        sigma_um = bandwidth_nm * 1e-3 / (2.0 * np.sqrt(2.0 * np.log(2.0)))
        for depth, group in zip(self.depths_um, self.groups, strict=True):
            washed = np.fft.irfft2(np.fft.rfft2(group) * np.exp(-0.5 * (np.pi * sigma_um * depth * f2[:, : group.shape[1] // 2 + 1]) ** 2), s=group.shape)
            image += (washed - group).astype(np.float32)
        return image
