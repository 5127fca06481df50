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
from numba import njit
from scipy import fft
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
        nyquist = self.size / 2  # in frequency bins
        offsets = (np.arange(SAMPLES) + 0.5) / SAMPLES
        radius = ((np.arange(rings)[:, None] + offsets[None, :]) / rings * nyquist)[:, None, :, None]
        angle = ((np.arange(sectors)[:, None] + offsets[None, :]) * (2 * math.pi / sectors))[None, :, None, :]
        shape = (rings, sectors, SAMPLES, SAMPLES)
        fy = np.broadcast_to(radius * np.sin(angle), shape).ravel()  # y frequency: image rows
        fx = np.broadcast_to(radius * np.cos(angle), shape).ravel()
        # a real image's spectrum is symmetric, |F(-k)| = |F(k)|: read every sample in the
        # half plane fx >= 0 that rfft2 computes, its rows shifted so that fy = 0 is the centre
        flip = fx < 0
        fy, fx = np.where(flip, -fy, fy), np.abs(fx)
        self.coordinates = np.stack([self.size // 2 + fy, fx])
        window = np.hanning(self.size)
        self.window = np.outer(window, window)

    def image(self, xy: np.ndarray, height: np.ndarray) -> np.ndarray:
        """The top height of every cell of (N, 2) points ``xy`` (sensor at the centre)."""
        return _top_image(np.ascontiguousarray(xy, dtype=np.float64), np.ascontiguousarray(height, dtype=np.float64),
                          self.size, EXTENT_M, CELL_M)

    def spectrum(self, image: np.ndarray) -> np.ndarray:
        """(rings * sectors,) mean log-magnitude of every (ring, sector) bin, ring-major."""
        half = np.fft.fftshift(fft.rfft2(image * self.window, workers=1), axes=0)
        samples = map_coordinates(np.log1p(np.abs(half)), self.coordinates, order=1, mode="nearest")
        return samples.reshape(self.rings, self.sectors, SAMPLES * SAMPLES).mean(axis=2).ravel()


@njit(cache=True, nogil=True)
def _top_image(xy, height, size, extent, cell):
    image = np.zeros((size, size))
    for k in range(xy.shape[0]):
        i = int(np.floor((xy[k, 0] + extent) / cell))
        j = int(np.floor((xy[k, 1] + extent) / cell))
        if 0 <= i < size and 0 <= j < size and height[k] > image[j, i]:
            image[j, i] = height[k]
    return image
