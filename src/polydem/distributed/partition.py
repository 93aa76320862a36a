"""Slabs: which rank owns a body, and which ranks hold it as a ghost.

Space is cut into slabs across one axis (the longest extent of the bodies at the start), one per
rank, with cuts at the quantiles of the bodies' coordinates so that every rank owns about as many
bodies. The quantiles come from a histogram summed over the ranks (a fixed number of bins whatever
the number of bodies), so finding the cuts sends a few kilobytes, not the positions.

A rank holds, besides the bodies it owns, copies (ghosts) of every body within ``halo`` of its
slab. With ``halo = 2 r_max + margin`` (r_max the largest bounding radius) and bodies moving less
than ``margin / 2`` between two partitions, every body that can touch a body of the slab is held
(two bodies touch only when their centres are within ``2 r_max``; each moved less than ``margin /
2``), which is what makes the rank's contacts those of the undivided run.
"""

from __future__ import annotations

import numpy as np

HISTOGRAM_BINS = 4096
"""Bins of the histogram the cuts are read from: cuts fall on bin edges, so the balance is within
about N / 4096 bodies of the ideal."""


def longest_axis(lower: np.ndarray, upper: np.ndarray) -> int:
    """The axis (0, 1, 2) along which the box ``lower``..``upper`` is longest."""
    return int(np.argmax(np.asarray(upper, dtype=np.float64) - np.asarray(lower, dtype=np.float64)))


def cuts_from_histogram(counts: np.ndarray, lo: float, hi: float, ranks: int) -> np.ndarray:
    """(ranks + 1,) slab boundaries along the axis: ``-inf``, the inner cuts, ``+inf``.

    ``counts`` is the histogram of the bodies' coordinates over ``HISTOGRAM_BINS`` equal bins from
    ``lo`` to ``hi``; inner cut k lies on the first bin edge where the cumulative count reaches
    ``k / ranks`` of the bodies. Cuts never decrease; a slab may be empty where bodies pile up in one bin.
    """
    counts = np.asarray(counts, dtype=np.int64)
    total = int(counts.sum())
    cuts = np.empty(ranks + 1, dtype=np.float64)
    cuts[0], cuts[-1] = -np.inf, np.inf
    if ranks == 1:
        return cuts
    edges = np.linspace(lo, hi, len(counts) + 1)
    cumulative = np.cumsum(counts)
    for k in range(1, ranks):
        target = total * k / ranks
        b = int(np.searchsorted(cumulative, target, side="left"))
        cuts[k] = edges[min(b + 1, len(counts))]
    return np.maximum.accumulate(cuts)


def owner(coordinate: np.ndarray, cuts: np.ndarray) -> np.ndarray:
    """Rank owning each coordinate: slab k is ``cuts[k] <= x < cuts[k + 1]``."""
    return (np.searchsorted(cuts, np.asarray(coordinate, dtype=np.float64), side="right") - 1).astype(np.int64)


def holders(coordinate: np.ndarray, cuts: np.ndarray, halo: float) -> np.ndarray:
    """(n, ranks) bool: whether each rank holds each body (it owns it, or it lies within ``halo`` of its slab)."""
    x = np.asarray(coordinate, dtype=np.float64)[:, None]
    return (x >= cuts[None, :-1] - halo) & (x < cuts[None, 1:] + halo)
