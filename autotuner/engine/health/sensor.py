"""The PV sensor: its noise level and whether it froze."""

from __future__ import annotations

import numpy as np


def frozen_share(pv: np.ndarray) -> float:
    """The longest run of samples over which the PV did not change at all, as a share of the record, 0–1.

    A live sensor never reads the very same number for long: its noise and quantisation move it.

    ``pv``: the PV record.
    """
    if len(pv) < 2:
        return 0.0
    moves = np.flatnonzero(np.diff(pv) != 0.0)
    edges = np.concatenate(([-1], moves, [len(pv) - 1]))
    return float(np.max(np.diff(edges)) - 1) / (len(pv) - 1)
