"""Exact k-nearest-neighbour search within a radius, for ReSTIR reservoir reuse (Wang et al. 2023).

Two back-ends that return the *same* neighbours (ascending distance, ties by index):

- ``kdtree``: scipy's ``cKDTree`` on the host (LLVM arrays live in host memory, so the copy
  is cheap); no JIT compilation.
- ``grid``: a uniform grid in Dr.Jit (cell >= radius, counting sort with ``scatter_inc`` +
  ``prefix_sum``, then each query scans its 27 cells in one ``dr.while_loop`` keeping a sorted
  top-k). Stays on the device (the CUDA back-end).
- ``screen`` (:func:`knn_screen`): for a sensor that has not moved, the points are the previous
  step's samples laid out like the queries (pixel-major, ``spp`` lanes per pixel), so the
  candidates of a query are the samples of the ``(2 window + 1)^2`` pixels around its own: no
  build, no host copy, one kernel. Exact (the same neighbours as the others) wherever every
  point within ``radius`` of a query projects within ``window`` pixels of it.

Both return ``(index, ok)``: lists of ``k`` ``UInt32``/``Bool`` arrays of the query width;
``index[i][q]`` is the ``i``-th nearest point of query ``q`` (only meaningful where ``ok``).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from ..backend import jit_array
from .restir_options import NN_BACKENDS

__all__ = ["knn", "knn_kdtree", "knn_grid", "knn_screen", "have_scipy", "NeighbourSearch", "ScreenLayout"]

_MAX_CELLS = 1 << 22  # grid memory bound: coarser cells (still exact) beyond this


def have_scipy() -> bool:
    try:
        import scipy.spatial  # noqa: F401
    except ImportError:
        return False
    return True


def _to_numpy(p: mi.Point3f) -> np.ndarray:
    return np.stack([np.asarray(p.x), np.asarray(p.y), np.asarray(p.z)], axis=1).astype(np.float64)


def _columns(idx: np.ndarray, ok: np.ndarray, k: int) -> tuple[list[mi.UInt32], list[mi.Bool]]:
    return (
        [jit_array(mi.UInt32, idx[:, i].astype(np.uint32)) for i in range(k)],
        [jit_array(mi.Bool, ok[:, i]) for i in range(k)],
    )


def knn_kdtree(points: mi.Point3f, queries: mi.Point3f, k: int, radius: float, exclude_self: bool = False):
    """k nearest ``points`` of each query, strictly closer than ``radius`` (scipy cKDTree).

    ``exclude_self``: queries are the points themselves; drop each query's own index.
    """
    from scipy.spatial import cKDTree

    pts, qs = _to_numpy(points), _to_numpy(queries)
    n, nq = len(pts), len(qs)
    if n == 0 or nq == 0:
        return _columns(np.zeros((nq, k), np.int64), np.zeros((nq, k), bool), k)
    kk = k + 1 if exclude_self else k
    tree, m = cKDTree(pts), kk + 1
    while True:  # cKDTree orders equal distances arbitrarily: take every tie at the kk-th distance
        dist, idx = tree.query(qs, k=m, distance_upper_bound=radius, workers=-1)
        dist, idx = np.asarray(dist).reshape(nq, m), np.asarray(idx).reshape(nq, m)
        if m >= n or not np.any(np.isfinite(dist[:, -1]) & (dist[:, -1] == dist[:, kk - 1])):
            break
        m = min(2 * m, n)
    order = np.lexsort((idx, dist), axis=1)  # ascending distance, ties by index
    idx = np.take_along_axis(idx, order, 1)[:, :kk]
    ok = idx < n
    if exclude_self:
        own = idx == np.arange(nq)[:, None]
        keep = ok & ~own
        # stable compaction of the kept entries to the left, k columns
        order = np.argsort(~keep, axis=1, kind="stable")
        idx = np.take_along_axis(idx, order, 1)[:, :k]
        ok = np.take_along_axis(keep, order, 1)[:, :k]
    idx = np.where(ok, idx, 0)
    return _columns(idx, ok, k)


def _grid_build(points: mi.Point3f, radius: float):
    lo = [float(dr.min(c)[0]) for c in (points.x, points.y, points.z)]
    hi = [float(dr.max(c)[0]) for c in (points.x, points.y, points.z)]
    cell = max(radius, 1e-12)
    while True:
        dims = [max(1, int(math.floor((h - l) / cell)) + 1) for l, h in zip(lo, hi)]
        if math.prod(dims) <= _MAX_CELLS:
            break
        cell *= 2.0
    return lo, dims, cell


def _cell_coords(p: mi.Point3f, lo, dims, cell) -> tuple[mi.Int32, mi.Int32, mi.Int32]:
    # lo, dims, cell are opaque Dr.Jit scalars: one compiled kernel for every grid
    out = []
    for c, l, d in zip((p.x, p.y, p.z), lo, dims):
        i = mi.Int32(dr.floor((c - l) / cell))
        out.append(dr.clip(i, 0, d - 1))
    return tuple(out)


def knn_grid(points: mi.Point3f, queries: mi.Point3f, k: int, radius: float, exclude_self: bool = False):
    """Same contract as :func:`knn_kdtree`, computed with a uniform grid in Dr.Jit."""
    n, nq = dr.width(points), dr.width(queries)
    if n == 0 or nq == 0:
        return [dr.zeros(mi.UInt32, nq) for _ in range(k)], [dr.zeros(mi.Bool, nq) for _ in range(k)]
    lo, dims_s, cell_s = _grid_build(points, radius)
    lo = [dr.opaque(mi.Float, v) for v in lo]
    dims = [dr.opaque(mi.Int32, v) for v in dims_s]
    cell = dr.opaque(mi.Float, cell_s)
    ix, iy, iz = _cell_coords(points, lo, dims, cell)
    buckets = _counting_sort(mi.UInt32(ix + dims[0] * (iy + dims[1] * iz)), math.prod(dims_s))
    qx, qy, qz = _cell_coords(queries, lo, dims, cell)
    qself = dr.arange(mi.UInt32, nq)

    def cell_at(c):  # the c-th of the query's 27 cells
        cx, cy, cz = qx + mi.Int32(c % 3) - 1, qy + mi.Int32((c // 3) % 3) - 1, qz + mi.Int32(c // 9) - 1
        inside = (cx >= 0) & (cx < dims[0]) & (cy >= 0) & (cy < dims[1]) & (cz >= 0) & (cz < dims[2])
        return inside, mi.UInt32(cx + dims[0] * (cy + dims[1] * cz))

    return _scan_buckets(buckets, points, queries, k, radius, 27, cell_at, (lambda j: j != qself) if exclude_self else None)


def _counting_sort(key: mi.UInt32, keys: int, active: mi.Bool | bool = True) -> tuple[mi.UInt32, mi.UInt32, mi.UInt32]:
    """Points sorted by ``key`` in ``[0, keys)`` (the ``active`` ones): ``(order, starts,
    counts)``, key ``i``'s points being ``order[starts[i] : starts[i] + counts[i]]``."""
    n = dr.width(key)
    counts = dr.zeros(mi.UInt32, keys)
    slot = dr.scatter_inc(counts, key, active)
    dr.eval(slot, counts)
    starts = dr.prefix_sum(counts)  # exclusive
    order = dr.zeros(mi.UInt32, max(n, 1))
    dr.scatter(order, dr.arange(mi.UInt32, n), dr.gather(mi.UInt32, starts, key, active) + slot, active)
    dr.eval(order, starts)
    return order, starts, counts


def _scan_buckets(buckets: tuple, points: mi.Point3f, queries: mi.Point3f, k: int, radius: float, cells,
                  cell_at, accept_also=None):
    """The k nearest of ``points`` closer than ``radius`` to each query among the buckets
    (:func:`_counting_sort`) of its ``cells`` cells, ``cell_at(c) -> (inside, bucket)`` naming
    the c-th; one ``dr.while_loop`` scans a bucket's points, then loads the next bucket.
    ``accept_also(j)``: a further test of point ``j``. Returns :func:`_top_k_scan`'s columns."""
    order, starts, counts = buckets
    nq = dr.width(queries)
    r2 = dr.opaque(mi.Float, radius * radius)

    def cond(c, pos, end, *best):
        return (pos < end) | (c < cells)

    def body(c, pos, end, *best):
        bd, bi = list(best[:k]), list(best[k:])
        in_range = pos < end
        j = dr.gather(mi.UInt32, order, pos, in_range)
        pj = dr.gather(mi.Point3f, points, j, in_range)
        d2 = dr.squared_norm(pj - queries)
        accept = in_range & (d2 < r2)
        if accept_also is not None:
            accept &= accept_also(j)
        _insert_top_k(bd, bi, accept, mi.Float(d2), mi.UInt32(j))
        load = ~in_range  # the next cell once the current bucket is exhausted
        inside, bucket = cell_at(c)
        s0 = dr.gather(mi.UInt32, starts, bucket, load & inside)
        cnt = dr.gather(mi.UInt32, counts, bucket, load & inside)
        pos = dr.select(in_range, pos + 1, dr.select(inside, s0, 0))
        end = dr.select(in_range, end, dr.select(inside, s0 + cnt, 0))
        return (dr.select(load, c + 1, c), pos, end, *bd, *bi)

    head = (dr.zeros(mi.UInt32, nq), dr.zeros(mi.UInt32, nq), dr.zeros(mi.UInt32, nq))
    return _top_k_scan(head, k, nq, r2, cond, body)


@dataclass(frozen=True)
class ScreenLayout:
    """Lane layout shared by the points and the queries of :func:`knn_screen`: lane
    ``(y * width + x) * spp + s`` is sample ``s`` of pixel ``(x, y)``. ``chains``: sample ``s``
    of a pixel searches only samples ``s`` of the pixels around it (``spp`` interleaved chains
    of one sample per pixel)."""

    width: int
    height: int
    spp: int
    window: int = 2  # half-width in pixels of the searched square
    chains: bool = False

    @property
    def searches_chains(self) -> bool:
        """Whether a query searches only its own chain (``chains`` with several samples a pixel)."""
        return self.chains and self.spp > 1


def _insert_top_k(bd: list, bi: list, accept, dc, ic) -> None:
    """Insert ``(dc, ic)`` where ``accept`` into the per-lane sorted top-k ``(bd, bi)``,
    ordered by (distance, index)."""
    for t in range(len(bd)):
        less = accept & ((dc < bd[t]) | ((dc == bd[t]) & (ic < bi[t])))
        nd, ni = dr.select(less, dc, bd[t]), dr.select(less, ic, bi[t])
        dc, ic = dr.select(less, bd[t], dc), dr.select(less, bi[t], ic)
        bd[t], bi[t] = nd, ni


def _top_k_scan(head: tuple, k: int, n: int, r2, cond, body):
    """Run a neighbour scan: ``dr.while_loop`` over the scan's own state ``head`` followed by an
    empty sorted top-k (``k`` distances at +inf, ``k`` indices at 0xFFFFFFFF) that ``body``
    fills with :func:`_insert_top_k`. Returns ``k`` ``(index, ok)`` columns of width ``n``;
    ``ok`` where the entry is closer than the radius (``r2`` its square), index 0 elsewhere."""
    empty = mi.UInt32(0xFFFFFFFF)
    state = head + tuple(dr.full(mi.Float, dr.inf, n) for _ in range(k))
    state += tuple(empty + dr.zeros(mi.UInt32, n) for _ in range(k))
    out = dr.while_loop(state, cond, body)
    bd, bi = out[len(head) : len(head) + k], out[len(head) + k :]
    ok = [d < r2 for d in bd]
    idx = [dr.select(o, i, 0) for o, i in zip(ok, bi)]
    dr.eval(idx, ok)
    return idx, ok


def knn_screen(points: mi.Point3f, valid: mi.Bool, queries: mi.Point3f, layout: ScreenLayout, k: int,
               radius: float, exclude_self: bool = False, windows: mi.UInt32 | None = None):
    """k nearest valid ``points`` strictly closer than ``radius``, among the samples of the
    pixels within ``layout.window`` of each query's pixel (or within ``windows``, one
    half-width per query, at most ``layout.window``). ``points`` and ``queries`` both have
    width ``width * height * spp`` in :class:`ScreenLayout` order; returns full-width columns
    like :func:`knn_kdtree` (``index`` into ``points``).

    A sample ``w + 1`` pixels away lies more than ``w`` pixel footprints away, so a window of
    ``ceil(radius / footprint)`` around a query finds every point within the radius (with
    ``layout.chains``: every point of the query's own chain)."""
    w, h, spp, win = layout.width, layout.height, layout.spp, layout.window
    n = w * h * spp
    if dr.width(points) != n or dr.width(queries) != n:
        raise ValueError(f"knn_screen: points and queries must have {n} lanes ({w}x{h}x{spp}), got "
                         f"{dr.width(points)} and {dr.width(queries)}")
    lane = dr.arange(mi.UInt32, n)
    if windows is None:
        win_q = dr.full(mi.UInt32, win, n)
    else:
        win_q = dr.minimum(mi.UInt32(windows), win)
    side_q = 2 * win_q + 1
    chains = layout.searches_chains
    per_pixel = 1 if chains else spp  # samples searched in each pixel of the window
    count_q = side_q * side_q * per_pixel
    pix = lane // spp
    own = lane - pix * spp  # the query's sample index in its pixel
    qx, qy = mi.Int32(pix % w), mi.Int32(pix // w)
    r2 = dr.opaque(mi.Float, radius * radius)
    w_o, h_o, spp_o = dr.opaque(mi.Int32, w), dr.opaque(mi.Int32, h), dr.opaque(mi.UInt32, spp)

    def cond(c, *best):
        return c < count_q

    def body(c, *best):
        bd, bi = list(best[:k]), list(best[k:])
        if chains:
            cell, s = c, own
        else:
            cell = c // spp_o
            s = c - cell * spp_o
        cx = qx + mi.Int32(cell % side_q) - mi.Int32(win_q)
        cy = qy + mi.Int32(cell // side_q) - mi.Int32(win_q)
        inside = (cx >= 0) & (cx < w_o) & (cy >= 0) & (cy < h_o)
        j = (mi.UInt32(cy * w_o + cx)) * spp_o + s
        accept = inside & dr.gather(mi.Bool, valid, j, inside)
        pj = dr.gather(mi.Point3f, points, j, accept)
        d2 = dr.squared_norm(pj - queries)
        accept &= d2 < r2
        if exclude_self:
            accept &= j != lane
        _insert_top_k(bd, bi, accept, mi.Float(d2), mi.UInt32(j))
        return (c + 1, *bd, *bi)

    return _top_k_scan((dr.zeros(mi.UInt32, n),), k, n, r2, cond, body)


def bucket_by_pixel(valid: mi.Bool, pixel: mi.UInt32, pixels: int) -> tuple[mi.UInt32, mi.UInt32, mi.UInt32]:
    """The ``valid`` points sorted by ``pixel`` (a counting sort): ``(order, starts, counts)``,
    the points of pixel ``i`` being ``order[starts[i] : starts[i] + counts[i]]``. Run it traced:
    ``scatter_inc`` inside a frozen function corrupted memory on replay (Dr.Jit 1.5)."""
    return _counting_sort(pixel, pixels, valid)


def knn_in_buckets(points: mi.Point3f, buckets: tuple, queries: mi.Point3f, width: int, height: int, spp: int,
                   k: int, radius: float, windows: mi.UInt32):
    """k nearest ``points`` strictly closer than ``radius`` among those bucketed
    (:func:`bucket_by_pixel`) into the pixels within ``windows`` (one half-width per query) of
    each query's pixel; the queries are ``width * height * spp`` lanes in :class:`ScreenLayout`
    order. Pure Dr.Jit, no host copies (it can be frozen). Returns ``k`` ``(index, ok)`` columns
    like :func:`knn_kdtree` (``index`` into ``points``)."""
    nq = width * height * spp
    if dr.width(queries) != nq:
        raise ValueError(f"knn_in_buckets: queries must have {nq} lanes ({width}x{height}x{spp}), got {dr.width(queries)}")
    q_pix = dr.arange(mi.UInt32, nq) // dr.opaque(mi.UInt32, spp)
    w_o, h_o = dr.opaque(mi.Int32, width), dr.opaque(mi.Int32, height)
    qx, qy = mi.Int32(q_pix) % w_o, mi.Int32(q_pix) // w_o
    win_q = mi.UInt32(windows)
    side_q = 2 * win_q + 1

    def cell_at(c):  # the c-th pixel of the query's window
        cx = qx + mi.Int32(c % side_q) - mi.Int32(win_q)
        cy = qy + mi.Int32(c // side_q) - mi.Int32(win_q)
        return (cx >= 0) & (cx < w_o) & (cy >= 0) & (cy < h_o), mi.UInt32(cy * w_o + cx)

    return _scan_buckets(buckets, points, queries, k, radius, side_q * side_q, cell_at)


def knn_reprojected(points: mi.Point3f, valid: mi.Bool, pixel: mi.UInt32, queries: mi.Point3f, width: int,
                    height: int, spp: int, k: int, radius: float, windows: mi.UInt32):
    """:func:`knn_in_buckets` of the ``valid`` points bucketed by their ``pixel`` in the
    queries' film (any number of points, from any views)."""
    buckets = bucket_by_pixel(valid, pixel, width * height)
    return knn_in_buckets(points, buckets, queries, width, height, spp, k, radius, windows)


def _default_backend() -> str:
    return "kdtree" if (have_scipy() and not mi.variant().startswith("cuda")) else "grid"


def knn(points: mi.Point3f, queries: mi.Point3f, k: int, radius: float, backend: str = "auto", exclude_self: bool = False):
    """Dispatch to ``kdtree`` (``auto`` on CPU with scipy) or ``grid``."""
    if backend == "auto":
        backend = _default_backend()
    if backend == "kdtree":
        return knn_kdtree(points, queries, k, radius, exclude_self)
    if backend == "grid":
        return knn_grid(points, queries, k, radius, exclude_self)
    raise ValueError(f"nn_backend must be 'auto', 'kdtree' or 'grid', got {backend!r}")


class NeighbourSearch:
    """The neighbour search of ReSTIR reuse, with its back-end fixed or chosen by measurement.

    Called with full-width point and query arrays and their validity masks, it returns ``k``
    full-width ``(index, ok)`` columns (``ok`` is False for invalid queries). ``kdtree`` and
    ``grid`` return the same neighbours, and so does ``screen`` where its window covers the
    radius; it is available only when the caller passes the :class:`ScreenLayout` shared by
    points and queries (a sensor that has not moved).

    ``auto`` times the available back-ends on the caller's own queries: after one untimed call
    each (compilation), ``timed`` calls each in turn, then keeps the one with the lower median
    (``chosen``, separately for calls with and without a layout), since their speeds differ
    with the queries (measurements: docs/restir-measurements.md, "Neighbour search"). Without
    scipy, or on CUDA, the kd-tree is not a candidate.
    """

    BACKENDS = tuple(b for b in NN_BACKENDS if b != "auto")

    def __init__(self, backend: str = "auto", timed: int = 3) -> None:
        if backend not in ("auto", *self.BACKENDS):
            raise ValueError(f"nn_backend must be 'auto', 'kdtree', 'grid' or 'screen', got {backend!r}")
        self.backend, self.timed = backend, timed
        self.chosen: dict[bool, str] = {}  # has a layout -> back-end kept by 'auto'
        self.seconds: dict[str, list[float]] = {b: [] for b in self.BACKENDS}
        self._untimed: set[str] = set()
        self.last: str | None = None  # the back-end of the last call

    def candidates(self, layout: ScreenLayout | None) -> tuple[str, ...]:
        if layout is not None and layout.searches_chains:
            return ("screen",)  # only it searches within a chain
        out = ("kdtree", "grid") if _default_backend() == "kdtree" else ("grid",)
        return out + (("screen",) if layout is not None else ())

    def __call__(self, points: mi.Point3f, valid: mi.Bool, queries: mi.Point3f, q_valid: mi.Bool, k: int,
                 radius: float, exclude_self: bool = False, layout: ScreenLayout | None = None,
                 windows: mi.UInt32 | None = None):
        if self.backend != "auto":
            backend = self.backend
            if backend == "screen" and layout is None:
                backend = _default_backend()  # the sensor moved: no shared layout this step
            return self._search(backend, points, valid, queries, q_valid, k, radius, exclude_self, layout, windows)
        key = layout is not None
        if key in self.chosen:
            return self._search(self.chosen[key], points, valid, queries, q_valid, k, radius, exclude_self, layout, windows)
        options = self.candidates(layout)
        backend = min(options, key=lambda b: (b in self._untimed, len(self.seconds[b])))
        dr.eval(points, valid, queries, q_valid)
        dr.sync_thread()
        start = time.perf_counter()
        out = self._search(backend, points, valid, queries, q_valid, k, radius, exclude_self, layout, windows)
        dr.eval(out)
        dr.sync_thread()
        if backend in self._untimed:
            self.seconds[backend].append(time.perf_counter() - start)
        self._untimed.add(backend)
        if all(len(self.seconds[b]) >= self.timed for b in options):
            self.chosen[key] = min(options, key=lambda b: float(np.median(self.seconds[b])))
        return out

    def _search(self, backend, points, valid, queries, q_valid, k, radius, exclude_self, layout, windows=None):
        self.last = backend
        if backend == "screen":
            idx, ok = knn_screen(points, valid, queries, layout, k, radius, exclude_self, windows)
            ok = [o & q_valid for o in ok]
            return idx, ok
        n = dr.width(q_valid)
        src_idx = dr.compress(valid)
        q_idx = dr.compress(q_valid)
        pts = dr.gather(mi.Point3f, points, src_idx)
        qs = dr.gather(mi.Point3f, queries, q_idx)
        # exclude_self is only used with points == queries (same step), so compressed indices agree
        idx_c, ok_c = knn(pts, qs, k, radius, backend, exclude_self)
        idx, ok = [], []
        for ic, oc in zip(idx_c, ok_c):
            full_i = dr.zeros(mi.UInt32, n)
            full_ok = dr.zeros(mi.Bool, n)
            dr.scatter(full_i, dr.gather(mi.UInt32, src_idx, ic, oc), q_idx)
            dr.scatter(full_ok, oc, q_idx)
            idx.append(full_i)
            ok.append(full_ok)
        return idx, ok
