"""Quantities of interest of a contact solution (SPEC section 4).

Conventions
-----------
* Fields are nodal arrays of shape ``(n0, n1)`` on the periodic grid of
  :mod:`rough_uq.physics.fft`. A node is *in contact* when its pressure is strictly
  positive (``p > 0``); the solver returns exact zeros outside the contact.
* Values are raw: area fractions in ``[0, 1]``, cluster counts as absolute
  numbers, gaps and pressures in the units of the solution (length unit of
  ``L``, pressure unit of ``E*``). Conversion to percent or per unit area
  happens where the study is reported, not here.
* Clusters are connected components of the contact set on the *periodic*
  grid: a cluster that crosses an edge of the box counts once. With
  4-connectivity nodes sharing an edge are neighbours; with 8-connectivity
  nodes sharing a corner are too, including across the periodic edges and
  corners (node ``(0, 0)`` touches ``(n0 - 1, n1 - 1)``).
* On a grid, 4-connectivity splits clusters that touch only at corners and
  8-connectivity merges clusters that are merely close: as the grid is refined
  the 4-count approaches the limit from above and the 8-count from below. The
  ``clusters`` quantity may therefore also be their mean (connectivity
  ``"mean"``, :data:`CLUSTER_COUNTS`), whose errors partly cancel: on the
  classic cluster setting it is the only one of the three within ``eps = 2``
  per unit area of the limit on grids up to 1536^2 (README, "The classic
  study").

Contact area
------------
The node count ``N_c / N`` overestimates the true contact area: a node is
counted whole as soon as its centre is in contact, and along the contact
boundary this error does not average out, so the bias is proportional to the
perimeter in grid units and decays only like ``h``. The default estimator is
the perimeter-corrected count of Yastrebov, Anciaux & Molinari ("On the
accurate computation of the true contact-area in mechanical contact of
random rough surfaces", Tribology International 114, 2017)::

    A / A_0 = (N_c - c P) / N,    c = (pi - 1 + ln 2) / 24 ~= 0.1181,

with ``P`` the number of edges between a contact node and a non-contact
4-neighbour on the periodic grid (the outer boundary of every cluster and the
boundary of every hole; each such edge counted once). ``c`` is the paper's
coefficient for a boundary of random orientation. ``P <= 4 N_c`` and
``4 c < 1``, so the corrected area lies in ``[0, N_c / N]``; it is ``1`` for
full contact and ``0`` for none. ``"nodes"`` keeps the plain count.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from rough_uq.errors import InvalidParameterError, is_integer, is_one_of, is_real_number, refuse_non_real

__all__ = [
    "QOI_NAMES",
    "CONNECTIVITIES",
    "CLUSTER_COUNTS",
    "AREA_ESTIMATORS",
    "PERIMETER_COEFFICIENT",
    "contact_area",
    "contact_perimeter",
    "count_clusters",
    "cluster_count",
    "label_clusters",
    "mean_gap",
    "max_pressure",
    "area_above",
    "evaluate_qoi",
]

#: Names accepted by :func:`evaluate_qoi`, in a fixed order.
QOI_NAMES = ("contact_area", "clusters", "mean_gap", "max_pressure", "area_above")

#: Neighbourhoods accepted for cluster counting and labelling.
CONNECTIVITIES = (4, 8)

#: Settings of the ``clusters`` quantity: a neighbourhood, or ``"mean"`` of the 4- and 8-connected counts.
CLUSTER_COUNTS = (4, 8, "mean")

#: Contact-area estimators: perimeter-corrected (default) and plain node count.
AREA_ESTIMATORS = ("corrected", "nodes")

#: ``c`` of the corrected contact area ``(N_c - c P) / N`` (module docstring).
PERIMETER_COEFFICIENT = (math.pi - 1.0 + math.log(2.0)) / 24.0


def _grid_shaped(name: str, array: np.ndarray) -> np.ndarray:
    """``array`` if it is a non-empty 2-d grid ``(n0, n1)``, else :class:`InvalidParameterError` naming ``name``.

    The shape check of every field and contact map: a 1-d, 3-d or scalar
    field would otherwise give a contact area, mean or maximum of nodes that
    are no grid (the perimeter and the clusters need two axes).
    """
    if array.ndim != 2 or array.size == 0:
        raise InvalidParameterError(name, f"array of shape {array.shape}", "a non-empty 2-d array")
    return array


def _field(name: str, values: object) -> np.ndarray:
    """A non-empty, finite 2-d float64 array, or :class:`InvalidParameterError` naming ``name``.

    A NaN would silently compare as "not in contact", so it is refused here;
    so are complex numbers (converting drops the imaginary part, with a numpy
    warning), booleans (a contact map is no pressure or gap field) and Python
    objects (integers beyond int64 among them), as :func:`solve_contact` refuses them.
    """
    if values is None:  # asarray(None, float) is a NaN, which would read as "non-finite entries"
        raise InvalidParameterError(name, None, "an array of finite numbers")
    try:
        array = np.asarray(values)
    except ValueError:  # numpy refuses a ragged sequence
        raise InvalidParameterError(name, "a ragged sequence (rows of different lengths)", "a 2-d array") from None
    refuse_non_real(name, array)
    array = _grid_shaped(name, array.astype(np.float64, copy=False))
    if not np.all(np.isfinite(array)):
        raise InvalidParameterError(name, "an array with non-finite entries", "finite values")
    return array


def _pressure(values: object) -> np.ndarray:
    """:func:`_field` of a contact pressure, which must also be non-negative.

    Contact is ``pressure > 0``: a field of the opposite sign (tension
    positive, or a load given with the wrong sign) would silently read as no
    contact at all, so it is refused here.
    """
    array = _field("pressure", values)
    lowest = float(array.min())
    if lowest < 0.0:
        raise InvalidParameterError(
            "pressure", f"an array with negative entries (the lowest is {lowest:.3g})", "non-negative values"
        )
    return array


def _contact_map(name: str, contact: object) -> np.ndarray:
    allowed = "a boolean array (e.g. pressure > 0)"
    if contact is None:  # "array of dtype object" said less than None
        raise InvalidParameterError(name, None, allowed)
    array = np.asarray(contact)
    if array.dtype != np.bool_:
        raise InvalidParameterError(name, f"array of dtype {array.dtype}", allowed)
    return _grid_shaped(name, array)


def _is_setting(value: object, allowed: tuple) -> bool:
    """``value`` is one of ``allowed``: a string, or an integer (not a bool, not a float equal to one, like 8.0)."""
    return (isinstance(value, str) or is_integer(value)) and value in allowed


def _check_cluster_count(connectivity: object) -> object:
    if not _is_setting(connectivity, CLUSTER_COUNTS):
        raise InvalidParameterError("connectivity", connectivity, "4, 8 or 'mean'")
    return connectivity


def cluster_count(contact: np.ndarray, connectivity: int | str) -> float:
    """Clusters of a contact map: :func:`count_clusters` with 4 or 8, or the mean of both with ``"mean"``."""
    if _check_cluster_count(connectivity) == "mean":
        return 0.5 * (count_clusters(contact, connectivity=4) + count_clusters(contact, connectivity=8))
    return float(count_clusters(contact, connectivity=connectivity))


def _structure(connectivity: object) -> np.ndarray:
    if not _is_setting(connectivity, CONNECTIVITIES):
        raise InvalidParameterError("connectivity", connectivity, "4 or 8")
    if connectivity == 4:
        return ndimage.generate_binary_structure(2, 1)
    return np.ones((3, 3), dtype=bool)


def contact_perimeter(contact: np.ndarray) -> int:
    """Number of edges between a contact node and a non-contact 4-neighbour (periodic grid).

    Every pair of edge-sharing nodes with different states counts once, the
    pairs across the periodic edges included, so the boundaries of holes count
    as well as the outer boundaries of clusters. On a grid of one row (or
    column) a node is its own neighbour along that axis, which adds nothing.

    Parameters
    ----------
    contact : ndarray of bool, shape (n0, n1)
        Contact map (e.g. ``pressure > 0``).

    Returns
    -------
    int
        The perimeter ``P`` in grid edges (multiply by ``h`` for a length).

    Raises
    ------
    InvalidParameterError
        If ``contact`` is not a non-empty 2-d boolean array.
    """
    contact = _contact_map("contact", contact)
    # Compare each node with its successor along each axis, the last with the first;
    # slices instead of np.roll avoid copying the whole map.
    perimeter = np.count_nonzero(contact[1:, :] != contact[:-1, :])
    perimeter += np.count_nonzero(contact[0, :] != contact[-1, :])
    perimeter += np.count_nonzero(contact[:, 1:] != contact[:, :-1])
    perimeter += np.count_nonzero(contact[:, 0] != contact[:, -1])
    return int(perimeter)


def _check_estimator(estimator: object) -> str:
    if not isinstance(estimator, str) or estimator not in AREA_ESTIMATORS:
        raise InvalidParameterError("estimator", estimator, "'corrected' or 'nodes'")
    return estimator


def contact_area(pressure: np.ndarray, *, estimator: str = "corrected") -> float:
    """Real contact area as a fraction of the nominal area.

    Parameters
    ----------
    pressure : array_like, shape (n0, n1)
        Contact pressure (unit of ``E*``), finite and non-negative; contact is ``pressure > 0``.
    estimator : {"corrected", "nodes"}
        ``"corrected"`` (default): ``(N_c - c P) / N`` with the perimeter ``P``
        of :func:`contact_perimeter` and ``c`` = :data:`PERIMETER_COEFFICIENT`
        (module docstring); ``"nodes"``: the fraction of nodes in contact,
        ``N_c / N``.

    Returns
    -------
    float
        Area fraction in ``[0, 1]`` (dimensionless).

    Raises
    ------
    InvalidParameterError
        If ``pressure`` is not a non-empty 2-d array of finite, non-negative
        numbers (a 1-d field included, whatever the estimator), or for an
        unknown ``estimator``.
    """
    estimator = _check_estimator(estimator)
    contact = _pressure(pressure) > 0.0
    n_contact = np.count_nonzero(contact)
    if estimator == "nodes" or n_contact == 0 or n_contact == contact.size:
        return float(n_contact / contact.size)
    corrected = n_contact - PERIMETER_COEFFICIENT * contact_perimeter(contact)
    return float(corrected / contact.size)


def area_above(pressure: np.ndarray, critical_pressure: float) -> float:
    """Fraction of nodes whose pressure exceeds ``critical_pressure``.

    Parameters
    ----------
    pressure : array_like, shape (n0, n1)
        Contact pressure (unit of ``E*``), finite and non-negative.
    critical_pressure : float
        Threshold (unit of ``E*``), finite and ``>= 0``; 0 gives the node count
        fraction, :func:`contact_area` with ``estimator="nodes"``.

    Returns
    -------
    float
        ``mean(pressure > critical_pressure)``, in ``[0, 1]`` (dimensionless).

    Raises
    ------
    InvalidParameterError
        If ``pressure`` is not a non-empty 2-d array of finite, non-negative
        numbers, or ``critical_pressure`` not a finite number >= 0.
    """
    threshold = float(critical_pressure) if is_real_number(critical_pressure) else math.nan
    if not (np.isfinite(threshold) and threshold >= 0.0):
        raise InvalidParameterError("critical_pressure", critical_pressure, "a finite number >= 0")
    array = _pressure(pressure)
    return float(np.count_nonzero(array > threshold) / array.size)


def mean_gap(gap: np.ndarray) -> float:
    """Mean gap between the surfaces (unit of ``L``), zero-gap contact nodes included.

    Raises
    ------
    InvalidParameterError
        If ``gap`` is not a non-empty 2-d array ``(n0, n1)`` of finite numbers.
    """
    return float(np.mean(_field("gap", gap)))


def max_pressure(pressure: np.ndarray) -> float:
    """Largest nodal pressure (unit of ``E*``).

    Raises
    ------
    InvalidParameterError
        If ``pressure`` is not a non-empty 2-d array ``(n0, n1)`` of finite, non-negative numbers.
    """
    return float(np.max(_pressure(pressure))) + 0.0  # + 0.0: a field of -0.0 (no contact) has maximum 0, not -0


def _periodic_components(contact: np.ndarray, connectivity: int) -> tuple[np.ndarray, np.ndarray, int]:
    """Non-periodic labels, the periodic component of each label, and the component count.

    ``scipy.ndimage.label`` labels the open grid; labels that touch across a
    periodic edge are then merged as the connected components of the graph
    whose edges are those touching label pairs.

    Returns
    -------
    labels : ndarray of int, shape (n0, n1)
        ``ndimage.label`` output (0 = no contact, 1..n_labels).
    component : ndarray of int64, shape (n_labels,)
        Component of label ``l`` at ``component[l - 1]``, numbered ``0, 1, ...``
        in the order of each component's first node in C (raster) order.
    n_components : int
    """
    labels, n_labels = ndimage.label(contact, structure=_structure(connectivity))
    if n_labels == 0:
        return labels, np.zeros(0, dtype=np.int64), 0
    # Node (0, j) touches (n0 - 1, j + s) for s = 0 (and s = -1, 1 with diagonals),
    # columns likewise; np.roll(x, s)[j] = x[j - s] wraps those shifts around the corners.
    shifts = (0,) if connectivity == 4 else (-1, 0, 1)
    first_edge = []
    second_edge = []
    for near, far in ((labels[0, :], labels[-1, :]), (labels[:, 0], labels[:, -1])):
        for shift in shifts:
            first_edge.append(near)
            second_edge.append(np.roll(far, shift))
    a = np.concatenate(first_edge)
    b = np.concatenate(second_edge)
    touching = (a > 0) & (b > 0) & (a != b)
    if not np.any(touching):
        return labels, np.arange(n_labels, dtype=np.int64), n_labels
    a = a[touching] - 1
    b = b[touching] - 1
    graph = coo_matrix((np.ones(a.size, dtype=np.int8), (a, b)), shape=(n_labels, n_labels)).tocsr()
    n_components, component = connected_components(graph, directed=False)
    # ndimage numbers labels in raster order of their first node; renumber the
    # components by their smallest label so the numbering is raster order too.
    _, first_label, inverse = np.unique(component, return_index=True, return_inverse=True)
    rank = np.empty(first_label.size, dtype=np.int64)
    rank[np.argsort(first_label, kind="stable")] = np.arange(first_label.size)
    return labels, rank[inverse], int(n_components)


def label_clusters(contact: np.ndarray, *, connectivity: int = 4) -> np.ndarray:
    """Label the connected contact clusters on the periodic grid.

    Parameters
    ----------
    contact : ndarray of bool, shape (n0, n1)
        Contact map (e.g. ``pressure > 0``).
    connectivity : {4, 8}
        4: neighbours share an edge; 8: an edge or a corner (module docstring).

    Returns
    -------
    ndarray of int64, shape (n0, n1)
        0 outside the contact; clusters numbered ``1, 2, ...`` in the raster
        order of their first node. A cluster crossing the periodic boundary
        has one label.

    Raises
    ------
    InvalidParameterError
        If ``contact`` is not a non-empty 2-d boolean array, or for a bad ``connectivity``.
    """
    contact = _contact_map("contact", contact)
    labels, component, _ = _periodic_components(contact, connectivity)
    lookup = np.zeros(component.size + 1, dtype=np.int64)
    lookup[1:] = component + 1
    return lookup[labels]


def count_clusters(contact: np.ndarray, *, connectivity: int = 4) -> int:
    """Number of connected contact clusters on the periodic grid.

    Parameters
    ----------
    contact : ndarray of bool, shape (n0, n1)
        Contact map (e.g. ``pressure > 0``).
    connectivity : {4, 8}
        4: neighbours share an edge; 8: an edge or a corner (module docstring).

    Returns
    -------
    int
        Absolute number of clusters (a cluster crossing the boundary counts once).

    Raises
    ------
    InvalidParameterError
        If ``contact`` is not a non-empty 2-d boolean array, or for a bad ``connectivity``.
    """
    contact = _contact_map("contact", contact)
    return _periodic_components(contact, connectivity)[2]


def ordered_names(label: str, names: object, allowed: str) -> tuple[str, ...]:
    """A name or an ordered collection of names as a tuple of plain ``str``; refused naming ``label``.

    A set is refused: its order changes from one process to the next (string
    hashing is randomised), and the order of the names is the order of the
    values, of the result's columns and of a list of tolerances. Whether each
    name is allowed is the caller's check.
    """
    if isinstance(names, str):
        return (str(names),)
    if isinstance(names, (set, frozenset)):
        raise InvalidParameterError(label, names, allowed + " in a list or tuple (a set has no fixed order)")
    try:
        listed = tuple(names)  # type: ignore[arg-type]
    except TypeError:
        raise InvalidParameterError(label, names, allowed) from None
    if not all(isinstance(name, str) for name in listed):
        # The value as given: b'contact_area' read as (99, 111, ...) once made a tuple.
        raise InvalidParameterError(label, names, allowed)
    return tuple(str(name) for name in listed)


def _names(names: object) -> tuple[str, ...]:
    """``names`` of :func:`evaluate_qoi` as a tuple, or :class:`InvalidParameterError` naming ``names``."""
    names = ordered_names("names", names, "a name or a list of names from " + ", ".join(QOI_NAMES))
    for name in names:
        if not is_one_of(name, QOI_NAMES):
            raise InvalidParameterError("names", name, "one of " + ", ".join(QOI_NAMES))
    return names


def _gap(gap: object, shape: tuple[int, ...]) -> np.ndarray:
    """The gap field of ``"mean_gap"``: finite, of the pressure's ``shape`` (the nodes it averages over)."""
    if gap is None:
        raise InvalidParameterError("gap", None, "a gap field when 'mean_gap' is requested")
    array = _field("gap", gap)
    if array.shape != shape:
        raise InvalidParameterError(
            "gap", f"an array of shape {array.shape}", f"an array of the pressure's shape {shape}"
        )
    return array


def evaluate_qoi(
    names: Iterable[str] | str,
    *,
    pressure: np.ndarray,
    gap: np.ndarray | None = None,
    connectivity: int | str = 4,
    critical_pressure: float | None = None,
    area_estimator: str = "corrected",
) -> np.ndarray:
    """Evaluate the requested quantities of interest of one contact solution.

    Only the requested quantities are computed (no cluster labelling unless
    ``"clusters"`` is asked for); a name given twice is computed once.
    ``"area_above"`` is always a node count (the perimeter correction is
    derived for the contact boundary only).

    Parameters
    ----------
    names : str or ordered iterable of str (a list, a tuple; not a set)
        Names from :data:`QOI_NAMES`: ``"contact_area"`` (fraction, by
        ``area_estimator``),
        ``"clusters"`` (absolute count), ``"mean_gap"`` (unit of ``L``),
        ``"max_pressure"`` (unit of ``E*``), ``"area_above"`` (fraction above
        ``critical_pressure``). A single string is one name.
    pressure : array_like, shape (n0, n1)
        Contact pressure (unit of ``E*``), finite and non-negative.
    gap : array_like, shape (n0, n1), optional
        Gap (unit of ``L``); required for ``"mean_gap"``.
    connectivity : {4, 8, "mean"}
        Neighbourhood for ``"clusters"``, or the mean of the 4- and
        8-connected counts (:func:`cluster_count`).
    critical_pressure : float, optional
        Threshold (unit of ``E*``); required for ``"area_above"``.
    area_estimator : {"corrected", "nodes"}
        Estimator of ``"contact_area"`` (:func:`contact_area`).

    Returns
    -------
    ndarray of float64, shape (len(names),)
        One value per name, in the order given.

    Raises
    ------
    InvalidParameterError
        An unknown name, or ``names`` that are not an ordered iterable of
        strings (``name="names"``, listing the allowed ones), a missing ``gap`` / ``critical_pressure``, a
        ``gap`` of another shape than ``pressure``, a bad ``connectivity`` or
        ``area_estimator`` (``name="estimator"``), a field that is not a
        non-empty 2-d array of real numbers (complex, boolean and object arrays
        are refused, not converted), a non-finite field, or a negative pressure.
    """
    names = _names(names)
    _check_cluster_count(connectivity)  # a bad setting is an error even when clusters are not asked for
    _check_estimator(area_estimator)
    pressure = _pressure(pressure)
    values: dict[str, float] = {}
    for name in names:
        if name in values:
            continue
        if name == "contact_area":
            values[name] = contact_area(pressure, estimator=area_estimator)
        elif name == "clusters":
            values[name] = cluster_count(pressure > 0.0, connectivity)
        elif name == "mean_gap":
            values[name] = mean_gap(_gap(gap, pressure.shape))
        elif name == "max_pressure":
            values[name] = max_pressure(pressure)
        else:  # "area_above"
            if critical_pressure is None:
                raise InvalidParameterError(
                    "critical_pressure", None, "a number >= 0 when 'area_above' is requested"
                )
            values[name] = area_above(pressure, critical_pressure)
    return np.array([values[name] for name in names], dtype=np.float64)
