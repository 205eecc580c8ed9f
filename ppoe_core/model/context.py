"""The context the model's effects read beside the joint values, built from the joint-state stream.

Effects such as ``backlash`` (the sign of each joint's last motion), ``thermal_growth`` (time since the
start of the recording, or a temperature) and ``time_offset`` (joint velocities) need more than one
configuration: ``ppoe diagnose`` builds their context from a bag's joint states, and the same rules apply
where a diagnosed model is used again: :func:`batch_context` for ``ppoe evaluate`` (a whole bag at once)
and :class:`LiveContext` for the nodes (one joint state at a time).  ``time`` is seconds since the first
joint state; ``motion_sign`` the sign of each joint's last motion out of a dead band (:func:`motion_signs`);
the FK of the joint-state stream itself is no sensor's, so a sensor's ``time_offset`` shifts nothing there
(context ``sensor`` is empty).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from ppoe_core.errors import ModelConfigError

__all__ = ["LiveContext", "REST_SPEED", "at_rest", "batch_context", "follow", "motion_band", "motion_signs",
           "needed_context", "sample_series", "temperature_at"]

#: Half-width of the dead band [rad or m] a joint must leave to count as moving (no noise: a change this small).
MOTION_THRESHOLD = 1e-5
#: the dead band of a noisy encoder, in its noise sigmas (jitter at rest stays inside it)
NOISE_BANDS = 5.0
#: a joint rests when it turns slower than this [rad/s or m/s]: 1 mrad/s moves a 1 m arm's tool by 1 mm/s, below a
#: tracker's noise during a measurement of a few tenths of a second (and an accelerometer then reads gravity alone)
REST_SPEED = 1e-3
#: the spread of a resting joint's samples that encoder noise alone explains, in noise sigmas (the range of up to
#: about 100 Gaussian samples exceeds 6 sigma in under 1 % of windows): only the spread beyond it counts as motion
REST_JITTER_SIGMAS = 6.0
#: half-width [s] of the window of joint samples the rest test looks at around a time
REST_WINDOW = 0.1


def motion_signs(stamps: np.ndarray, positions: np.ndarray, at: np.ndarray,
                 threshold: float | np.ndarray = MOTION_THRESHOLD) -> np.ndarray:
    """Sign of each joint's last motion before each time ``at`` (backlash context).

    A joint has moved when its value leaves a dead band of half-width ``threshold`` around a follower that trails
    it (the follower is pulled along by the motion, so jitter inside the band at rest changes nothing; a reversal
    needs a motion of twice the band): :func:`motion_band` gives a band above the encoder noise of a recording.

    Parameters
    ----------
    stamps : (M,) joint-state times [s], increasing
    positions : (M, J) joint values
    at : (N,) query times [s]
    threshold : float or (J,)
        Half-width of the dead band [rad or m].

    Returns
    -------
    ndarray (N, J) of -1, 0, +1 (0: no motion seen yet).
    """
    band = np.broadcast_to(np.asarray(threshold, dtype=float), positions.shape[1:])
    last = np.zeros_like(positions)
    cur = np.zeros(positions.shape[1])
    ref = positions[0].copy() if len(positions) else cur
    for k in range(1, positions.shape[0]):
        cur, ref = follow(positions[k], ref, cur, band)
        last[k] = cur
    idx = np.clip(np.searchsorted(stamps, at, side="right") - 1, 0, len(stamps) - 1)
    return last[idx]


def follow(q: np.ndarray, ref: np.ndarray, sign: np.ndarray, band: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One step of the dead-band follower of :func:`motion_signs`: the new (sign, follower) at joint values ``q``."""
    up, down = q > ref + band, q < ref - band
    return (np.where(up, 1.0, np.where(down, -1.0, sign)),
            np.where(up, q - band, np.where(down, q + band, ref)))


def motion_band(positions: np.ndarray, threshold: float = MOTION_THRESHOLD) -> np.ndarray:
    """Half-width (J,) of the motion dead band of a recording: :data:`NOISE_BANDS` times the encoder noise of each
    joint (from the low tail of its second differences, where the joint rests: the 10 % quantile of a half-normal
    is 0.126 of its sigma, and a second difference of white noise has sigma sqrt(6) of it), at least
    ``threshold``."""
    if positions.shape[0] < 3:
        return np.full(positions.shape[1:], threshold)
    d2 = np.abs(np.diff(positions, n=2, axis=0))
    noise = np.quantile(d2, 0.1, axis=0) / (0.126 * np.sqrt(6.0))
    return np.maximum(threshold, NOISE_BANDS * noise)


def at_rest(stamps: np.ndarray, positions: np.ndarray, at: np.ndarray, rest_speed: float = REST_SPEED) -> np.ndarray:
    """(N,) bool: at each time ``at`` no joint moves faster than ``rest_speed``.

    The speed is the spread of the joint values (``positions`` (M, J) at ``stamps`` (M,), increasing) within
    :data:`REST_WINDOW` of the time, less what each joint's encoder noise explains (:data:`REST_JITTER_SIGMAS` times
    the noise :func:`motion_band` estimates; noise-free: about 2e-6), over that time; where no joint state is that
    close (a static dataset: a burst, then the measurements) the last three joint states before it.  NaN values
    (a joint a message lacks) are ignored."""
    J = positions.shape[1]
    jitter = REST_JITTER_SIGMAS * np.nan_to_num(motion_band(positions) / NOISE_BANDS, nan=0.0) if J else 0.0
    out = np.zeros(np.shape(at), dtype=bool)
    for k, s in enumerate(np.asarray(at, dtype=float)):
        sel = np.flatnonzero(np.abs(stamps - s) <= REST_WINDOW)
        if sel.size < 2:
            i = int(np.searchsorted(stamps, s, side="right"))
            sel = np.arange(max(i - 3, 0), i)
        if sel.size < 2:
            continue
        span = max(float(stamps[sel[-1]] - stamps[sel[0]]), 1e-3)
        with np.errstate(invalid="ignore"):
            spread = np.nanmax(positions[sel], axis=0) - np.nanmin(positions[sel], axis=0) if J else np.zeros(1)
        moved = np.maximum(np.nan_to_num(spread, nan=0.0) - jitter, 0.0)
        out[k] = bool(np.all(moved / span <= rest_speed))
    return out

def sample_series(t: np.ndarray, v: np.ndarray, at: np.ndarray) -> np.ndarray:
    """Values of a series (times ``t`` (M,) increasing, values ``v`` (M,)) at times ``at``: linear interpolation
    between samples, but the last sample is held across a gap longer than 5 median sample periods (a static stop's
    burst followed by its measurements, docs/conventions.md sec. 3); NaN without samples."""
    if t.size == 0:
        return np.full(at.shape, np.nan)
    if t.size == 1:
        return np.full(at.shape, v[0])
    dt = np.diff(t)
    gap = 5.0 * float(np.median(dt[dt > 0])) if np.any(dt > 0) else 0.0
    i = np.clip(np.searchsorted(t, at, side="right") - 1, 0, t.size - 1)
    j = np.minimum(i + 1, t.size - 1)
    hold = (t[j] - t[i]) > gap
    return np.where(hold | (at <= t[0]), v[i], np.interp(at, t, v))


def temperature_at(temperatures: Mapping[str, Any], stamps: np.ndarray) -> np.ndarray | None:
    """The first (by topic name) ``/temperature[/<name>]`` series with a finite value (``.stamps``,
    ``.temperature``) sampled at ``stamps`` by :func:`sample_series`; None when there is none."""
    for _topic, series in sorted(temperatures.items()):
        good = np.isfinite(series.temperature)
        if good.any():
            order = np.argsort(series.stamps[good], kind="stable")
            return sample_series(series.stamps[good][order], series.temperature[good][order], stamps)
    return None


def needed_context(effects: Sequence[Any]) -> set[str]:
    """Context keys the ``effects`` cannot do without (``time``, ``temperature``, ``motion_sign``,
    ``joint_velocity``); empty for a model without such effects."""
    keys: set[str] = set()
    for eff in effects:
        keys.update(getattr(eff, "context_keys", ()))
    return keys


def batch_context(effects: Sequence[Any], joint_names: Sequence[str], stamps: np.ndarray, Q: np.ndarray,
                  t0: float, temperatures: Mapping[str, Any] | None = None, where: str = "") -> dict[str, Any] | None:
    """Context for ``N`` configurations of a recording (``ppoe evaluate``), by the rules of ``ppoe diagnose``.

    Parameters
    ----------
    effects : the model's effects
    joint_names : (J,) names of the columns of ``Q``
    stamps : (N,) times [s] of the rows of ``Q``, increasing
    Q : (N, J) joint values
    t0 : float
        Time [s] of the recording's first joint state (``time`` = ``stamps - t0``).
    temperatures : topic -> temperature series of the recording (``BagData.temperatures``), optional
        Read by :func:`temperature_at`.
    where : str
        Names the recording in errors.

    Returns
    -------
    dict or None (no effect needs a context).
    """
    need = needed_context(effects)
    if not need:
        return None
    ctx: dict[str, Any] = {"time": stamps - t0, "sensor": ""}
    if "motion_sign" in need:
        s = motion_signs(stamps, Q, stamps)
        ctx["motion_sign"] = {n: s[:, j] for j, n in enumerate(joint_names)}
    if "joint_velocity" in need:
        ctx["joint_velocity"] = {n: (np.gradient(Q[:, j], stamps) if len(stamps) > 1 else np.zeros(len(stamps)))
                                 for j, n in enumerate(joint_names)}
    if "temperature" in need:
        temp = temperature_at(temperatures or {}, stamps)
        if temp is None:
            raise ModelConfigError(f"{where}: the model has thermal_growth against temperature, but there is no "
                                   "/temperature with a finite value")
        ctx["temperature"] = temp
    return ctx


class LiveContext:
    """The context of one joint state at a time (the nodes), by the rules of :func:`batch_context`.

    Parameters
    ----------
    effects : the model's effects
    joint_names : (J,) names of the joint vectors passed to :meth:`update`
    """

    def __init__(self, effects: Sequence[Any], joint_names: Sequence[str]) -> None:
        self.needed = needed_context(effects)
        self.names = list(joint_names)
        self._t0: float | None = None
        self._last: tuple[float, np.ndarray] | None = None
        self._sign = np.zeros(len(self.names))
        self._ref: np.ndarray | None = None
        self.temperature: float | None = None

    def __bool__(self) -> bool:
        return bool(self.needed)

    def update(self, stamp: float, q: np.ndarray) -> dict[str, Any]:
        """Context of joint vector ``q`` (J,) at ``stamp`` [s]; remembers it for the next call.

        Raises :class:`ModelConfigError` while a needed temperature has not been received."""
        q = np.asarray(q, dtype=float)
        vel = np.zeros(len(self.names))
        if self._last is not None:
            t_prev, q_prev = self._last
            d = q - q_prev
            self._sign, self._ref = follow(q, q_prev if self._ref is None else self._ref, self._sign,
                                           np.full(len(self.names), MOTION_THRESHOLD))
            if stamp > t_prev:
                vel = d / (stamp - t_prev)
        if self._t0 is None:
            self._t0 = stamp
        self._last = (stamp, q.copy())
        ctx: dict[str, Any] = {"time": stamp - self._t0, "sensor": ""}
        if "motion_sign" in self.needed:
            ctx["motion_sign"] = dict(zip(self.names, self._sign.copy()))
        if "joint_velocity" in self.needed:
            ctx["joint_velocity"] = dict(zip(self.names, vel))
        if "temperature" in self.needed:
            if self.temperature is None:
                raise ModelConfigError("the model has thermal_growth against temperature: no /temperature "
                                       "received yet")
            ctx["temperature"] = self.temperature
        return ctx

    def update_many(self, stamps: Sequence[float], Q: np.ndarray) -> dict[str, Any]:
        """:meth:`update` of each row of ``Q`` (N, J) in turn, as one batched context (arrays of length N)."""
        ctxs = [self.update(t, q) for t, q in zip(stamps, Q)]
        out: dict[str, Any] = {"time": np.array([c["time"] for c in ctxs]), "sensor": ""}
        for key in ("motion_sign", "joint_velocity"):
            if key in self.needed:
                out[key] = {n: np.array([c[key][n] for c in ctxs]) for n in self.names}
        if "temperature" in self.needed:
            out["temperature"] = np.array([c["temperature"] for c in ctxs])
        return out

    def neutral(self) -> dict[str, Any]:
        """A context in which time- and motion-dependent effects are at their start (the nodes' warm-up)."""
        zeros = dict.fromkeys(self.names, 0.0)
        ctx: dict[str, Any] = {"time": 0.0, "sensor": "", "motion_sign": zeros, "joint_velocity": zeros}
        if "temperature" in self.needed:
            ctx["temperature"] = 0.0
        return ctx
