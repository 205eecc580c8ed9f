"""The edge fit's kernel as it was before its fast path (commit 6d8db13 of ``ppoe_core/sensing/edge_kernel.py``,
verbatim but for the name): the reference that :mod:`ppoe_core.sensing.edge_kernel` (THE implementation) must match
bit for bit (``test/test_edge_kernel.py``); nothing else uses it."""

from __future__ import annotations

import math

import numba
import numpy as np

__all__ = ["edge_pass_reference"]


@numba.njit(cache=False, inline="always")
def _sample(img: np.ndarray, u: float, v: float) -> float:
    """Bilinear grey value at (u, v), the border replicated."""
    h, w = img.shape
    u = min(max(u, 0.0), w - 1.0)
    v = min(max(v, 0.0), h - 1.0)
    u0 = min(int(u), w - 2) if w > 1 else 0
    v0 = min(int(v), h - 2) if h > 1 else 0
    fu = u - u0
    fv = v - v0
    u1 = min(u0 + 1, w - 1)
    v1 = min(v0 + 1, h - 1)
    top = (1.0 - fu) * img[v0, u0] + fu * img[v0, u1]
    bottom = (1.0 - fu) * img[v1, u0] + fu * img[v1, u1]
    return (1.0 - fv) * top + fv * bottom


@numba.njit(cache=False)
def _edge_line(img: np.ndarray, ax: float, ay: float, bx: float, by: float, cx: float, cy: float, n_cells: int,
               n_t: int, step: float, window: float, line: np.ndarray) -> bool:
    """The fitted line ``line = (nx, ny, -n.m)`` of the edge from (ax, ay) to (bx, by) (quad centre (cx, cy));
    False when it has fewer than 3 usable profiles."""
    dx, dy = bx - ax, by - ay
    length = math.sqrt(dx * dx + dy * dy)
    ex, ey = dx / length, dy / length
    nx, ny = ey, -ex
    if nx * (0.5 * (ax + bx) - cx) + ny * (0.5 * (ay + by) - cy) < 0:  # outward normal
        nx, ny = -nx, -ny
    half = min(2.0, window * length / n_cells)
    n_s = int(math.floor(2.0 * half / step + 1e-9)) + 1
    offs = np.empty(n_t)
    wsums = np.empty(n_t)
    prof = np.empty(n_s)
    for i in range(n_t):
        t = 0.15 + 0.7 * i / (n_t - 1)
        px, py = ax + t * dx, ay + t * dy
        for j in range(n_s):
            s = -half + step * j
            prof[j] = _sample(img, px + s * nx, py + s * ny)
        wsum = 0.0
        acc = 0.0
        for j in range(n_s - 1):
            g = prof[j + 1] - prof[j]  # dark (inside) -> light (outside)
            if g > 0.0:
                wsum += g
                acc += g * (-half + step * (j + 0.5))
        wsums[i] = wsum
        offs[i] = acc / wsum if wsum > 0.0 else 0.0
    top = wsums.max()
    sw = sx = sy = 0.0
    for i in range(n_t):
        if wsums[i] > 1e-3 * max(top, 1e-9):
            t = 0.15 + 0.7 * i / (n_t - 1)
            sw += 1.0
            sx += ax + t * dx + offs[i] * nx
            sy += ay + t * dy + offs[i] * ny
    if sw < 3.0:
        return False
    mx, my = sx / sw, sy / sw
    sxx = syy = sxy = 0.0
    for i in range(n_t):
        if wsums[i] > 1e-3 * max(top, 1e-9):
            t = 0.15 + 0.7 * i / (n_t - 1)
            qx = ax + t * dx + offs[i] * nx - mx
            qy = ay + t * dy + offs[i] * ny - my
            sxx += qx * qx
            syy += qy * qy
            sxy += qx * qy
    theta = 0.5 * math.atan2(2.0 * sxy, sxx - syy)  # direction of the edge
    line[0] = -math.sin(theta)
    line[1] = math.cos(theta)
    line[2] = -(line[0] * mx + line[1] * my)
    return True


@numba.njit(cache=False)
def edge_pass_reference(img: np.ndarray, c: np.ndarray, n_cells: int, max_profiles: int, step: float, window: float,
              out: np.ndarray) -> None:
    """One pass of the edge fit (module docstring): corners ``c`` (4, 2) -> ``out`` (4, 2) (may be ``c``).

    Parameters
    ----------
    img : ndarray, shape (H, W), uint8
    c : ndarray, shape (4, 2)
        Corners, clockwise in the image (:mod:`ppoe_core.sensing.tags`).
    n_cells : int
        Cells across the black square (8 for 36h11).
    max_profiles : int
        Profiles per edge at most.
    step : float
        Sample step across an edge [px].
    window : float
        Half width of a profile [cells] (at most 2 px).
    """
    lines = np.empty((4, 3))
    longest = 0.0
    for k in range(4):
        k1 = (k + 1) % 4
        length = math.sqrt((c[k1, 0] - c[k, 0]) ** 2 + (c[k1, 1] - c[k, 1]) ** 2)
        if length < 4.0:
            out[:, :] = c
            return
        longest = max(longest, length)
    n_t = min(max(int(longest), 6), max_profiles)
    cx = 0.25 * (c[0, 0] + c[1, 0] + c[2, 0] + c[3, 0])
    cy = 0.25 * (c[0, 1] + c[1, 1] + c[2, 1] + c[3, 1])
    for k in range(4):
        k1 = (k + 1) % 4
        if not _edge_line(img, c[k, 0], c[k, 1], c[k1, 0], c[k1, 1], cx, cy, n_cells, n_t, step, window, lines[k]):
            out[:, :] = c
            return
    res = np.empty((4, 2))
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
    out[:, :] = res
