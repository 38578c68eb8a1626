"""Tests of rough_uq.physics.qoi on hand-built fields and against a brute-force periodic flood fill."""

from __future__ import annotations

import math
from collections import deque

import numpy as np
import pytest

from rough_uq.physics import qoi
from rough_uq.errors import InvalidParameterError
from rough_uq.physics.qoi import (
    PERIMETER_COEFFICIENT,
    QOI_NAMES,
    area_above,
    contact_area,
    contact_perimeter,
    cluster_count,
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
    assert contact_area(pressure, estimator="nodes") == pytest.approx(0.5)
    assert area_above(pressure, 0.3) == pytest.approx(2 / 6)
    assert area_above(pressure, 0.0) == contact_area(pressure, estimator="nodes")
    assert max_pressure(pressure) == 2.0
    assert mean_gap(gap) == pytest.approx(0.2)
    assert isinstance(contact_area(pressure), float)


@pytest.mark.parametrize("function", [contact_area, max_pressure, mean_gap, lambda field: area_above(field, 0.5)])
def test_complex_and_boolean_fields_are_refused_not_converted(function) -> None:
    # A complex field was read with its imaginary part dropped (a numpy ComplexWarning, then numbers); a boolean
    # contact map passed for a pressure read as pressures 0 and 1. solve_contact refuses both alike.
    for field, held in ((np.ones((4, 4)) + 1j, "complex numbers"), (np.ones((4, 4)) > 0, "booleans")):
        with pytest.raises(InvalidParameterError, match=f"an array of {held}"):
            function(field)


def test_non_finite_fields_are_refused() -> None:
    pressure = np.zeros((4, 4))
    pressure[1, 2] = np.nan
    with pytest.raises(InvalidParameterError) as info:
        contact_area(pressure)
    assert info.value.name == "pressure"
    with pytest.raises(InvalidParameterError) as info:
        mean_gap(np.full((2, 2), np.inf))
    assert info.value.name == "gap"
    # None read as "non-finite entries"; a ragged list
    refusals = ((None, "an array of finite numbers"), ("abc", "an array of text"), ([[1.0], [1.0, 2.0]], "ragged"))
    for field, said in refusals:
        with pytest.raises(InvalidParameterError, match=said) as info:
            contact_area(field)
        assert info.value.name == "pressure"
    for bad in (-0.1, np.nan, "high", "0.1", True):
        with pytest.raises(InvalidParameterError) as info:
            area_above(np.zeros((2, 2)), bad)
        assert info.value.name == "critical_pressure"


@pytest.mark.parametrize(
    ("measure", "name"),
    [
        (contact_area, "pressure"),
        (lambda p: contact_area(p, estimator="nodes"), "pressure"),
        (lambda p: area_above(p, 0.5), "pressure"),
        (max_pressure, "pressure"),
        (mean_gap, "gap"),
        (lambda p: count_clusters(np.asarray(p) > 0), "contact"),
        (lambda p: label_clusters(np.asarray(p) > 0, connectivity=8), "contact"),
        (lambda p: contact_perimeter(np.asarray(p) > 0), "contact"),
        (lambda p: evaluate_qoi(("max_pressure",), pressure=p), "pressure"),
        (lambda p: evaluate_qoi(("mean_gap",), pressure=np.ones((1, 3)), gap=p), "gap"),
    ],
)
@pytest.mark.parametrize("field", [np.array([1.0, 0.0, 2.0]), np.zeros(3), np.ones((2, 2, 2)), 5.0, np.zeros((0, 3))])
def test_fields_that_are_not_2d_grids_are_refused_by_name(measure, name, field) -> None:
    # contact_area refused a 1-d field only for partial contact with the corrected estimator: no contact, full
    # contact or "nodes" gave an area (a scalar 5.0 an area of 1), and mean_gap, max_pressure and area_above
    # took any shape.
    refusal = r"^\w+: got 'array of shape .*'; allowed: a non-empty 2-d array$"
    with pytest.raises(InvalidParameterError, match=refusal) as info:
        measure(field)
    assert info.value.name == name
    measure(np.ones((1, 3)))  # a grid of one row is a grid


@pytest.mark.parametrize(
    "measure",
    [
        contact_area,
        lambda p: contact_area(p, estimator="nodes"),
        lambda p: area_above(p, 0.5),
        max_pressure,
        lambda p: evaluate_qoi(("clusters",), pressure=p),
    ],
)
def test_negative_pressures_are_refused(measure) -> None:
    # A field of the opposite sign would read as no contact at all (area 0), not as an error.
    pressure = -np.abs(np.random.default_rng(3).normal(size=(8, 8)))
    pressure[0, 0] = 0.0
    with pytest.raises(InvalidParameterError, match="negative entries") as info:
        measure(pressure)
    assert info.value.name == "pressure"
    measure(np.abs(pressure))  # the same field with the sign of a pressure is accepted


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
    with pytest.raises(InvalidParameterError, match="^contact: got None; allowed: a boolean array"):
        count_clusters(None)  # it said "got 'array of dtype object'"
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
    # Corrected area: the single nodes have perimeter 4 each, the pair (5, 5:7) 6.
    area = (4 - PERIMETER_COEFFICIENT * (4 + 6 + 4)) / 64
    np.testing.assert_allclose(values, [3, area, 2.0, 0.5, 3 / 64, area])
    assert evaluate_qoi("contact_area", pressure=pressure, area_estimator="nodes").tolist() == [4 / 64]
    assert evaluate_qoi([], pressure=pressure).shape == (0,)
    assert set(QOI_NAMES) == {"contact_area", "clusters", "mean_gap", "max_pressure", "area_above"}


def test_evaluate_qoi_connectivity() -> None:
    pressure = np.zeros((6, 6))
    pressure[0, 0] = pressure[5, 5] = 1.0
    assert evaluate_qoi(["clusters"], pressure=pressure)[0] == 2
    assert evaluate_qoi(["clusters"], pressure=pressure, connectivity=8)[0] == 1
    assert evaluate_qoi(["clusters"], pressure=pressure, connectivity="mean")[0] == 1.5


@pytest.mark.parametrize("seed", range(6))
def test_mean_count_is_the_mean_of_the_two_neighbourhoods(seed: int) -> None:
    # Random maps, some wrapping both boundaries: "mean" is (N4 + N8) / 2, and N8 <= mean <= N4.
    rng = np.random.default_rng([77, seed])
    contact = rng.random((24, 24)) < rng.uniform(0.2, 0.6)
    four, eight = count_clusters(contact, connectivity=4), count_clusters(contact, connectivity=8)
    mean = cluster_count(contact, "mean")
    assert mean == 0.5 * (four + eight)
    assert eight <= mean <= four
    assert cluster_count(contact, 4) == four and cluster_count(contact, 8) == eight
    for bad in (6, "8", True, None, "average"):
        with pytest.raises(InvalidParameterError) as info:
            cluster_count(contact, bad)
        assert info.value.name == "connectivity"


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
    for bad in ("perimeter", None, 1):
        with pytest.raises(InvalidParameterError) as info:
            evaluate_qoi(["mean_gap"], pressure=pressure, gap=pressure, area_estimator=bad)
        assert info.value.name == "estimator"


def test_evaluate_qoi_computes_only_what_is_asked(monkeypatch: pytest.MonkeyPatch) -> None:
    def forbidden(*args: object, **kwargs: object) -> None:
        raise AssertionError("clusters were labelled although not requested")

    monkeypatch.setattr(qoi, "count_clusters", forbidden)
    monkeypatch.setattr(qoi, "_periodic_components", forbidden)
    pressure = np.ones((4, 4))
    values = evaluate_qoi(["contact_area", "max_pressure", "mean_gap"], pressure=pressure, gap=np.zeros((4, 4)))
    np.testing.assert_array_equal(values, [1.0, 1.0, 0.0])


# -- the perimeter-corrected contact area -----------------------------------------


def brute_force_perimeter(contact: np.ndarray) -> int:
    """Contact/non-contact 4-neighbour edges, by visiting each node's right and lower edge."""
    n0, n1 = contact.shape
    edges = 0
    for i in range(n0):
        for j in range(n1):
            edges += contact[i, j] != contact[(i + 1) % n0, j]
            edges += contact[i, j] != contact[i, (j + 1) % n1]
    return int(edges)


def corrected(n_contact: int, perimeter: int, n_nodes: int) -> float:
    return (n_contact - PERIMETER_COEFFICIENT * perimeter) / n_nodes


def test_perimeter_coefficient_is_the_published_one() -> None:
    # Yastrebov, Anciaux & Molinari (2017): c = (pi - 1 + ln 2) / 24 = 0.1181...
    assert PERIMETER_COEFFICIENT == pytest.approx(0.1181142, abs=1e-7)
    assert 4 * PERIMETER_COEFFICIENT < 1  # so the corrected area is never negative


def test_empty_full_and_single_node_maps() -> None:
    for shape in [(1, 1), (6, 6), (5, 8)]:
        assert contact_area(np.zeros(shape)) == 0.0
        assert contact_area(np.ones(shape)) == 1.0
        assert contact_perimeter(np.ones(shape, dtype=bool)) == 0
    single = np.zeros((6, 8))
    single[2, 3] = 1.0
    assert contact_perimeter(single > 0) == 4
    assert contact_area(single) == pytest.approx(corrected(1, 4, 48))
    assert contact_area(single, estimator="nodes") == 1 / 48


def test_holes_count_in_the_perimeter() -> None:
    contact = np.zeros((12, 12), dtype=bool)
    contact[2:9, 2:9] = True  # a 7 x 7 block: outer perimeter 28
    contact[4, 4] = False  # a one-node hole: 4 more edges
    contact[6, 5:7] = False  # a two-node hole: 6 more edges
    assert contact_perimeter(contact) == 28 + 4 + 6 == brute_force_perimeter(contact)
    assert contact_area(contact.astype(float)) == pytest.approx(corrected(49 - 3, 38, 144))
    # The holes are part of the contact boundary: filling them removes their edges.
    contact[4, 4] = contact[6, 5] = contact[6, 6] = True
    assert contact_perimeter(contact) == 28


def test_clusters_wrapping_both_boundaries_have_their_interior_perimeter() -> None:
    block = np.zeros((8, 8), dtype=bool)
    block[3:6, 3:6] = True  # an interior 3 x 3 block: perimeter 12
    assert contact_perimeter(block) == 12
    for shift in [(3, 0), (0, 4), (4, 4), (5, 7)]:  # the same block split by one or both edges
        wrapped = np.roll(block, shift, axis=(0, 1))
        assert contact_perimeter(wrapped) == 12
        assert contact_area(wrapped.astype(float)) == contact_area(block.astype(float))
    band = np.zeros((8, 6), dtype=bool)
    band[0, :] = band[7, :] = True  # a band of two rows across the top/bottom edge, around the box
    assert contact_perimeter(band) == 2 * 6
    cross = np.zeros((8, 6), dtype=bool)
    cross[0, :] = cross[:, 0] = True  # wraps both ways: a row and a column
    assert contact_perimeter(cross) == brute_force_perimeter(cross) == 2 * 5 + 2 * 7


@pytest.mark.parametrize(("shape", "density"), [((16, 16), 0.3), ((12, 20), 0.6), ((1, 9), 0.5), ((2, 7), 0.5)])
def test_perimeter_matches_brute_force_and_symmetries(shape: tuple[int, int], density: float) -> None:
    rng = np.random.default_rng([*shape, round(100 * density)])
    for _ in range(20):
        contact = rng.random(shape) < density
        perimeter = contact_perimeter(contact)
        assert perimeter == brute_force_perimeter(contact)
        assert perimeter == contact_perimeter(contact.T) == contact_perimeter(~contact)
        assert perimeter == contact_perimeter(np.roll(contact, (1, -2), axis=(0, 1)))
        n_contact = int(np.count_nonzero(contact))
        area = contact_area(np.where(contact, 1.0, 0.0))
        assert area == pytest.approx(corrected(n_contact, perimeter, contact.size), abs=1e-15)
        assert 0.0 <= area <= n_contact / contact.size


def test_checkerboard_perimeter_is_four_per_node() -> None:
    i, j = np.indices((6, 6))
    contact = (i + j) % 2 == 0
    assert contact_perimeter(contact) == 4 * 18
    with pytest.raises(InvalidParameterError) as info:
        contact_area(np.ones((3, 3)), estimator="exact")
    assert info.value.name == "estimator"


def hertz_area_errors(n: int, offsets: np.ndarray) -> tuple[float, float]:
    """Mean relative area errors (nodes, corrected) of a periodic Hertz contact on an n x n grid.

    A paraboloid ``-r^2 / (2 R)`` (R = 1) in a unit box pressed with the force
    ``F = 4 E* a^3 / (3 R)`` of the Hertz contact radius ``a = 0.05``; the
    periodic images change the radius by a relative O((a / L)^3) ~ 1e-4, well
    below the errors measured here. The centre is placed at sub-grid
    ``offsets`` (fractions of h): the error of one placement oscillates with
    it, the mean over placements is the systematic error.
    """
    from rough_uq.physics.solver import solve_contact

    radius, box = 0.05, 1.0
    force = 4.0 * radius**3 / 3.0
    exact = math.pi * radius**2 / box**2
    h = box / n
    errors = []
    for offset in offsets:
        x = (np.arange(n) + offset[0]) * h - 0.5 * box
        y = (np.arange(n) + offset[1]) * h - 0.5 * box
        heights = -(x[:, None] ** 2 + y[None, :] ** 2) / 2.0
        solution = solve_contact(heights, system_size=box, mean_pressure=force / box**2, tol=1e-10)
        assert solution.converged
        errors.append(
            [contact_area(solution.pressure, estimator=name) / exact - 1.0 for name in ("nodes", "corrected")]
        )
    nodes, corrected_ = np.mean(errors, axis=0)
    return float(nodes), float(corrected_)


def test_corrected_area_converges_faster_on_a_hertz_contact() -> None:
    offsets = np.random.default_rng(1).random((8, 2))
    grids = np.array([128, 256, 512])  # the contact radius spans 6.4 to 25.6 nodes
    errors = np.array([hertz_area_errors(int(n), offsets) for n in grids])
    nodes, corrected_ = np.abs(errors[:, 0]), np.abs(errors[:, 1])
    log_h = np.log2(1.0 / grids)  # the box is 1: h = 1 / n
    rate_nodes = np.polyfit(log_h, np.log2(nodes), 1)[0]
    rate_corrected = np.polyfit(log_h, np.log2(corrected_), 1)[0]
    # The node count overestimates the area by a perimeter term: first order, from above.
    assert np.all(errors[:, 0] > 0)
    assert 0.8 <= rate_nodes <= 1.2
    # The correction removes most of it (measured: 3-5x smaller here) and its error decays faster
    # on these grids (fitted rate 1.3 against 0.95).
    assert np.all(corrected_ < nodes / 2.5)
    assert rate_corrected > rate_nodes + 0.15


def test_the_largest_pressure_of_a_field_of_negative_zeros_is_zero_not_minus_zero() -> None:
    # -0.0 passes as a non-negative pressure; its maximum printed as "-0".
    value = max_pressure(np.full((4, 4), -0.0))
    assert value == 0.0 and math.copysign(1.0, value) == 1.0
