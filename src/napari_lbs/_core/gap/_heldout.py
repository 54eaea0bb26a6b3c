"""The held-out likelihood a nested model is scored by: fitted on half of the frame's tiles, judged on the other half.

The frame is cut into a grid of square tiles coloured like a checkerboard. A model's
parameters are fitted on the tiles of one colour and its residual judged on the other
(and the other way round), so an effect that fits noise or one tile's accident gains
nothing where it was not fitted.

The noise is what the model leaves: a stationary Gaussian field judged tile by tile with
Whittle's log-likelihood, ``-½ Σ_f (|R(f)|² / P(f) + ln P(f))`` over the 2-D frequencies of
the tile's tapered residual (Whittle, 1953), whose spectrum ``P`` is the judged tile's own,
one level per radial frequency bin (`RADIAL_BINS` up to the Nyquist frequency) at its most
likely value, the tile's mean ``|R(f)|²`` over the bin. The tile's log-likelihood is then
``-½ Σ_b n_b (1 + ln mean_b |R|²)``: a model gains where it lowers the residual's power in
a band, by the log of how much, whatever the other bands hold. The structure the experiment
holds beyond every model (debris, dust, a speckled background) is thereby part of each
tile's own noise instead of swamping every comparison.

Tiles differ in how much of the particles' misfit they hold (a pair fitted as one leaves
ten times the residual of a tile of lone spheres), and in which bands. Judged against a
spectrum estimated from the fitted tiles, a tile of misfit lost thousands of nats to a model
that rightly took a structure out of every tile, since that structure had raised the
spectrum its misfit was judged against: a straight fringe at its frequency (against one
level per tile over a shared spectrum's shape: summed gains of −4 200 and −1 800 nats for
fringes fitted to within 0.001 px), and an illumination envelope at the lowest frequencies
even with a level per tile (on a development frame, and on two frozen frames no longer used
to judge, one tile lost 3 300–9 500 nats to the vignetting's envelope that gained in 14 of
16 tiles). With a level per bin each band of a tile is judged against itself. The fit is
still held out: a model that fits the fitted tiles' noise raises the judged tiles' power and
loses.

A model's gain over another is the sum of its tiles' gains; its error is the tiles' spread
(``√n`` times their standard deviation), since neighbouring pixels are not independent but
tiles nearly are.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["TileSplit", "RADIAL_BINS", "tile_spectra", "whittle_loglik", "model_probabilities"]

RADIAL_BINS = 48


@dataclass(frozen=True)
class TileSplit:
    """A frame cut into ``grid × grid`` square tiles of ``size`` pixels, centred, coloured as a checkerboard.

    Attributes
    ----------
    shape : (int, int)
        The frame (pixels).
    grid : int
        Tiles per side.
    size : int
        Tile edge (pixels).
    """

    shape: tuple[int, int]
    grid: int
    size: int

    @classmethod
    def of(cls, shape: tuple[int, int], *, grid: int = 4) -> "TileSplit":
        size = min(shape) // grid
        return cls((int(shape[0]), int(shape[1])), grid, int(size))

    def windows(self) -> list[tuple[slice, slice]]:
        """Every tile's rows and columns, row by row."""
        top = (self.shape[0] - self.grid * self.size) // 2
        left = (self.shape[1] - self.grid * self.size) // 2
        return [(slice(top + i * self.size, top + (i + 1) * self.size), slice(left + j * self.size, left + (j + 1) * self.size))
                for i in range(self.grid) for j in range(self.grid)]

    def colours(self) -> np.ndarray:
        """(tiles,) 0 or 1: the checkerboard's colour of each tile."""
        i, j = np.divmod(np.arange(self.grid * self.grid), self.grid)
        return (i + j) % 2

    def labels(self) -> np.ndarray:
        """(rows, cols) int: each pixel's tile (its index in `windows`), -1 outside every tile."""
        out = np.full(self.shape, -1)
        for index, window in enumerate(self.windows()):
            out[window] = index
        return out

    def mask(self, colour: int) -> np.ndarray:
        """(rows, cols) bool: the pixels of the tiles of ``colour``."""
        out = np.zeros(self.shape, bool)
        for window, c in zip(self.windows(), self.colours(), strict=True):
            if c == colour:
                out[window] = True
        return out


def _taper(size: int) -> np.ndarray:
    hann = np.hanning(size + 2)[1:-1]
    window = np.outer(hann, hann)
    return window / np.sqrt(np.mean(window**2))  # the taper keeps a white residual's power


def _radial_index(size: int) -> np.ndarray:
    f = np.hypot(*np.meshgrid(np.fft.fftfreq(size), np.fft.fftfreq(size), indexing="ij"))
    return np.minimum((f / 0.5 * RADIAL_BINS).astype(int), RADIAL_BINS)  # corners beyond Nyquist share the last bin


def tile_spectra(residual: np.ndarray, split: TileSplit) -> np.ndarray:
    """(tiles, size, size) the periodogram ``|FFT(taper · r)|² / size²`` of each tile's residual.

    The tile's mean stays in: what a model gets wrong about a tile's brightness (an
    illumination envelope) is in the lowest frequencies.
    """
    taper = _taper(split.size)
    out = np.empty((split.grid * split.grid, split.size, split.size))
    for k, window in enumerate(split.windows()):
        out[k] = np.abs(np.fft.fft2(residual[window] * taper)) ** 2 / split.size**2
    return out


def whittle_loglik(spectra_by_fit: tuple[np.ndarray, np.ndarray], split: TileSplit) -> np.ndarray:
    """(tiles,) each tile's held-out Whittle log-likelihood (nats), its spectrum its own per radial bin (module docstring).

    Parameters
    ----------
    spectra_by_fit : two (tiles, size, size) arrays
        `tile_spectra` of every tile's residual under the parameters fitted on the tiles of
        colour 0, then of colour 1. A tile is judged under the other colour's fit.
    """
    index = _radial_index(split.size).ravel()
    counts = np.bincount(index, minlength=RADIAL_BINS + 1)
    present = counts > 0
    colours = split.colours()
    out = np.empty(len(colours))
    for fitted_on, spectra in enumerate(spectra_by_fit):
        judged = np.flatnonzero(colours != fitted_on)
        for k in judged:
            power = np.bincount(index, spectra[k].ravel(), minlength=RADIAL_BINS + 1)[present] / counts[present]
            out[k] = -0.5 * float(np.sum(counts[present] * (1.0 + np.log(np.maximum(power, 1e-300)))))
    return out


def model_probabilities(logliks: dict[str, np.ndarray], *, draws: int = 2000, seed: int = 0) -> dict[str, float]:
    """Each model's probability of the best held-out fit, over a Bayesian bootstrap of the tiles.

    Every draw weighs the tiles by Dirichlet(1) weights (Rubin, 1981) and picks the model of
    the highest weighted log-likelihood; a model's probability is the share of draws it wins
    (the pseudo-BMA+ idea of Yao et al., *Bayesian Analysis* 13, 917 (2018), taken to its
    limit of one winner a draw, since a frame's log-likelihoods differ by thousands of nats).
    """
    names = list(logliks)
    table = np.stack([logliks[name] for name in names])
    weights = np.random.default_rng(seed).dirichlet(np.ones(table.shape[1]), size=draws)
    wins = np.bincount(np.argmax(weights @ table.T, axis=1), minlength=len(names))
    return {name: float(count) / draws for name, count in zip(names, wins, strict=True)}
