"""Tests of rough_uq.qoi on hand-built fields and against a brute-force periodic flood fill."""

from __future__ import annotations

from collections import deque

import numpy as np
import pytest

from rough_uq import qoi
from rough_uq.errors import InvalidParameterError
from rough_uq.qoi import (
    QOI_NAMES,
    area_above,
    contact_area,
    count_clusters,
    evaluate_qoi,
    label_clusters,
    max_pressure,
    mean_gap,
)


def flood_fill_labels(contact: np.ndarray, connectivity: int) -> np.ndarray:
    """Periodic connected-component labels by breadth-first search, 1..N in raster order."""
    n0, n1 = contact.shape
    if connectivity == 4:
        offsets = [(1, 0), (-1, 0), (0, 1), (0, -1)]
    else:
        offsets = [(d0, d1) for d0 in (-1, 0, 1) for d1 in (-1, 0, 1) if (d0, d1) != (0, 0)]
    labels = np.zeros(contact.shape, dtype=np.int64)
    current = 0
    for i in range(n0):
        for j in range(n1):
            if not contact[i, j] or labels[i, j]:
                continue
            current += 1
            labels[i, j] = current
            queue = deque([(i, j)])
            while queue:
                a, b = queue.popleft()
                for d0, d1 in offsets:
                    c, d = (a + d0) % n0, (b + d1) % n1
                    if contact[c, d] and not labels[c, d]:
                        labels[c, d] = current
                        queue.append((c, d))
    return labels


# -- area and simple quantities -------------------------------------------------


def test_no_contact() -> None:
    pressure = np.zeros((8, 8))
    assert contact_area(pressure) == 0.0
    assert count_clusters(pressure > 0) == 0
    assert not label_clusters(pressure > 0).any()


def test_full_contact() -> None:
    pressure = np.full((8, 6), 0.3)
    assert contact_area(pressure) == 1.0
    for connectivity in (4, 8):
        assert count_clusters(pressure > 0, connectivity=connectivity) == 1
        assert (label_clusters(pressure > 0, connectivity=connectivity) == 1).all()


def test_area_and_extras() -> None:
    pressure = np.array([[0.0, 0.1, 0.5], [2.0, 0.0, 0.0]])
    gap = np.array([[0.2, 0.0, 0.0], [0.0, 0.4, 0.6]])
    assert contact_area(pressure) == pytest.approx(0.5)
    assert area_above(pressure, 0.3) == pytest.approx(2 / 6)
    assert area_above(pressure, 0.0) == contact_area(pressure)
    assert max_pressure(pressure) == 2.0
    assert mean_gap(gap) == pytest.approx(0.2)
    assert isinstance(contact_area(pressure), float)


def test_non_finite_fields_are_refused() -> None:
    pressure = np.zeros((4, 4))
    pressure[1, 2] = np.nan
    with pytest.raises(InvalidParameterError) as info:
        contact_area(pressure)
    assert info.value.name == "pressure"
    with pytest.raises(InvalidParameterError) as info:
        mean_gap(np.full((2, 2), np.inf))
    assert info.value.name == "gap"
    for bad in (-0.1, np.nan, "high"):
        with pytest.raises(InvalidParameterError) as info:
            area_above(np.zeros((2, 2)), bad)
        assert info.value.name == "critical_pressure"


# -- clusters on the periodic grid ------------------------------------------------


def test_cluster_wrapping_both_boundaries_counts_once() -> None:
    contact = np.zeros((10, 12), dtype=bool)
    contact[0, :] = True  # a row touching the top edge...
    contact[:, 0] = True  # ...and a column touching the left edge, joined at (0, 0)
    contact[9, 11] = True  # bottom-right corner: 4-connected to (0, 11) and (9, 0) across the edges
    contact[4:6, 11] = True  # touches column 0 across the left/right edge
    contact[5, 5] = True  # an isolated node
    for connectivity in (4, 8):
        assert count_clusters(contact, connectivity=connectivity) == 2
    labels = label_clusters(contact)
    assert labels[0, 0] == labels[9, 11] == labels[4, 11] == 1 and labels[5, 5] == 2


def test_blob_split_by_both_edges_counts_once() -> None:
    contact = np.zeros((8, 8), dtype=bool)
    contact[np.ix_([0, 1, 7], [0, 1, 7])] = True  # a 3 x 3 block centred on node (0, 0)
    assert count_clusters(contact) == 1
    assert count_clusters(contact, connectivity=8) == 1


def test_corner_touching_clusters() -> None:
    contact = np.zeros((8, 8), dtype=bool)
    contact[2, 2] = contact[3, 3] = True  # diagonal neighbours inside the box
    assert count_clusters(contact, connectivity=4) == 2
    assert count_clusters(contact, connectivity=8) == 1


@pytest.mark.parametrize(
    "nodes",
    [
        [(0, 0), (7, 7)],  # across the corner of the box
        [(0, 7), (7, 0)],  # across the other corner
        [(0, 3), (7, 4)],  # across the top/bottom edge
        [(3, 0), (4, 7)],  # across the left/right edge
    ],
)
def test_corner_touching_across_the_periodic_boundary(nodes: list[tuple[int, int]]) -> None:
    contact = np.zeros((8, 8), dtype=bool)
    for node in nodes:
        contact[node] = True
    assert count_clusters(contact, connectivity=4) == 2
    assert count_clusters(contact, connectivity=8) == 1


@pytest.mark.parametrize("n", [4, 10])
def test_checkerboard(n: int) -> None:
    i, j = np.indices((n, n))
    contact = (i + j) % 2 == 0
    assert count_clusters(contact, connectivity=4) == n * n // 2
    assert count_clusters(contact, connectivity=8) == 1
    labels = label_clusters(contact, connectivity=4)
    assert sorted(np.unique(labels[contact])) == list(range(1, n * n // 2 + 1))


def test_open_grid_diagonal_is_not_a_periodic_diagonal() -> None:
    # (0, 2) and (7, 0) are two columns apart: not neighbours under either connectivity.
    contact = np.zeros((8, 8), dtype=bool)
    contact[0, 2] = contact[7, 0] = True
    assert count_clusters(contact, connectivity=8) == 2


@pytest.mark.parametrize("connectivity", [4, 8])
@pytest.mark.parametrize(("shape", "density"), [((16, 16), 0.3), ((16, 16), 0.55), ((12, 20), 0.45), ((1, 9), 0.5)])
def test_random_maps_match_brute_force_flood_fill(connectivity: int, shape: tuple[int, int], density: float) -> None:
    rng = np.random.default_rng([connectivity, *shape, round(100 * density)])
    for _ in range(20):
        contact = rng.random(shape) < density
        expected = flood_fill_labels(contact, connectivity)
        labels = label_clusters(contact, connectivity=connectivity)
        # Same partition, same numbering (both number clusters by their first node in raster order).
        np.testing.assert_array_equal(labels, expected)
        assert count_clusters(contact, connectivity=connectivity) == expected.max()


def test_cluster_arguments_are_checked() -> None:
    with pytest.raises(InvalidParameterError) as info:
        count_clusters(np.zeros((4, 4)))  # float, not a contact map
    assert info.value.name == "contact"
    with pytest.raises(InvalidParameterError) as info:
        count_clusters(np.zeros(4, dtype=bool))
    assert info.value.name == "contact"
    for bad in (6, True, "8"):
        with pytest.raises(InvalidParameterError) as info:
            count_clusters(np.zeros((4, 4), dtype=bool), connectivity=bad)
        assert info.value.name == "connectivity"


# -- the registry ---------------------------------------------------------------


def test_evaluate_qoi_in_the_order_given() -> None:
    pressure = np.zeros((8, 8))
    pressure[1, 1] = 0.5
    pressure[5, 5:7] = 2.0
    pressure[7, 7] = 1.0
    gap = np.linspace(0.0, 1.0, 64).reshape(8, 8)
    values = evaluate_qoi(
        ["clusters", "contact_area", "max_pressure", "mean_gap", "area_above", "contact_area"],
        pressure=pressure,
        gap=gap,
        critical_pressure=0.7,
    )
    assert values.dtype == np.float64
    np.testing.assert_allclose(values, [3, 4 / 64, 2.0, 0.5, 3 / 64, 4 / 64])
    assert evaluate_qoi("contact_area", pressure=pressure).tolist() == [4 / 64]
    assert evaluate_qoi([], pressure=pressure).shape == (0,)
    assert set(QOI_NAMES) == {"contact_area", "clusters", "mean_gap", "max_pressure", "area_above"}


def test_evaluate_qoi_connectivity() -> None:
    pressure = np.zeros((6, 6))
    pressure[0, 0] = pressure[5, 5] = 1.0
    assert evaluate_qoi(["clusters"], pressure=pressure)[0] == 2
    assert evaluate_qoi(["clusters"], pressure=pressure, connectivity=8)[0] == 1


def test_evaluate_qoi_rejects_bad_requests() -> None:
    pressure = np.ones((4, 4))
    with pytest.raises(InvalidParameterError) as info:
        evaluate_qoi(["contact_area", "contact_length"], pressure=pressure)
    assert info.value.name == "names" and info.value.value == "contact_length"
    assert all(name in str(info.value) for name in QOI_NAMES)
    with pytest.raises(InvalidParameterError) as info:
        evaluate_qoi(["mean_gap"], pressure=pressure)
    assert info.value.name == "gap"
    with pytest.raises(InvalidParameterError) as info:
        evaluate_qoi(["area_above"], pressure=pressure)
    assert info.value.name == "critical_pressure"
    with pytest.raises(InvalidParameterError) as info:
        evaluate_qoi(["contact_area"], pressure=pressure, connectivity=6)
    assert info.value.name == "connectivity"


def test_evaluate_qoi_computes_only_what_is_asked(monkeypatch: pytest.MonkeyPatch) -> None:
    def forbidden(*args: object, **kwargs: object) -> None:
        raise AssertionError("clusters were labelled although not requested")

    monkeypatch.setattr(qoi, "count_clusters", forbidden)
    monkeypatch.setattr(qoi, "_periodic_components", forbidden)
    pressure = np.ones((4, 4))
    values = evaluate_qoi(["contact_area", "max_pressure", "mean_gap"], pressure=pressure, gap=np.zeros((4, 4)))
    np.testing.assert_array_equal(values, [1.0, 1.0, 0.0])
