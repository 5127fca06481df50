"""The spectrum modality: the bird's-eye height image's Fourier magnitude, in polar coordinates.

A revisit driven the other way comes back rotated and 1-3 m to the side; a polar grid
around the sensor follows the rotation (a sector shift) but not the offset, which moves
nearby structure across rings and sectors. The magnitude of a 2-D Fourier transform does
not change when its image is translated, and it turns with the image: sampled on the
polar grid's rings (spatial frequency) and sectors (direction), the same sector shift that
aligns the height block aligns this one. Measured on the shared hand-held recordings,
adding it to the height modality put more true revisits in the first few candidates, where
verification finds them.

The image is the top height above the ground of every ``CELL_M`` column within
``EXTENT_M`` of the sensor (read from the height map of :mod:`.height_map`), windowed so
that its edge does not ring; its log-magnitude is sampled at ``SAMPLES`` x ``SAMPLES``
points of every (ring, sector) bin and averaged. Ring r covers frequencies
[r, r + 1) / rings of the Nyquist frequency; the spectrum of a real image is symmetric
under a half turn, so opposite sectors hold the same values.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.ndimage import map_coordinates

CELL_M = 0.5  # image cell: finer than the nearest structure a revisit must match
EXTENT_M = 40.0  # the image reaches this far in x and y
SAMPLES = 3  # sample points per bin along each of frequency and direction


class SpectrumSampler:
    """Polar sampling of a ``size`` x ``size`` image's centred magnitude spectrum, for one
    ``rings`` x ``sectors`` grid (sector b covers directions [b, b + 1) * 2 pi / sectors from +x,
    counterclockwise, as the polar grid's azimuth sectors do)."""

    def __init__(self, rings: int, sectors: int) -> None:
        self.rings, self.sectors = rings, sectors
        self.size = int(round(2 * EXTENT_M / CELL_M))
        centre = self.size // 2  # where np.fft.fftshift puts frequency 0
        nyquist = self.size / 2  # in frequency bins
        offsets = (np.arange(SAMPLES) + 0.5) / SAMPLES
        radius = (np.arange(rings)[:, None] + offsets[None, :]).ravel() / rings * nyquist
        angle = (np.arange(sectors)[:, None] + offsets[None, :]).ravel() * (2 * math.pi / sectors)
        r = radius.reshape(rings, SAMPLES)[:, None, :, None]
        a = angle.reshape(sectors, SAMPLES)[None, :, None, :]
        # row = y frequency, column = x frequency (the image is indexed [y, x])
        self.coordinates = np.stack([np.broadcast_to(centre + r * np.sin(a), (rings, sectors, SAMPLES, SAMPLES)),
                                     np.broadcast_to(centre + r * np.cos(a), (rings, sectors, SAMPLES, SAMPLES))])
        window = np.hanning(self.size)
        self.window = np.outer(window, window)

    def image(self, xy: np.ndarray, height: np.ndarray) -> np.ndarray:
        """The top height of every cell of (N, 2) points ``xy`` (sensor at the centre)."""
        image = np.zeros((self.size, self.size))
        ij = np.floor((xy + EXTENT_M) / CELL_M).astype(np.int64)
        inside = np.all((ij >= 0) & (ij < self.size), axis=1)
        np.maximum.at(image, (ij[inside, 1], ij[inside, 0]), height[inside])
        return image

    def spectrum(self, image: np.ndarray) -> np.ndarray:
        """(rings * sectors,) mean log-magnitude of every (ring, sector) bin, ring-major."""
        magnitude = np.log1p(np.abs(np.fft.fftshift(np.fft.fft2(image * self.window))))
        samples = map_coordinates(magnitude, self.coordinates.reshape(2, -1), order=1, mode="nearest")
        return samples.reshape(self.rings, self.sectors, SAMPLES * SAMPLES).mean(axis=2).ravel()
