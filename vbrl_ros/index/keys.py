"""The keyframe index's two small keys: their construction and compiled kernels.

Both keys are signed group sums of weighted descriptor entries, so by the
triangle inequality their L1 distances are lower bounds of the Eq. 4 distance
(see :mod:`vbrl_ros.index.keyframe_index`):

- the *candidate key* (``key_dim`` entries) is made of features of each column
  that do not change when a scan is rotated by whole sectors: its sum over the
  sectors and, when the columns alone cannot fill the key (a narrow descriptor),
  the magnitudes of its first harmonics over the sectors (:mod:`.harmonics`);
  a finer *refine key* (``refine_dim`` entries, the same construction, stored
  row-major) re-scores the scan's best candidates;
- the *yaw key* (``S x G`` entries) keeps the sectors apart, so comparing it
  under every circular shift ranks the candidates and their shifts cheaply.

Candidate keys are 4-bit: each entry is rounded to an integer in [-7, 7] and
stored as a nibble (value + 8), two entries per byte, in blocks of
:data:`BLOCK` keyframes, entry-pair-major inside a block, so the scan compares
one query pair against 128 keyframes in one vector loop. Nibble differences
(<= 15) are summed in uint8 over 8 pairs (<= 240) before widening to uint16
(exact up to :data:`MAX_KEY_DIM` entries). 4 bits rank the brute-force
match as well as 8 bits at the same number of entries (a trained polar model
at 100k keyframes), so twice the entries fit in the same bytes, and the scan
is ~1.5x faster per entry than an int8 one. The scan selects the
best ``want`` keys by counting scores (the mask is applied inside), so nothing
is sorted or partitioned. All kernels are single-threaded and release the GIL.
"""

from __future__ import annotations

import heapq

import numpy as np
from numba import njit

from vbrl_ros.index import harmonics as hm
from vbrl_ros.model.distance_kernels import as_float32

BLOCK = 128  # keyframes per key block
MAX_KEY_DIM = 1024  # uint16 sums of nibble differences stay exact up to 4369 entries
KEY_LEVELS = 7  # a key entry is an integer in [-7, 7], stored as a nibble (value + 8)
HARMONIC_CLIP_RATIO = 2 / 3  # entries with harmonics clip at this share of key_clip_sigma
_PAIRS_PER_PARTIAL = 8  # 8 pairs of nibble differences: <= 240, fits a uint8 partial sum


def energy_balanced_groups(energy: np.ndarray, groups: int,
                           rng: np.random.Generator) -> np.ndarray:
    """Group of each column: greedy longest-processing-time partition of ``energy``.

    Columns heaviest first (random order among equals) each join the group with
    the least energy so far, so group energies end up nearly equal.
    """
    order = np.lexsort((rng.permutation(len(energy)), -energy))
    heap = [(0.0, g) for g in range(groups)]
    group = np.empty(len(energy), np.int64)
    for column in order:
        total, g = heapq.heappop(heap)
        group[column] = g
        heapq.heappush(heap, (total + float(energy[column]), g))
    return group


class KeyLayout:
    """How one key's entries are made from the invariant column features (:mod:`.harmonics`).

    Features (the column sums, then the first ``harmonics`` magnitudes of every
    column) are split into ``entries`` groups of equal weight energy, each a
    signed, weighted sum: ``group``/``signed`` per feature. ``offset`` is each
    entry's nominal mean (0 without harmonics; magnitudes are never negative), taken
    off before the 4-bit rounding so the codes centre on the nibble range;
    ``inverse_scale`` maps ``key_clip_sigma`` nominal standard deviations to 7.
    """

    def __init__(self, column_weights: np.ndarray, sectors: int, entries: int,
                 rng: np.random.Generator, clip_sigma: float) -> None:
        width = len(column_weights)
        w64 = np.asarray(column_weights, np.float64)
        self.harmonics = hm.harmonics_for(entries, width, sectors)
        coefficients, means = hm.feature_coefficients(w64, sectors, self.harmonics)
        # equal weight energy per entry (heaviest features alone), random signs. A random
        # partition would let one heavy column set the scale of every entry: with a model
        # whose weight sits on a few rows most entries would round to 0. Every harmonic of
        # a column has the same nominal spread, so the energy is the column's weight squared.
        groups = max(entries, 1)
        self.group = energy_balanced_groups(np.tile(w64**2, self.harmonics + 1), groups, rng)
        sign = rng.integers(0, 2, len(coefficients)) * 2 - 1
        self.signed = (sign * coefficients).astype(np.float32)
        self.offset = np.bincount(self.group, weights=sign * means,
                                  minlength=groups)[:entries].astype(np.float32)
        # an entry sums unit-variance terms, nominal spread sqrt(S) w_r / sum(beta) each
        spread = hm.nominal_statistics(sectors, self.harmonics)[1]
        beta_sum = float((spread[0] / spread).sum())
        sigma = np.sqrt(sectors * np.bincount(self.group, weights=np.tile(w64**2, self.harmonics + 1),
                                              minlength=groups)) / beta_sum
        if self.harmonics:
            # Entries of few columns cannot be balanced (40 columns, 256 entries: most stand
            # alone, their weights 4x apart), so each gets its own scale: light columns keep
            # all 15 levels. Real magnitudes spread less than independent sectors would make
            # them, so they clip sooner (the ratio ranked the brute-force match best among
            # 1.5, 2, 2.5, 3 and 4 sigma at 100k keyframes).
            clip = HARMONIC_CLIP_RATIO * clip_sigma * sigma[: max(entries, 1)]
            self.inverse_scale = (KEY_LEVELS / np.where(clip > 0, clip, KEY_LEVELS)).astype(np.float32)
        else:  # equal energies by construction: one scale, as the key always had
            scale = clip_sigma * float(sigma.max()) / KEY_LEVELS
            self.inverse_scale = np.float32(1.0 / scale) if scale > 0 else np.float32(1.0)

    def codes(self, raw: np.ndarray) -> np.ndarray:
        """Entries as nibble codes (uint8, value + 8 in [1, 15]), shape of ``raw``."""
        value = np.clip(np.rint((raw - self.offset) * self.inverse_scale), -KEY_LEVELS, KEY_LEVELS)
        return (value + 8).astype(np.uint8)


class KeyCodec:
    """Seeded layouts of the three keys (:class:`KeyLayout` for the candidate and refine
    keys, random column groups and signs for the yaw key) and the kernels' tables.

    ``key_clip_sigma``: the [-7, 7] range in standard deviations of a key
    entry, assuming unit-variance (standardised) features independent across
    sectors (3: ranked the brute-force match best among 2, 3 and 4).
    """

    def __init__(self, column_weights: np.ndarray, sectors: int, key_dim: int, yaw_dim: int,
                 seed: int, key_clip_sigma: float, refine_dim: int = 0) -> None:
        width = len(column_weights)
        self.sectors, self.key_dim, self.yaw_dim = sectors, key_dim, yaw_dim
        self.refine_dim = refine_dim
        w64 = np.asarray(column_weights, np.float64)
        # the refine key: the same construction with more entries (own seed stream)
        self.refine = KeyLayout(w64, sectors, refine_dim, np.random.default_rng([seed, 0x2EF1]),
                                key_clip_sigma)
        self.key = KeyLayout(w64, sectors, key_dim, np.random.default_rng([seed, 0x1DE7]),
                             key_clip_sigma)
        # The yaw key's groups are drawn where they always were: in the candidate key's
        # stream after a column-sum key's column order and signs, so they do not change
        # with the candidate key (a narrow model's saved yaw keys stay valid, and the
        # search's later stages, sensitive to this draw, stay as measured).
        rng = np.random.default_rng([seed, 0x1DE7])
        rng.permutation(width), rng.integers(0, 2, width)
        self.yaw_group = rng.permutation(np.arange(width) % max(yaw_dim, 1)).astype(np.int64)
        self.yaw_signed = ((rng.integers(0, 2, width) * 2 - 1) * w64).astype(np.float32)
        self.cosines, self.sines = hm.dft_tables(sectors, max(self.key.harmonics,
                                                              self.refine.harmonics))

    def raw(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Unquantised (candidate keys (n, key_dim), yaw keys (n, S, yaw_dim), refine keys
        (n, refine_dim)) of (n, d) float32 (or the uint16 view of float16) descriptors,
        from one pass over them."""
        keys = np.empty((len(x), self.key_dim), np.float32)
        yaw = np.empty((len(x), self.sectors, self.yaw_dim), np.float32)
        refine = np.empty((len(x), self.refine_dim), np.float32)
        raw_keys(x, self.sectors, self.cosines, self.sines, self.key.group, self.key.signed,
                 self.refine.group, self.refine.signed, self.yaw_group, self.yaw_signed, keys,
                 refine, yaw)
        return keys, yaw, refine

    def quantised(self, raw: np.ndarray) -> np.ndarray:
        """Candidate-key entries as nibble codes (uint8, value + 8 in [1, 15]), shape of ``raw``."""
        return self.key.codes(raw)

    def refine_quantised(self, raw: np.ndarray) -> np.ndarray:
        """Refine-key entries as nibble codes, on the refine key's own scale."""
        return self.refine.codes(raw)


def packed(codes: np.ndarray) -> np.ndarray:
    """(n, ceil(key_dim / 2)) bytes of nibble codes (n, key_dim): entry 2p low, 2p + 1 high.

    An odd ``key_dim`` is padded with the code of 0 (8), which every key shares.
    """
    n, key_dim = codes.shape
    even = np.full((n, key_dim + key_dim % 2), 8, np.uint8)
    even[:, :key_dim] = codes
    return (even[:, 0::2] | (even[:, 1::2] << 4)).astype(np.uint8)


def padded(codes: np.ndarray) -> np.ndarray:
    """One key's nibble codes padded to an even length as :func:`packed` pads: a scan query."""
    out = np.full(len(codes) + len(codes) % 2, 8, np.uint8)
    out[: len(codes)] = codes
    return out


def unpacked(pairs: np.ndarray, key_dim: int) -> np.ndarray:
    """Inverse of :func:`packed`: nibble codes (n, key_dim)."""
    codes = np.empty((len(pairs), 2 * pairs.shape[1]), np.uint8)
    codes[:, 0::2] = pairs & 15
    codes[:, 1::2] = pairs >> 4
    return codes[:, :key_dim]


@njit(cache=True, nogil=True)
def raw_keys(x: np.ndarray, sectors: int, cosines: np.ndarray, sines: np.ndarray,
             group: np.ndarray, signed_w: np.ndarray, refine_group: np.ndarray,
             refine_signed_w: np.ndarray, yaw_group: np.ndarray, yaw_signed_w: np.ndarray,
             out_key: np.ndarray, out_refine: np.ndarray, out_yaw: np.ndarray) -> None:
    """Unquantised keys of (m, S*R) descriptors: out_key (m, key_dim), out_refine
    (m, refine_dim; skipped when 0), out_yaw (m, S, G; skipped when G = 0).

    ``x``: float32, or the uint16 view of float16 descriptors. ``cosines``/``sines``:
    :func:`~vbrl_ros.index.harmonics.dft_tables` for the most harmonics either key uses.

    key[j] = sum_{f in group j} signed_f feature_f over the invariant column features
    (:func:`~vbrl_ros.index.harmonics.column_features`; refine: its own groups, signs);
    yaw[s, g] = sum_{r in yaw group g} sign'_r w_r x[s, r].
    """
    width = len(yaw_group)
    yaw_dim = out_yaw.shape[2]
    features = np.empty(width * (cosines.shape[0] + 1), np.float32)
    re = np.empty((cosines.shape[0], width), np.float64)
    im = np.empty((cosines.shape[0], width), np.float64)
    for i in range(x.shape[0]):
        row = x[i]
        hm.column_features(row, sectors, width, cosines, sines, re, im, features)
        if yaw_dim > 0:
            out_yaw[i, :, :] = 0.0
            for s in range(sectors):
                part = row[s * width : (s + 1) * width]
                yaw = out_yaw[i, s]
                for r in range(width):
                    yaw[yaw_group[r]] += yaw_signed_w[r] * as_float32(part[r])
        out_key[i, :] = 0.0
        for f in range(len(group)):
            out_key[i, group[f]] += signed_w[f] * features[f]
        if out_refine.shape[1] > 0:
            out_refine[i, :] = 0.0
            for f in range(len(refine_group)):
                out_refine[i, refine_group[f]] += refine_signed_w[f] * features[f]


@njit(cache=True, nogil=True)
def refine_scores(keys: np.ndarray, rows: np.ndarray, query: np.ndarray, out: np.ndarray) -> None:
    """out[i] = L1 distance of row-major packed keys[rows[i]] to the query's nibble codes.

    Per row, the byte distances go to a uint8 buffer first and are summed in a
    second loop: both vectorise (one fused loop did not; 2x slower).
    """
    pairs = keys.shape[1]
    low, high = query[0::2].copy(), query[1::2].copy()
    byte_distance = np.empty(pairs, np.uint8)
    for i in range(len(rows)):
        packed_row = keys[rows[i]]
        for p in range(pairs):
            byte_distance[p] = _nibble_distance(packed_row[p], low[p], high[p])
        total = 0
        for p in range(pairs):
            total += byte_distance[p]
        out[i] = total


@njit(cache=True, nogil=True, inline="always")
def _nibble_distance(a: np.uint8, low: np.uint8, high: np.uint8) -> np.uint8:
    """|a's low nibble - low| + |a's high nibble - high| in uint8 arithmetic.

    Every step is cast back to uint8 so LLVM vectorises 32 bytes per op (numba
    would otherwise compute in int64 lanes, ~2.5x slower).
    """
    lo = np.uint8(a & np.uint8(15))
    hi = np.uint8(a >> np.uint8(4))
    return np.uint8(np.uint8(max(lo, low) - min(lo, low)) + np.uint8(max(hi, high) - min(hi, high)))


@njit(cache=True, nogil=True)
def scan_top(blocks: np.ndarray, query: np.ndarray, n: int, allowed: np.ndarray,
             want: int, out_rows: np.ndarray, out_scores: np.ndarray) -> int:
    """The ``want`` smallest key L1 distances (ties: lower row) among the first n keyframes.

    ``blocks``: (blocks, pairs, BLOCK) packed keys; ``query``: 2 * pairs nibble
    codes (padded like :func:`packed`). ``allowed`` is a boolean mask of length
    >= n, or empty for "everything". Fills ``out_rows``/``out_scores`` in
    ascending row order and returns how many were found.

    Scores are small integers (<= 30 per key byte), so the selection is a
    counting one: the scan writes every score (2 bytes per keyframe) and counts
    how many allowed keyframes reach each value; the cut-off is the smallest
    score with ``want`` at or below it, and a second pass keeps every row below
    it and the lowest rows at it. Exact, no sorting, and ~0.8 ms cheaper per
    100k-keyframe query at want = 4096 than partitioning a buffer of candidates.
    """
    pairs = blocks.shape[1]
    use_mask = len(allowed) > 0
    acc = np.empty(BLOCK, np.uint16)
    partial = np.empty(BLOCK, np.uint8)
    scores = np.empty(n, np.uint16)
    counts = np.zeros(30 * pairs + 1, np.int64)
    for block in range(blocks.shape[0]):
        base = block * BLOCK
        if base >= n:
            break
        acc[:] = 0
        for first in range(0, pairs, _PAIRS_PER_PARTIAL):
            partial[:] = 0
            for p in range(first, min(first + _PAIRS_PER_PARTIAL, pairs)):
                low, high = query[2 * p], query[2 * p + 1]
                entries = blocks[block, p]
                for b in range(BLOCK):
                    partial[b] = np.uint8(partial[b] + _nibble_distance(entries[b], low, high))
            for b in range(BLOCK):
                acc[b] += np.uint16(partial[b])
        for b in range(min(BLOCK, n - base)):
            scores[base + b] = acc[b]
            if not (use_mask and not allowed[base + b]):
                counts[acc[b]] += 1
    below, cutoff = 0, 0  # allowed keyframes scoring below cutoff; the cut-off score
    while cutoff < len(counts) and below + counts[cutoff] < want:
        below += counts[cutoff]
        cutoff += 1
    at_cutoff = want - below  # keyframes scoring exactly cutoff to keep, lowest rows first
    found = 0
    for row in range(n):
        score = scores[row]
        if score > cutoff or (use_mask and not allowed[row]):
            continue
        if score == cutoff:
            if at_cutoff == 0:
                continue
            at_cutoff -= 1
        out_rows[found] = row
        out_scores[found] = score
        found += 1
    return found


@njit(cache=True, nogil=True, fastmath=True)
def _l1(a: np.ndarray, start: int, b: np.ndarray) -> np.float32:
    """sum_j |a[start + j] - b[j]| (a separate fastmath function, so it is vectorised)."""
    window = a[start : start + len(b)]
    total = np.float32(0.0)
    for j in range(len(b)):
        total += abs(window[j] - b[j])
    return total


@njit(cache=True, nogil=True)
def yaw_bounds(yaw_keys: np.ndarray, rows: np.ndarray, query: np.ndarray, shifts: np.ndarray,
               out: np.ndarray) -> None:
    """out[i, j] = sum_s sum_g |query[(s + k) % S, g] - yaw_keys[rows[i], s, g]|, k = shifts[i, j].

    A lower bound of D_k for keyframe rows[i] (float32). With the query's
    flattened (S * G) key laid out twice, shift k is the contiguous window
    starting at k * G, so each bound is one vectorised L1 over S * G values
    (~1.3 us per keyframe and all 24 shifts at G = 16). ``shifts``: (len(rows), m)
    in [0, S), e.g. a broadcast ``arange(S)`` for every shift.
    """
    dim = query.shape[1]
    flat = query.ravel()
    doubled = np.empty(2 * len(flat), np.float32)
    doubled[: len(flat)] = flat
    doubled[len(flat) :] = flat
    for i in range(len(rows)):
        y = yaw_keys[rows[i]].ravel()
        for j in range(shifts.shape[1]):
            out[i, j] = _l1(doubled, shifts[i, j] * dim, y)
