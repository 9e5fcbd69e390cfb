"""The event graph's settings: positions whose offsets do not depend on where time counts from."""
from fractions import Fraction

import numpy as np
import pytest
import torch

from dagr_lite.graph.spec import TIME_SCALE_BITS, EventGraphSpec
from dagr_lite.graph.streaming import StreamingGraph


def boundary_events(r: float, beta: float) -> np.ndarray:
    """``(N, 4)`` events in whole pixels and microseconds, sorted by time, with many pairs exactly ``r``
    apart in ``(x, y, beta t)``: a 2-px offset and 4,000 us for ``r = 3`` (``4 + 1 + 2^2``), a 4-px offset and
    6,000 us for ``r = 5`` (``16 + 3^2``), and the same pixel ``r / beta`` later, over a random cloud."""
    rng = np.random.default_rng(3)
    rows = []
    for i in range(60):
        x, y, t = 10 + 7 * (i % 8), 10 + 7 * (i // 8), 1_000 + 37 * i
        rows += [(x, y, t, 1), (x + 2, y + 1, t + 4_000, 0), (x + 4, y, t + 6_000, 1), (x, y, t + round(r / beta), 0)]
    rows += [(rng.integers(0, 70), rng.integers(0, 70), rng.integers(0, 12_000), rng.integers(0, 2)) for _ in range(600)]
    events = np.array(rows, dtype=np.float64)
    return events[np.argsort(events[:, 2], kind="stable")]


def test_time_scale_is_beta_rounded_to_a_dyadic_step():
    spec = EventGraphSpec(radius=5.0, beta=5e-4, max_neighbors=16)
    scaled = Fraction(spec.time_scale) * 2 ** TIME_SCALE_BITS
    assert scaled.denominator == 1 and scaled == 536_871  # round(5e-4 * 2^30)
    assert abs(spec.time_scale - 5e-4) <= 2.0 ** -(TIME_SCALE_BITS + 1)
    events = torch.tensor([[3.0, 4.0, 333_333.0, 1.0], [0.0, 0.0, 987_654_321.0, 0.0]], dtype=torch.float64)
    z = spec.positions(events)[:, 2]
    for t, value in zip(events[:, 2].tolist(), z.tolist()):  # exact: a whole number of microseconds times the step
        assert Fraction(value) == Fraction(int(t)) * Fraction(spec.time_scale)
    for too_small in (1e-10, 2.0 ** -(TIME_SCALE_BITS + 1)):  # would round to a time scale of 0
        with pytest.raises(ValueError, match="beta"):
            EventGraphSpec(radius=5.0, beta=too_small, max_neighbors=16)
    assert EventGraphSpec(radius=5.0, beta=2.0 ** -TIME_SCALE_BITS, max_neighbors=16).time_scale == 2.0 ** -TIME_SCALE_BITS


@pytest.mark.parametrize("radius,beta", [(3.0, 5e-4), (5.0, 5e-4)])
def test_edges_do_not_depend_on_where_time_counts_from(radius, beta):
    # A sample counts event times from its image's time, a stream from an origin of its own: the
    # graph must be the same. With beta * t rounded in each position, pairs exactly r apart were kept
    # or not by the rounding of that origin.
    spec = EventGraphSpec(radius=radius, beta=beta, max_neighbors=8)
    events = boundary_events(radius, beta)
    reference = spec.edges(torch.from_numpy(events), workers=1)
    assert reference.shape[1] > 100
    for shift in (300_000, 633_333, 4_194_311, 8_388_607):
        shifted = events.copy()
        shifted[:, 2] += shift
        for backend in ("compiled", "kdtree", "torch"):
            got = spec.edges(torch.from_numpy(shifted), workers=1, backend=backend)
            assert torch.equal(got, reference), (shift, backend)
        stream = StreamingGraph(radius, 8, workers=1)  # in pieces, as a stream builds it
        pos = spec.positions(torch.from_numpy(shifted))
        pieces = [stream.insert(pos[a:a + 97]) for a in range(0, len(pos), 97)]
        assert torch.equal(torch.cat(pieces, dim=1), reference), shift
