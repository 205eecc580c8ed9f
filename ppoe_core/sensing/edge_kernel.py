"""Compiled edge fit of a tag's four outer edges: THE implementation of :func:`ppoe_core.sensing.tags.refine_edges`'s
passes (one call for all passes, no per-edge Python: the node's and ``ppoe evaluate``'s image path).

Along each edge of the quadrilateral, intensity profiles across the edge (bilinear samples of the grey image, step
``step`` px, half width ``min(2 px, window cells)``, at ``n_t`` evenly spaced positions over the middle 70 % of the
edge) give the sub-pixel edge position as the centroid of the dark-to-light gradient; a total-least-squares line
through those points (the minor axis of their scatter) is the edge, and the corners are the intersections of
consecutive edges.  A corner that would move by a cell or more, or a quad with an edge shorter than 4 px or with
fewer than 3 usable profiles on an edge, keeps its input value.  Pixel (u, v) = (column, row) centres, as OpenCV;
outside the image the nearest pixel (OpenCV's ``BORDER_REPLICATE``).
"""

from __future__ import annotations

import math

import numpy as np

from ppoe_core.jit import njit

__all__ = ["edge_fit"]


#: rows of the scratch array of :func:`_edge_line`: per profile (weight, point x, point y), per sample (value,
#: offset s * nx, offset s * ny), per step (the s halfway between two samples)
_WSUM, _X, _Y, _PROF, _SNX, _SNY, _MID = range(7)


@njit(cache=True, inline="always")
def _sample(flat: np.ndarray, h: int, w: int, u: float, v: float) -> float:
    """Bilinear grey value at (u, v) of the (h, w) image ``flat`` (h * w,), the border replicated."""
    u = min(max(u, 0.0), w - 1.0)
    v = min(max(v, 0.0), h - 1.0)
    u0 = min(int(u), w - 2) if w > 1 else 0
    v0 = min(int(v), h - 2) if h > 1 else 0
    fu = u - u0
    fv = v - v0
    u1 = min(u0 + 1, w - 1)
    v1 = min(v0 + 1, h - 1)
    top = (1.0 - fu) * flat[v0 * w + u0] + fu * flat[v0 * w + u1]
    bottom = (1.0 - fu) * flat[v1 * w + u0] + fu * flat[v1 * w + u1]
    return (1.0 - fv) * top + fv * bottom


@njit(cache=True, inline="always")
def _samples_inside(flat: np.ndarray, w: np.uint64, px: float, py: float, n_s: int, work: np.ndarray) -> None:
    """``work[_PROF, j]`` = :func:`_sample` at (u, v) = (px + work[_SNX, j], py + work[_SNY, j]), j < n_s, all at
    0 <= u < w - 1, 0 <= v < h - 1, where its clamps change nothing: the same floats, the four pixels read again
    only when a sample enters another pixel cell (unsigned indices: no negative-index wrap-around)."""
    pu = pv = -1
    p00 = p01 = p10 = p11 = 0.0
    one = np.uint64(1)
    for j in range(n_s):
        u = px + work[_SNX, j]
        v = py + work[_SNY, j]
        u0 = int(u)
        v0 = int(v)
        if u0 != pu or v0 != pv:
            k = np.uint64(v0 * np.int64(w) + u0)
            p00, p01 = np.float64(flat[k]), np.float64(flat[k + one])
            p10, p11 = np.float64(flat[k + w]), np.float64(flat[k + w + one])
            pu, pv = u0, v0
        fu = u - u0
        fv = v - v0
        top = (1.0 - fu) * p00 + fu * p01
        bottom = (1.0 - fu) * p10 + fu * p11
        work[_PROF, j] = (1.0 - fv) * top + fv * bottom


@njit(cache=True, inline="always")
def _inside(h: int, w: int, u: float, v: float) -> bool:
    """True where (u, v) is in the domain of :func:`_samples_inside`."""
    return 0.0 <= u < w - 1.0 and 0.0 <= v < h - 1.0


@njit(cache=True)
def _profiles(flat: np.ndarray, h: int, w: int, ax: float, ay: float, dx: float, dy: float, nx: float, ny: float,
              n_t: int, n_s: int, work: np.ndarray) -> float:
    """The ``n_t`` profiles across the edge from (ax, ay) along (dx, dy), outward normal (nx, ny): at t = 0.15 +
    0.7 i / (n_t - 1), the sum of the dark-to-light steps between consecutive samples at (px + s nx, py + s ny)
    (``work[_SNX]``, ``work[_SNY]``) and their centroid ``off`` in s (``work[_MID]``: halfway between two samples;
    0 without a step) -> ``work[_WSUM, i]`` and the edge point ``work[_X | _Y, i]`` = p + off n; returns the
    largest weight."""
    top = -math.inf
    last = n_s - 1
    wu = np.uint64(w)
    for i in range(n_t):
        t = 0.15 + 0.7 * i / (n_t - 1)
        px, py = ax + t * dx, ay + t * dy
        # u and v are monotonic in j (rounding is monotonic): both end samples inside put every sample inside
        if (_inside(h, w, px + work[_SNX, 0], py + work[_SNY, 0])
                and _inside(h, w, px + work[_SNX, last], py + work[_SNY, last])):
            _samples_inside(flat, wu, px, py, n_s, work)
        else:
            for j in range(n_s):
                work[_PROF, j] = _sample(flat, h, w, px + work[_SNX, j], py + work[_SNY, j])
        wsum = 0.0
        acc = 0.0
        for j in range(last):
            g = work[_PROF, j + 1] - work[_PROF, j]  # dark (inside) -> light (outside)
            # a non-positive step adds 0.0 (or -0.0): the same sums as skipping it, without a branch
            g = g if g > 0.0 else 0.0
            wsum += g
            acc += g * work[_MID, j]
        off = acc / wsum if wsum > 0.0 else 0.0
        work[_WSUM, i] = wsum
        work[_X, i] = px + off * nx
        work[_Y, i] = py + off * ny
        top = max(top, wsum)
    return top


@njit(cache=True)
def _edge_line(flat: np.ndarray, h: int, w: int, ax: float, ay: float, bx: float, by: float, cx: float, cy: float,
               n_cells: int, n_t: int, step: float, window: float, line: np.ndarray, work: np.ndarray) -> bool:
    """The fitted line ``line = (nx, ny, -n.m)`` of the edge from (ax, ay) to (bx, by) (quad centre (cx, cy)) in the
    (h, w) image ``flat`` (h * w,); False when it has fewer than 3 usable profiles.  ``work`` (7, >= max(n_t,
    samples per profile)): scratch."""
    dx, dy = bx - ax, by - ay
    length = math.sqrt(dx * dx + dy * dy)
    ex, ey = dx / length, dy / length
    nx, ny = ey, -ex
    if nx * (0.5 * (ax + bx) - cx) + ny * (0.5 * (ay + by) - cy) < 0:  # outward normal
        nx, ny = -nx, -ny
    half = min(2.0, window * length / n_cells)
    n_s = int(math.floor(2.0 * half / step + 1e-9)) + 1
    if not 2 <= n_s <= work.shape[1]:  # only with a step or window other than edge_fit's scratch was sized for
        return False
    for j in range(n_s):  # the same offsets for every profile of the edge
        s = -half + step * j
        work[_SNX, j] = s * nx
        work[_SNY, j] = s * ny
        work[_MID, j] = -half + step * (j + 0.5)
    top = _profiles(flat, h, w, ax, ay, dx, dy, nx, ny, n_t, n_s, work)
    wsums, xs, ys = work[_WSUM], work[_X], work[_Y]
    sw = sx = sy = 0.0
    for i in range(n_t):
        if wsums[i] > 1e-3 * max(top, 1e-9):
            sw += 1.0
            sx += xs[i]
            sy += ys[i]
    if sw < 3.0:
        return False
    mx, my = sx / sw, sy / sw
    sxx = syy = sxy = 0.0
    for i in range(n_t):
        if wsums[i] > 1e-3 * max(top, 1e-9):
            qx = xs[i] - mx
            qy = ys[i] - my
            sxx += qx * qx
            syy += qy * qy
            sxy += qx * qy
    theta = 0.5 * math.atan2(2.0 * sxy, sxx - syy)  # direction of the edge
    line[0] = -math.sin(theta)
    line[1] = math.cos(theta)
    line[2] = -(line[0] * mx + line[1] * my)
    return True


@njit(cache=True)
def edge_fit(img: np.ndarray, c: np.ndarray, n_cells: int, passes: int, max_profiles: int, step: float,
             window: float, out: np.ndarray) -> None:
    """``passes`` passes of the edge fit (module docstring), each from the previous one's corners: corners ``c``
    (4, 2) -> ``out`` (4, 2) (may be ``c``).

    Parameters
    ----------
    img : ndarray, shape (H, W), uint8, C-contiguous
    c : ndarray, shape (4, 2)
        Corners, clockwise in the image (:mod:`ppoe_core.sensing.tags`); kept if one is not finite.
    n_cells : int
        Cells across the black square (8 for 36h11).
    passes : int
        Passes (:data:`ppoe_core.sensing.tags.EDGE_PASSES`).
    max_profiles : int
        Profiles per edge at most.
    step : float
        Sample step across an edge [px].
    window : float
        Half width of a profile [cells] (at most 2 px).
    """
    lines = np.empty((4, 3))
    # scratch of _edge_line: its profiles (n_t <= max(max_profiles, 6)) and samples (half width <= 2 px)
    work = np.empty((7, max(max_profiles, 6, int(math.floor(4.0 / step + 1e-9)) + 2)))
    res = np.empty((4, 2))
    h, w = img.shape
    flat = img.reshape(h * w)
    out[:, :] = c
    if not np.all(np.isfinite(c)):  # no profile through a NaN or infinite corner: kept
        return
    for _ in range(passes):
        _edge_pass(flat, h, w, out, n_cells, max_profiles, step, window, lines, work, res)
        out[:, :] = res


@njit(cache=True)
def _edge_pass(flat: np.ndarray, h: int, w: int, c: np.ndarray, n_cells: int, max_profiles: int, step: float,
               window: float, lines: np.ndarray, work: np.ndarray, res: np.ndarray) -> None:
    """One pass of :func:`edge_fit` in the (h, w) image ``flat`` (h * w,): corners ``c`` (4, 2) -> ``res`` (4, 2);
    ``lines`` (4, 3), ``work``: scratch."""
    longest = 0.0
    for k in range(4):
        k1 = (k + 1) % 4
        length = math.sqrt((c[k1, 0] - c[k, 0]) ** 2 + (c[k1, 1] - c[k, 1]) ** 2)
        if length < 4.0:
            res[:, :] = c
            return
        longest = max(longest, length)
    n_t = min(max(int(longest), 6), max_profiles)
    cx = 0.25 * (c[0, 0] + c[1, 0] + c[2, 0] + c[3, 0])
    cy = 0.25 * (c[0, 1] + c[1, 1] + c[2, 1] + c[3, 1])
    for k in range(4):
        k1 = (k + 1) % 4
        if not _edge_line(flat, h, w, c[k, 0], c[k, 1], c[k1, 0], c[k1, 1], cx, cy, n_cells, n_t, step, window,
                          lines[k], work):
            res[:, :] = c
            return
    for k in range(4):
        p = lines[(k - 1) % 4]  # edge k-1 (into corner k) and edge k (out of it)
        q = lines[k]
        x0 = p[1] * q[2] - p[2] * q[1]
        x1 = p[2] * q[0] - p[0] * q[2]
        x2 = p[0] * q[1] - p[1] * q[0]
        res[k, 0], res[k, 1] = c[k, 0], c[k, 1]
        if abs(x2) < 1e-12:
            continue
        ux, uy = x0 / x2, x1 / x2
        k1 = (k + 1) % 4
        cell = math.sqrt((c[k1, 0] - c[k, 0]) ** 2 + (c[k1, 1] - c[k, 1]) ** 2) / n_cells
        if math.sqrt((ux - c[k, 0]) ** 2 + (uy - c[k, 1]) ** 2) < cell:
            res[k, 0], res[k, 1] = ux, uy
