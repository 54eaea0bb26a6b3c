"""The held-out likelihood a nested model is scored by: fitted on half of the frame's tiles, judged on the other half.

The frame is cut into a grid of square tiles coloured like a checkerboard. A model's
parameters are fitted on the tiles of one colour and its residual judged on the other
(and the other way round), so an effect that fits noise or one tile's accident gains
nothing where it was not fitted.

The noise is what the model leaves: a stationary Gaussian field whose power spectrum (radial,
`RADIAL_BINS` bins up to the Nyquist frequency) is estimated from the residuals of the tiles
the model was fitted on. A tile's log-likelihood is Whittle's,
``-½ Σ_f (|R(f)|² / P(f) + ln P(f))`` over the 2-D frequencies of its tapered residual
(Whittle, 1953): a model that explains structure lowers both the residual and the spectrum it
is judged against; one that does not, only costs. The structure the experiment holds beyond
every model (debris, dust, a speckled background) is thereby part of the noise, weighted
down where it is strong, instead of swamping every comparison.

Each judged tile has its own level: its spectrum is ``s · P(f)``, ``s`` at its most likely
value ``mean(|R(f)|² / P(f))``. Tiles differ in how much of the particles' misfit they hold
(a pair fitted as one leaves ten times the residual of a tile of lone spheres): judged
against a spectrum shared by every tile, a tile of misfit lost thousands of nats to a model
that rightly took a straight fringe out of every tile, since the fringe had raised the
spectrum its misfit was judged against. With its own level a tile is judged on the shape of
its residual's spectrum, and a model that fits the fitted tiles' noise (lowers their
spectrum where the judged tiles keep theirs) still loses: ``x - 1 - ln x >= 0``.

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


def _radial_power(spectra: np.ndarray, index: np.ndarray) -> np.ndarray:
    """The mean of ``spectra`` (tiles, n, n) over the tiles and over each radial bin, spread back over the 2-D grid."""
    mean = spectra.mean(axis=0)
    power = np.bincount(index.ravel(), mean.ravel(), minlength=RADIAL_BINS + 1) / np.maximum(np.bincount(index.ravel(), minlength=RADIAL_BINS + 1), 1)
    return np.maximum(power, 1e-30)[index]


def whittle_loglik(spectra_by_fit: tuple[np.ndarray, np.ndarray], split: TileSplit) -> np.ndarray:
    """(tiles,) each tile's held-out Whittle log-likelihood (nats).

    Parameters
    ----------
    spectra_by_fit : two (tiles, size, size) arrays
        `tile_spectra` of every tile's residual under the parameters fitted on the tiles of
        colour 0, then of colour 1. A tile is judged under the other colour's fit, against
        the spectrum of that fit's own tiles.
    """
    index = _radial_index(split.size)
    colours = split.colours()
    out = np.empty(len(colours))
    for fitted_on, spectra in enumerate(spectra_by_fit):
        power = _radial_power(spectra[colours == fitted_on], index)
        judged = colours != fitted_on
        # each tile's own level, at its most likely value: ``s = mean(|R|² / P)``
        level = np.maximum(np.mean(spectra[judged] / power, axis=(1, 2)), 1e-300)
        out[judged] = -0.5 * (power.size * (1.0 + np.log(level)) + np.sum(np.log(power)))
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
