"""Fast, exact tests of the ReSTIR neighbour search (``_knn``) and the scene watches
(``_scene_watch``): brute-force numpy references on integer coordinates (exact float32
distances, so ties and the strict radius are tested exactly), and the watches on tiny scenes
without rendering. Written for the mutation audit (scripts/mutation.sh)."""
from __future__ import annotations

import gc
import sys
import time

import numpy as np
import pytest

import torchir

torchir.backend.set_variant("auto")
import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

from torchir.integrators import _knn  # noqa: E402
from torchir.integrators._knn import (  # noqa: E402
    NeighbourSearch, ScreenLayout, _cell_coords, _grid_build, _insert_top_k, have_scipy, knn, knn_grid, knn_kdtree, knn_screen,
)
from torchir.integrators import _scene_watch  # noqa: E402
from torchir.integrators._scene_watch import EmitterWatch, GeometryWatch, _fingerprint, _has_nonzero, as_tuples  # noqa: E402
from tests.helpers import RES  # noqa: E402


# ------------------------------------------------------------------------------ helpers
def _pts(a: np.ndarray) -> mi.Point3f:
    a = np.asarray(a, np.float32).reshape(-1, 3)
    return mi.Point3f(*(mi.Float(np.ascontiguousarray(a[:, i])) for i in range(3)))


def _np(cols) -> np.ndarray:
    return np.stack([np.asarray(c) for c in cols], 1)


def brute(P, Q, k, radius, exclude_self=False, valid=None, q_valid=None, allowed=None):
    """(index, ok) of shape (nq, k): the k nearest valid points strictly within radius,
    ascending distance, ties by index; index 0 where not ok."""
    P, Q = np.asarray(P, np.float64), np.asarray(Q, np.float64)
    nq, n = len(Q), len(P)
    idx, ok = np.zeros((nq, k), np.int64), np.zeros((nq, k), bool)
    for q in range(nq):
        if q_valid is not None and not q_valid[q]:
            continue
        d2 = ((P - Q[q]) ** 2).sum(1)
        cand = [j for j in range(n) if d2[j] < radius * radius and (valid is None or valid[j])
                and not (exclude_self and j == q) and (allowed is None or allowed(q, j))]
        cand.sort(key=lambda j: (d2[j], j))
        for i, j in enumerate(cand[:k]):
            idx[q, i], ok[q, i] = j, True
    return idx, ok


def check(result, want, zeros=True):
    idx, ok = result
    assert np.array_equal(_np(ok), want[1])
    if zeros:
        assert np.array_equal(_np(idx), want[0])  # index 0 where not ok
    else:  # screen search: the index of an invalid query is left as searched
        assert np.array_equal(np.where(want[1], _np(idx), 0), want[0])
    assert all(type(i) is mi.UInt32 for i in idx) and all(type(o) is mi.Bool for o in ok)


def _int_cloud(n, seed, hi=4):
    return np.random.default_rng(seed).integers(0, hi, (n, 3)).astype(np.float32)


# ------------------------------------------------------------------------------ world space
@pytest.mark.parametrize("fn", [knn_kdtree, knn_grid, lambda *a: knn(*a[:4], "auto", *a[4:])])
@pytest.mark.parametrize("exclude_self", [False, True])
def test_exact_neighbours_against_brute_force(fn, exclude_self):
    P = _int_cloud(70, 0)  # many duplicates and exact ties
    Q = P if exclude_self else _int_cloud(40, 1, hi=5) - 0.5 * (np.arange(120).reshape(40, 3) % 2)
    for radius in (1.5, 2.0):  # 2.0: points at distance exactly 2 are excluded (strictly closer)
        check(fn(_pts(P), _pts(Q), 3, radius, exclude_self), brute(P, Q, 3, radius, exclude_self))
    shift = np.array([7.0, -3.0, 2.5], np.float32)  # the grid's lower corner is not the origin
    check(fn(_pts(P + shift), _pts(Q + shift), 3, 1.5, exclude_self), brute(P, Q, 3, 1.5, exclude_self))


@pytest.mark.parametrize("fn", [knn_kdtree, knn_grid])
def test_ties_by_index_and_k_larger_than_available(fn):
    # four points at distance 1 of the origin, listed in reverse, a duplicate of the query, one at 1.5
    P = np.array([[0, 0, 1.5], [0, 0, -1], [0, -1, 0], [-1, 0, 0], [1, 0, 0], [0, 0, 0], [0, 0, 0]], np.float32)
    Q = np.array([[0, 0, 0], [9, 9, 9]], np.float32)
    for k, radius in ((3, 1.2), (4, 1.0001), (9, 2.0), (9, 1.0)):
        check(fn(_pts(P), _pts(Q), k, radius), brute(P, Q, k, radius))
    check(fn(_pts(P), _pts(P), 3, 1.2, True), brute(P, P, 3, 1.2, True))


@pytest.mark.parametrize("fn", [knn_kdtree, knn_grid])
def test_empty_sets(fn):
    empty, two = _pts(np.zeros((0, 3))), _pts(np.zeros((2, 3)))
    check(fn(empty, two, 2, 1.0), (np.zeros((2, 2), int), np.zeros((2, 2), bool)))
    check(fn(two, empty, 2, 1.0), (np.zeros((0, 2), int), np.zeros((0, 2), bool)))
    check(fn(two, two, 3, 1.0), brute(np.zeros((2, 3)), np.zeros((2, 3)), 3, 1.0))
    one, near = np.array([[0.0, 0.0, 0.5]]), np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 1.0], [5.0, 0.0, 0.0]])
    check(fn(_pts(one), _pts(near), 2, 1.0), brute(one, near, 2, 1.0))  # a single point
    check(fn(_pts(near), _pts(one), 2, 1.0), brute(near, one, 2, 1.0))  # a single query


def test_grid_equals_kdtree_on_random_float_points_and_a_coarsened_grid():
    rng = np.random.default_rng(5)
    P = rng.random((400, 3)).astype(np.float32)
    Q = rng.random((300, 3)).astype(np.float32)
    for radius in (0.1, 0.003):
        a, b = knn_kdtree(_pts(P), _pts(Q), 3, radius), knn_grid(_pts(P), _pts(Q), 3, radius)
        check(a, (_np(b[0]), _np(b[1])))
        check(a, brute(P, Q, 3, radius))
    assert 0 < _np(knn_grid(_pts(P), _pts(Q), 3, 0.1)[1]).mean() < 1
    idx, ok = knn_grid(_pts(P), _pts(P), 3, 0.0)  # radius 0: nothing is strictly closer
    assert not _np(ok).any()


def test_grid_build_bounds_the_cell_count():
    P = _pts(np.array([[0, 0, 0], [1, 1, 1], [0.5, 0.2, 0.1]]))
    lo, dims, cell = _grid_build(P, 0.25)
    assert lo == [0.0, 0.0, 0.0] and dims == [5, 5, 5] and cell == 0.25
    assert _grid_build(_pts(np.array([[0, 0, 0], [2, 0.5, 0]])), 1.0)[1:] == ([3, 1, 1], 1.0)
    lo, dims, cell = _grid_build(P, 1 / 200)  # 201^3 > 2^22 cells: one doubling
    assert cell == 2 / 200 and dims == [101, 101, 101]
    lo, dims, cell = _grid_build(P, 0.0)
    assert 0 < cell < 0.01 and np.log2(cell / 1e-12) % 1 == 0 and np.prod(dims) <= _knn._MAX_CELLS
    assert _knn._MAX_CELLS == 1 << 22
    assert _grid_build(_pts(np.array([[-2, 1, 5], [0, 1, 5.5]])), 1.0) == ([-2.0, 1.0, 5.0], [3, 1, 1], 1.0)
    corners = _pts(np.array([[0, 0, 0], [255, 255, 63]]))  # exactly 2^22 cells of 1: no coarsening
    assert _grid_build(corners, 1.0)[1:] == ([256, 256, 64], 1.0)


def test_cell_coords_relative_to_the_lower_corner_and_clipped():
    p = _pts(np.array([[7.0, -3.0, 2.5], [8.6, -1.4, 4.0], [5.0, -9.0, 99.0], [11.0, 0.0, 3.0]]))
    got = [np.asarray(c).tolist() for c in _cell_coords(p, [7.0, -3.0, 2.5], [3, 3, 2], 0.75)]
    assert got == [[0, 2, 0, 2], [0, 2, 0, 2], [0, 1, 1, 0]]


def test_kdtree_queries_only_the_columns_it_needs(monkeypatch):
    import scipy.spatial

    ks = []

    class Tree(scipy.spatial.cKDTree):
        def query(self, *a, **kw):
            ks.append(kw["k"])
            assert kw["workers"] == -1
            return super().query(*a, **kw)

    monkeypatch.setattr(scipy.spatial, "cKDTree", Tree)
    rng = np.random.default_rng(7)
    P, Q = rng.random((50, 3)).astype(np.float32), rng.random((20, 3)).astype(np.float32)
    check(knn_kdtree(_pts(P), _pts(Q), 3, 0.5), brute(P, Q, 3, 0.5))
    check(knn_kdtree(_pts(P), _pts(P), 3, 0.5, True), brute(P, P, 3, 0.5, True))
    check(knn_kdtree(_pts(P), _pts(Q), 3, 0.15), brute(P, Q, 3, 0.15))  # rows with fewer than 3
    assert ks == [4, 5, 4]  # no ties: one more column than kept
    ring = np.array([[1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1], [5, 5, 5], [6, 6, 6],
                     [7, 7, 7], [8, 8, 8], [9, 9, 9]], np.float32)[::-1].copy()
    ks.clear()
    check(knn_kdtree(_pts(ring), _pts(np.zeros((1, 3))), 2, 1.5), brute(ring, np.zeros((1, 3)), 2, 1.5))
    assert ks == [3, 6, 11]  # six ties at the 2nd distance: doubled until the tie is passed, at most n
    ks.clear()
    check(knn_kdtree(_pts(ring[5:]), _pts(np.zeros((1, 3))), 2, 1.5), brute(ring[5:], np.zeros((1, 3)), 2, 1.5))
    assert ks == [3, 6]  # all six points tied: stops at n


def test_insert_top_k_orders_by_distance_then_index():
    bd, bi = [mi.Float(np.inf)] * 3, [mi.UInt32(0xFFFFFFFF)] * 3
    for d, i, a in ((2.0, 7, True), (1.0, 9, True), (2.0, 3, True), (0.5, 1, False), (1.0, 9, True), (3.0, 0, True)):
        _insert_top_k(bd, bi, mi.Bool(a), mi.Float(d), mi.UInt32(i))
    assert [float(x[0]) for x in bd] == [1.0, 1.0, 2.0] and [int(x[0]) for x in bi] == [9, 9, 3]


def test_knn_dispatch(monkeypatch):
    assert have_scipy() and _knn._default_backend() == "kdtree"
    with pytest.raises(ValueError, match=r"^nn_backend must be 'auto', 'kdtree' or 'grid', got 'ball'$"):
        knn(_pts(np.zeros((1, 3))), _pts(np.zeros((1, 3))), 1, 1.0, "ball")
    monkeypatch.setattr(_knn, "knn_grid", lambda *a: ("grid", a))
    monkeypatch.setattr(_knn, "knn_kdtree", lambda *a: ("kdtree", a))
    assert knn(1, 2, 3, 4.0) == ("kdtree", (1, 2, 3, 4.0, False))
    assert knn(1, 2, 3, 4.0, "grid", True) == ("grid", (1, 2, 3, 4.0, True))
    assert knn(1, 2, 3, 4.0, "kdtree", True) == ("kdtree", (1, 2, 3, 4.0, True))
    monkeypatch.setattr(mi, "variant", lambda: "cuda_ad_rgb")
    assert _knn._default_backend() == "grid" and knn(1, 2, 3, 4.0)[0] == "grid"
    assert NeighbourSearch().candidates(None) == ("grid",)
    monkeypatch.undo()
    monkeypatch.setitem(sys.modules, "scipy.spatial", None)  # import fails
    assert not have_scipy() and _knn._default_backend() == "grid"
    assert NeighbourSearch().candidates(ScreenLayout(1, 1, 1)) == ("grid", "screen")


# ------------------------------------------------------------------------------ screen space
W, H, SPP = 5, 4, 2


def _screen_points(seed):
    """Samples near their own pixel (integer offsets of -1..1: some lie in a neighbour pixel)."""
    rng = np.random.default_rng(seed)
    lane = np.arange(W * H * SPP)
    pix = lane // SPP
    p = np.stack([pix % W, pix // W, np.zeros(len(lane))], 1) + rng.integers(-1, 2, (len(lane), 3))
    return p.astype(np.float32)


def _window_rule(wins):
    def allowed(q, j):
        pq, pj = q // SPP, j // SPP
        return abs(pq % W - pj % W) <= wins[q] and abs(pq // W - pj // W) <= wins[q]
    return allowed


@pytest.mark.parametrize("exclude_self", [False, True])
def test_screen_search_is_exact_within_its_window(exclude_self):
    n = W * H * SPP
    P = _screen_points(0)
    Q = P if exclude_self else _screen_points(1)
    rng = np.random.default_rng(2)
    valid = rng.random(n) < 0.8
    per_query = rng.integers(0, 4, n).astype(np.uint32)
    for window, windows, radius in ((2, None, 10.0), (1, None, 10.0), (0, None, 10.0), (2, per_query, 10.0), (1, None, 1.5), (2, None, 2.0)):
        wins = np.full(n, window) if windows is None else np.minimum(windows, window)
        got = knn_screen(_pts(P), mi.Bool(valid), _pts(Q), ScreenLayout(W, H, SPP, window), 3, radius, exclude_self,
                         None if windows is None else mi.UInt32(windows))
        check(got, brute(P, Q, 3, radius, exclude_self, valid, allowed=_window_rule(wins)))


@pytest.mark.parametrize("exclude_self", [False, True])
def test_screen_chains_search_only_their_own_sample_index(exclude_self):
    """``chains``: sample s of a pixel finds the exact k nearest among samples s of its window."""
    n = W * H * SPP
    P = _screen_points(6)
    Q = P if exclude_self else _screen_points(7)
    valid = np.random.default_rng(8).random(n) < 0.8
    in_window = _window_rule(np.full(n, 2))
    same_chain = lambda q, j: in_window(q, j) and q % SPP == j % SPP  # noqa: E731
    want = brute(P, Q, 3, 10.0, exclude_self, valid, allowed=same_chain)
    check(knn_screen(_pts(P), mi.Bool(valid), _pts(Q), ScreenLayout(W, H, SPP, 2, chains=True), 3, 10.0, exclude_self), want)
    every = brute(P, Q, 3, 10.0, exclude_self, valid, allowed=in_window)
    assert not np.array_equal(every[0], want[0])
    first = np.arange(W * H) * SPP  # one sample per pixel: chains change nothing
    P1, valid1 = P[first], valid[first]
    want1 = brute(P1, P1, 3, 10.0, False, valid1, allowed=lambda q, j: abs(q % W - j % W) <= 2 and abs(q // W - j // W) <= 2)
    check(knn_screen(_pts(P1), mi.Bool(valid1), _pts(P1), ScreenLayout(W, H, 1, 2, chains=True), 3, 10.0), want1)
    assert want1[1].any()


def test_neighbour_search_keeps_chains_on_the_screen_search():
    layout = ScreenLayout(W, H, SPP, 2, chains=True)
    assert layout.searches_chains and not ScreenLayout(W, H, 1, 2, chains=True).searches_chains
    assert NeighbourSearch().candidates(layout) == ("screen",)
    assert NeighbourSearch().candidates(ScreenLayout(W, H, 1, 2, chains=True))[-1] == "screen"
    assert len(NeighbourSearch().candidates(ScreenLayout(W, H, 1, 2, chains=True))) > 1


def test_screen_search_equals_kdtree_and_grid_where_the_window_covers_the_radius():
    n = W * H * SPP
    P, Q = _screen_points(3), _screen_points(4)
    valid = np.random.default_rng(5).random(n) < 0.7
    want = brute(P, Q, 3, 1.5, False, valid)
    # offsets of at most 1 pixel: every point within 1.5 projects within 3 pixels
    check(knn_screen(_pts(P), mi.Bool(valid), _pts(Q), ScreenLayout(W, H, SPP, 3), 3, 1.5), want)
    for backend in ("kdtree", "grid", "screen"):
        s = NeighbourSearch(backend)
        check(s(_pts(P), mi.Bool(valid), _pts(Q), mi.Bool(np.ones(n, bool)), 3, 1.5, layout=ScreenLayout(W, H, SPP, 3)), want)
        assert s.last == backend


def test_screen_layout_width_error_and_default_window():
    assert ScreenLayout(3, 2, 1).window == 2
    p = _pts(np.zeros((12, 3)))
    with pytest.raises(ValueError, match=r"^knn_screen: points and queries must have 12 lanes \(3x2x2\), got 12 and 11$"):
        knn_screen(p, mi.Bool(np.ones(12, bool)), _pts(np.zeros((11, 3))), ScreenLayout(3, 2, 2), 2, 1.0)
    with pytest.raises(ValueError, match=r"^knn_screen: points and queries must have 6 lanes \(3x2x1\), got 12 and 12$"):
        knn_screen(p, mi.Bool(np.ones(12, bool)), p, ScreenLayout(3, 2, 1), 2, 1.0)


# ------------------------------------------------------------------------------ NeighbourSearch
@pytest.mark.parametrize("backend", ["kdtree", "grid", "screen"])
@pytest.mark.parametrize("exclude_self", [False, True])
def test_neighbour_search_full_width_with_validity_masks(backend, exclude_self):
    n = W * H * SPP
    P = _screen_points(6)
    Q = P if exclude_self else _screen_points(7)
    rng = np.random.default_rng(8)
    valid = rng.random(n) < 0.75
    q_valid = valid if exclude_self else rng.random(n) < 0.8
    want = brute(P, Q, 3, 1.5, exclude_self, valid, q_valid)
    s = NeighbourSearch(backend)
    check(s(_pts(P), mi.Bool(valid), _pts(Q), mi.Bool(q_valid), 3, 1.5, exclude_self, ScreenLayout(W, H, SPP, 3)), want,
          backend != "screen")
    assert s.last == backend
    check(s(_pts(P), mi.Bool(valid), _pts(Q), mi.Bool(q_valid), 3, 1.5, exclude_self), want)
    assert s.last == ("kdtree" if backend == "screen" else backend)  # no layout: the sensor moved


def test_neighbour_search_options():
    with pytest.raises(ValueError, match=r"^nn_backend must be 'auto', 'kdtree', 'grid' or 'screen', got 'ball'$"):
        NeighbourSearch("ball")
    s = NeighbourSearch()
    assert (s.backend, s.timed, s.chosen, s.last) == ("auto", 3, {}, None)
    assert s.seconds == {"kdtree": [], "grid": [], "screen": []} and s.BACKENDS == ("kdtree", "grid", "screen")
    assert s.candidates(None) == ("kdtree", "grid") and s.candidates(ScreenLayout(1, 1, 1)) == ("kdtree", "grid", "screen")
    for b in s.BACKENDS:
        assert NeighbourSearch(b, timed=5).backend == b and NeighbourSearch(b, timed=5).timed == 5


def test_auto_times_each_back_end_then_keeps_the_lowest_median():
    n = W * H * SPP
    P, Q = _screen_points(9), _screen_points(10)
    ones = mi.Bool(np.ones(n, bool))
    want = brute(P, Q, 3, 1.5)
    layout = ScreenLayout(W, H, SPP, 3)
    s = NeighbourSearch("auto", timed=2)
    order = []
    t0 = time.perf_counter()
    for call in range(9):  # one untimed call, then 2 timed calls per back-end
        check(s(_pts(P), ones, _pts(Q), ones, 3, 1.5, layout=layout), want)
        order.append(s.last)
        assert [len(s.seconds[b]) for b in s.BACKENDS] == [max(0, (call - i) // 3) for i in range(3)]
        assert (True in s.chosen) == (call == 8) and False not in s.chosen
    assert order == ["kdtree", "grid", "screen"] * 3
    assert all(0 < t < time.perf_counter() - t0 for v in s.seconds.values() for t in v)
    assert s.chosen[True] == min(s.BACKENDS, key=lambda b: float(np.median(s.seconds[b])))
    before = {b: list(v) for b, v in s.seconds.items()}
    s.chosen[True] = "grid"
    check(s(_pts(P), ones, _pts(Q), ones, 3, 1.5, layout=layout), want)
    assert s.last == "grid" and s.seconds == before  # chosen: no more timing
    # without a layout: kd-tree and grid already have their timed calls; one more, then the choice
    check(s(_pts(P), ones, _pts(Q), ones, 3, 1.5), want)
    assert s.last == "kdtree" and len(s.seconds["kdtree"]) == 3 and s.chosen[False] in ("kdtree", "grid")
    assert s.chosen[True] == "grid"


def test_auto_choice_uses_the_median():
    n = W * H * SPP
    P = _screen_points(11)
    ones = mi.Bool(np.ones(n, bool))
    s = NeighbourSearch("auto", timed=3)
    s._untimed = {"kdtree", "grid"}
    s.seconds.update(kdtree=[1.0, 1.0, 1.0], grid=[0.5, 0.5, 100.0])  # grid: lower median, higher mean
    s(_pts(P), ones, _pts(P), ones, 3, 1.5)
    assert s.chosen == {False: "grid"} and s.last == "kdtree" and s.seconds["kdtree"][:3] == [1.0] * 3
    s = NeighbourSearch("auto", timed=3)
    s._untimed = {"kdtree"}
    s.seconds.update(kdtree=[0.1, 0.1, 0.1], grid=[9.0, 9.0, 9.0])
    s(_pts(P), ones, _pts(P), ones, 3, 1.5)  # grid's first call is untimed, however many times it holds
    assert s.last == "grid" and s.seconds["grid"] == [9.0] * 3 and s.chosen == {False: "kdtree"}


# ------------------------------------------------------------------------------ watches
def test_fingerprint_values(monkeypatch):
    assert _fingerprint(3) == (3.0,) and type(_fingerprint(3)[0]) is float and _fingerprint(2.5) == (2.5,)
    m = np.arange(16, dtype=np.float64).reshape(4, 4)
    assert _fingerprint(mi.ScalarTransform4f(m.tolist())) == tuple(m.ravel())
    assert _fingerprint(mi.Transform4f(m.tolist())) == tuple(m.ravel())
    assert _fingerprint(mi.Float([1.5, 2.0])) == (1.5, 2.0)
    assert _fingerprint(mi.Float(np.arange(16))) == tuple(float(i) for i in range(16))
    big = np.arange(17, dtype=np.float32)
    fp = _fingerprint(mi.Float(big))
    assert fp == (17, float(big.sum()), float((big * big).sum())) and type(fp[0]) is int
    rnd = np.random.default_rng(0).random(1000).astype(np.float32)
    want = rnd.astype(np.float64)
    assert _fingerprint(mi.Float(rnd)) == (1000, float(want.sum()), float((want * want).sum()))
    assert _fingerprint(mi.TensorXf(np.ones((2, 2, 3), np.float32))) == (1.0,) * 12
    assert _fingerprint(mi.TensorXf(np.full((1,), 4.0, np.float32))) == (4.0,)

    class NoNumpy:  # width-1 literals are read without numpy
        def __getattr__(self, name):
            raise AssertionError("numpy used")

    monkeypatch.setattr(_scene_watch, "np", NoNumpy())
    assert _fingerprint(mi.Color3f(1, 2, 3)) == (1.0, 2.0, 3.0)
    assert _fingerprint(mi.Point3f(-1, 0.5, 4)) == (-1.0, 0.5, 4.0)
    assert _fingerprint(mi.Float(2.5)) == (2.5,)


def _any_nonzero(value) -> bool:
    return _has_nonzero(_fingerprint(value))  # as the emitter watch reads a light's emission


def test_any_nonzero():
    zeros = np.zeros(40, np.float32)
    assert not _any_nonzero(mi.Float(zeros))
    for i, v in ((0, 1.0), (39, -2.0)):
        one = zeros.copy()
        one[i] = v
        assert _any_nonzero(mi.Float(one))
    pm = zeros.copy()
    pm[3], pm[4] = 1.0, -1.0  # sum 0, sum of squares 2
    assert _any_nonzero(mi.Float(pm))
    assert not _any_nonzero(mi.Color3f(0.0)) and not _any_nonzero(0.0) and _any_nonzero(2)
    for c in ((1, 0, 0), (0, 1, 0), (0, 0, 1)):
        assert _any_nonzero(mi.Color3f(*c))
    assert _any_nonzero(mi.Float([0, 0, 0, 5.0]))


def test_as_tuples():
    assert as_tuples([[1, [2, 3]], (4,), []]) == ((1, (2, 3)), (4,), ())
    assert as_tuples(5) == 5 and as_tuples("ab") == "ab" and as_tuples(None) is None


@pytest.fixture(scope="module")
def oxalis():
    return torchir.Scene.builtin("oxalis_lite", resolution=8, texture=2, dim_lights=2, hidden_lights=1)


@pytest.fixture(scope="module")
def cbox():
    return torchir.Scene.builtin("cbox", resolution=8, max_depth=2)


def _after(scene, watch, key, value):
    params = scene.params
    old = type(params[key])(params[key])  # a copy: the parameter object is updated in place
    params[key] = value
    params.update()
    state = watch(scene.mi_scene)
    params[key] = old
    params.update()
    return state


SPOT = "spot_left.intensity.value"


def test_emitter_watch_point_and_spot_lights(oxalis):
    watch = EmitterWatch()
    base = watch(oxalis.mi_scene)
    assert base[0] == (True,) * 5 and len(base[1]) == 5
    assert base[1][2] == ((float(oxalis.params["dim_00.position"].x[0]), float(oxalis.params["dim_00.position"].y[0]),
                           float(oxalis.params["dim_00.position"].z[0])),)
    assert len(base[1][0]) == 1 and len(base[1][0][0]) == 16  # the spot's to_world
    assert not EmitterWatch.same_support(None, base) and EmitterWatch.same_support(base, base)
    off = _after(oxalis, watch, SPOT, mi.Color3f(0.0))
    assert off[0] == (False, True, True, True, True) and off[1] == base[1]
    assert EmitterWatch.same_support(base, off) and not EmitterWatch.same_support(off, base)
    assert _after(oxalis, watch, SPOT, mi.Color3f(0.0, 0.0, 1.0))[0] == base[0]
    assert _after(oxalis, watch, "dim_01.intensity.value", mi.Color3f(0.0))[0] == (True, True, True, False, True)
    brighter = _after(oxalis, watch, SPOT, mi.Color3f(400.0))
    assert brighter == base and EmitterWatch.same_support(base, brighter)
    moved = _after(oxalis, watch, "dim_00.position", mi.Point3f(0.1, 0.2, 2.0))
    assert moved[1][2] == ((float(np.float32(0.1)), float(np.float32(0.2)), 2.0),)
    assert moved[0] == base[0] and not EmitterWatch.same_support(base, moved)
    turned = _after(oxalis, watch, "spot_left.to_world", mi.ScalarTransform4f().translate([0.0, 0.0, 1.0]))
    assert turned[1][0] != base[1][0] and turned[1][1:] == base[1][1:] and not EmitterWatch.same_support(base, turned)
    assert watch(oxalis.mi_scene) == base
    _no_traverse_on_the_bound_scene(watch, oxalis)


def _no_traverse_on_the_bound_scene(watch, scene):
    state = watch(scene.mi_scene)
    assert watch._scene is scene.mi_scene  # the scene itself, held: a freed one's address is reused
    traverse = mi.traverse
    try:
        mi.traverse = None  # the bound parameters are reused: a call costs host reads only
        assert watch(scene.mi_scene) == state
    finally:
        mi.traverse = traverse


def test_emitter_watch_same_support_rules():
    base = ((True, False), ((1.0,), (2.0,)))
    assert EmitterWatch.same_support(base, ((True, False), ((1.0,), (2.0,))))
    assert EmitterWatch.same_support(base, ((False, False), ((1.0,), (2.0,))))  # one went off
    assert not EmitterWatch.same_support(base, ((True, True), ((1.0,), (2.0,))))  # one came on
    assert not EmitterWatch.same_support(base, ((True, False), ((1.0,), (3.0,))))  # one moved
    assert not EmitterWatch.same_support(base, ((True,), ((1.0,),)))  # a light fewer
    assert not EmitterWatch.same_support(((True,), ((1.0,),)), ((True, True), ((1.0,), (1.0,))))


def test_emitter_watch_area_light_and_rebinding(oxalis, cbox):
    watch = EmitterWatch()
    base = watch(cbox.mi_scene)
    assert base[0] == (True,) and len(base[1][0]) == 1 and len(base[1][0][0]) == 16
    off = _after(cbox, watch, "light.emitter.radiance.value", mi.Color3f(0.0))
    assert off == ((False,), base[1]) and not EmitterWatch.same_support(off, base)
    moved = _after(cbox, watch, "light.to_world", mi.ScalarTransform4f().translate([0.0, 0.9, 0.0]))
    assert moved[0] == base[0] and moved[1] != base[1]
    assert len(watch(oxalis.mi_scene)[0]) == 5 and watch(cbox.mi_scene) == base  # another scene: rebinds


def test_emitter_watch_mesh_directional_and_environment_lights(tmp_path):
    obj = tmp_path / "lamp.obj"
    obj.write_text("v -1 -1 2\nv 1 -1 2\nv 1 1 2\nv -1 1 2\nf 1 2 3\nf 1 3 4\n")
    scene = torchir.Scene.from_dict({
        "type": "scene", "integrator": {"type": "direct"},
        "sensor": torchir.scenes._common.perspective([0, 0, 3.0], [0, 0, 0], [0, 1, 0], 30.0, 8, 8),
        "lamp": {"type": "obj", "filename": str(obj), "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 1.0}}},
        "sun": {"type": "directional", "direction": [0, 0, -1], "irradiance": {"type": "rgb", "value": 1.0}},
        "env": {"type": "envmap", "bitmap": mi.Bitmap(np.ones((4, 8, 3), np.float32)), "scale": 0.5},
    })
    watch = EmitterWatch()
    base = watch(scene.mi_scene)
    assert watch._keys == [(["lamp.emitter.radiance.value"], ["lamp.vertex_positions"]),
                           (["sun.irradiance.value"], ["sun.to_world"]), (["env.scale", "env.data"], ["env.to_world"])]
    assert base[0] == (True, True, True) and base[1][0] == ((-1.0, -1.0, 2.0, 1.0, -1.0, 2.0, 1.0, 1.0, 2.0, -1.0, 1.0, 2.0),)
    assert _after(scene, watch, "sun.irradiance.value", mi.Color3f(0.0))[0] == (True, False, True)
    assert _after(scene, watch, "env.scale", mi.Float(0.0))[0] == (True, True, False)
    assert _after(scene, watch, "env.data", mi.TensorXf(np.zeros((4, 9, 3), np.float32)))[0] == (True, True, False)
    moved = _after(scene, watch, "lamp.vertex_positions", mi.Float(np.arange(12, dtype=np.float32)))
    assert moved[1][0] == (tuple(float(i) for i in range(12)),) and moved[1][1:] == base[1][1:]


def test_geometry_watch(oxalis):
    # A private scene: re-setting the box's vertices rebuilds its acceleration structure, which moved
    # later renders of the shared session scene by ~1e-8 (and a path's fate with it).
    cbox = torchir.Scene.builtin("cbox", resolution=RES)
    watch = GeometryWatch()
    base = watch(cbox.mi_scene)
    assert watch._keys == ["light.to_world", "floor.to_world", "ceiling.to_world", "back.to_world", "green-wall.to_world",
                           "red-wall.to_world", "small-box.vertex_positions", "large-box.vertex_positions"]
    assert isinstance(base[-1], int) and base[-1] == cbox.params["large-box.vertex_positions"].index
    assert len(base[0]) == 16 and watch(cbox.mi_scene) == base
    red = _after(cbox, watch, "red.reflectance.value", mi.Color3f(0.1))
    assert red == base  # not geometry
    sensor = _after(cbox, watch, "sensor.to_world", mi.ScalarTransform4f().translate([0.0, 0.0, 1.0]))
    assert sensor == base  # the sensor is not a shape
    light = _after(cbox, watch, "light.to_world", mi.ScalarTransform4f().translate([0.0, 0.9, 0.0]))
    assert light[0] != base[0] and light[1:] == base[1:]
    v = cbox.params["small-box.vertex_positions"]
    cbox.params["small-box.vertex_positions"] = mi.Float(np.asarray(v))  # the same values, a new variable
    cbox.params.update()
    now = watch(cbox.mi_scene)
    assert now[6] != base[6] and now[:6] == base[:6] and now[7] == base[7]
    assert watch(cbox.mi_scene) == now
    _no_traverse_on_the_bound_scene(watch, cbox)
    ox = watch(oxalis.mi_scene)  # another scene: rebinds (shapes' transforms only)
    assert watch._keys == ["canvas.to_world", "leaf.to_world", "wall.to_world"] and len(ox) == 3
    assert _after(oxalis, watch, "spot_left.to_world", mi.ScalarTransform4f().translate([0.0, 0.0, 1.0])) == ox


def test_neighbour_search_passes_windows_and_exclude_self_on_every_path():
    n = W * H * SPP
    P = _screen_points(12)
    rng = np.random.default_rng(13)
    valid = rng.random(n) < 0.8
    per_query = rng.integers(0, 3, n).astype(np.uint32)
    layout = ScreenLayout(W, H, SPP, 2)
    want = brute(P, P, 3, 10.0, True, valid, valid, allowed=_window_rule(np.minimum(per_query, 2)))
    args = (_pts(P), mi.Bool(valid), _pts(P), mi.Bool(valid), 3, 10.0, True, layout, mi.UInt32(per_query))
    check(NeighbourSearch("screen")(*args), want, False)
    s = NeighbourSearch("auto", timed=1)
    s._untimed, s.seconds["kdtree"], s.seconds["grid"] = {"kdtree", "grid", "screen"}, [9.0], [9.0]
    check(s(*args), want, False)  # timed: screen
    assert s.last == "screen" and s.chosen == {True: "screen"}
    check(s(*args), want, False)  # chosen
    want_world = brute(P, P, 3, 1.5, True, valid, valid)
    check(s(*args[:5], 1.5, True, layout), brute(P, P, 3, 1.5, True, valid, valid, allowed=_window_rule(np.full(n, 2))), False)
    s.chosen[True] = "kdtree"
    check(s(*args[:5], 1.5, True, layout), want_world)


def test_value_reader_reads_again_only_new_variables(monkeypatch):
    reads = []
    fingerprint = _scene_watch._fingerprint
    monkeypatch.setattr(_scene_watch, "_fingerprint", lambda v: reads.append(1) or fingerprint(v))
    read = _scene_watch.ValueReader()
    m = np.arange(16, dtype=np.float64).reshape(4, 4)
    pose = mi.Transform4f(m.tolist())
    assert read("pose", pose) == tuple(m.ravel()) and read("pose", pose) == tuple(m.ravel()) and len(reads) == 1
    assert read("pose", mi.Transform4f(m.tolist())) == tuple(m.ravel())  # the same values (Dr.Jit may share their variables)
    moved = m.copy()
    moved[0, 3] = 7.0
    before = len(reads)
    assert read("pose", mi.Transform4f(moved.tolist())) == tuple(moved.ravel()) and len(reads) == before + 1
    assert read("other", mi.Transform4f(moved.tolist())) == tuple(moved.ravel())  # keys are separate
    assert read("count", 3) == (3.0,) and read("count", 4) == (4.0,)  # Python numbers: always read


def test_value_reader_is_not_fooled_by_freed_variables():
    # a value freed and a new one made could reuse its variable indices; the reader keeps the
    # last value it read alive, so a new value is always read
    read = _scene_watch.ValueReader()
    for i in range(50):
        value = mi.Float(float(i), float(i) + 0.5)
        assert read("k", value) == (float(i), float(i) + 0.5)
        del value  # no cycle holds it: its variables are freed here (a full gc.collect() each step cost 0.3 s)
        gc.collect(0)
