"""The drift monitor of the online filter (issue 22, docs/online.md "Drift monitor"): a windowed test of the
innovations that says when the tracked effects no longer explain the data, and what it does then.

**What is tested.**  Under the filter's model (the tracked effects drift as random walks, everything else is the
diagnosed model's noise), the innovations are white and each normalised innovation squared (NIS) is chi-square
with the measurement's dimension ``m_k`` degrees of freedom.  Per source (a topic and frame: one tracker, one camera,
one accelerometer) the monitor keeps the last ``window`` NIS and tests, after every measurement of that source once
the window is full, ::

    E = sum of the window's NIS  >  chi2.isf(false_alarm, sum of the window's m_k)

A measurement that fired the jump rule enters with its NIS under the re-opened covariance (a jump the tracked effects
can explain is not a drift they fail to explain).  **False-alarm rate**: under the model each test exceeds its
threshold with probability ``false_alarm``, so the expected number of alarms is at most ``false_alarm`` times the
number of tests (one per measurement; alarms of overlapping windows are counted once, as one episode, so the
observed count is lower).  An alarm starts an episode; the episode ends when ``E`` falls back to its median under the
model (``chi2.ppf(0.5, ...)``), so a drift that hovers at the threshold is one alarm, not many.

**What happens at an alarm.**  The ``namer`` (the calibration engine's candidate screening on the last
``name_window`` measurements of every source, :mod:`ppoe_core.analysis.drift_naming`) names the effects that
explain the drift, with their held-out gain; with ``add_named`` the trackable ones join the online state
(:meth:`~ppoe_core.estimation.online_effects.OnlineEffects.add_effects`) at the window's estimate and the windows
restart.  The event (:class:`DriftEvent`) goes to ``/diagnostics`` and the drift message live, to the report
offline.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.stats import chi2

from ppoe_core.estimation.online_config import tracked
from ppoe_core.estimation.online_effects import OnlineEffects, OnlineUpdate
from ppoe_core.estimation.online_models import OnlineRow
from ppoe_core.model.effects import Effect

__all__ = ["DriftEvent", "DriftMonitor", "DriftNaming", "MonitorSettings", "NamedEffect"]


@dataclass(frozen=True)
class MonitorSettings:
    """The monitor's parameters (node parameters ``online_monitor_*``).

    Attributes
    ----------
    window : int
        Measurements per source in the test (20).
    false_alarm : float
        Probability that one test alarms while the model holds (1e-4): at most this many alarms per measurement.
    name_window : int
        Measurements (all sources) the namer screens at an alarm (40).
    add_named : bool
        Add the named trackable effects to the online state (False).
    """

    window: int = 20
    false_alarm: float = 1e-4
    name_window: int = 40
    add_named: bool = False


@dataclass
class NamedEffect:
    """An effect that explains the drift: the window's estimate (``effect.params``), its 1-sigma, held-out gain
    (relative decrease of the held-out whitened squared residual), paired t statistic, whether it can be tracked,
    and the candidates the window cannot tell from it (``name@location``: the same columns up to scale, e.g. the
    growth of two segments along one axis)."""

    effect: Effect
    gain: float
    t: float
    sigma: np.ndarray
    trackable: bool
    equivalent: list[str] = field(default_factory=list)

    @property
    def key(self) -> str:
        return f"{self.effect.name}@{self.effect.location}"

    def to_dict(self) -> dict[str, Any]:
        return {"effect": self.key, "parameters": dict(zip(self.effect.param_names, self.effect.params.tolist())),
                "sigma": dict(zip(self.effect.param_names, np.asarray(self.sigma, float).tolist())),
                "heldout_gain": float(self.gain), "t": float(self.t), "trackable": bool(self.trackable),
                "equivalent": list(self.equivalent)}


@dataclass
class DriftNaming:
    """The namer's answer: the named effects (best first), what was screened, and for ``add_named`` the window's
    estimate of the tracked parameters plus the named ones (``theta`` in state order, then each named effect's
    parameters) and its covariance."""

    named: list[NamedEffect]
    rows: int
    candidates: int
    why: str = ""
    theta: np.ndarray | None = None
    cov: np.ndarray | None = None


@dataclass
class DriftEvent:
    """One alarm: when, which source, the test (statistic, threshold, degrees of freedom), the measurement index
    (count of the filter's updates), the naming, the labels added to the state."""

    stamp: float
    source: str
    index: int
    statistic: float
    threshold: float
    dof: int
    naming: DriftNaming | None = None
    added: list[str] = field(default_factory=list)

    def describe(self) -> str:
        """One line for ``/diagnostics`` and the log."""
        head = (f"drift at {self.stamp:.3f} s: the online effects do not explain {self.source} (NIS over the window "
                f"{self.statistic:.1f} > {self.threshold:.1f}, {self.dof} dof)")
        n = self.naming
        if n is None:
            return head
        if not n.named:
            return f"{head}; no candidate effect explains it ({n.why})"
        names = ", ".join(f"{e.key} (held-out gain {100 * e.gain:.0f} %, t {e.t:.1f}"
                          + (f", the same on this data as {' or '.join(e.equivalent)}" if e.equivalent else "")
                          + ("" if e.trackable else ", not trackable online: run ppoe diagnose") + ")"
                          for e in n.named)
        return f"{head}; explained by {names}" + (f"; added to the online state: {self.added}" if self.added else "")

    def to_dict(self) -> dict[str, Any]:
        n = self.naming
        return {"stamp": self.stamp, "source": self.source, "measurement": self.index,
                "statistic": self.statistic, "threshold": self.threshold, "dof": self.dof,
                "named": [e.to_dict() for e in n.named] if n is not None else [],
                "screened": {"rows": n.rows, "candidates": n.candidates, "why": n.why} if n is not None else None,
                "added": list(self.added), "message": self.describe()}


Namer = Callable[[OnlineEffects, Sequence[OnlineRow]], DriftNaming]


@dataclass
class _Source:
    nis: deque = field(default_factory=deque)
    dims: deque = field(default_factory=deque)
    alarm: bool = False


class DriftMonitor:
    """The windowed NIS test per source and the naming at an alarm (module docstring).

    Parameters
    ----------
    settings : MonitorSettings
    namer : callable ``(filter, rows) -> DriftNaming``, optional
        Without one an alarm names nothing.

    Attributes
    ----------
    events : list of DriftEvent
    trace : list of (stamp [s], source, statistic, threshold)
        Every test (for the plot).
    tests : int
        Tests made (the false-alarm bound is ``false_alarm * tests``).
    """

    def __init__(self, settings: MonitorSettings | None = None, namer: Namer | None = None) -> None:
        self.settings = settings or MonitorSettings()
        self.namer = namer
        self.sources: dict[str, _Source] = {}
        self.rows: deque[OnlineRow] = deque(maxlen=max(1, self.settings.name_window))
        self.events: list[DriftEvent] = []
        self.trace: list[tuple[float, str, float, float]] = []
        self.tests = 0
        self._thresholds: dict[int, float] = {}
        self._quiet = 0  # tests without an alarm since the last event

    @property
    def in_alarm(self) -> bool:
        """An episode is on, or the last event is less than a window of quiet tests ago."""
        return bool(self.events) and (any(s.alarm for s in self.sources.values())
                                      or self._quiet < self.settings.window)

    def threshold(self, dof: int) -> float:
        """``chi2.isf(false_alarm, dof)``."""
        if dof not in self._thresholds:
            self._thresholds[dof] = float(chi2.isf(self.settings.false_alarm, dof))
        return self._thresholds[dof]

    def median(self, dof: int) -> float:
        """``chi2.ppf(0.5, dof)``: an alarm episode ends when the window statistic falls below it."""
        return float(chi2.ppf(0.5, dof))

    def reset(self) -> None:
        """Restart every source's window (after the state changed)."""
        self.sources.clear()

    def observe(self, filt: OnlineEffects, row: OnlineRow, update: OnlineUpdate) -> DriftEvent | None:
        """Take one update of ``filt``; the event when it starts an alarm episode."""
        self.rows.append(row)
        s = self.sources.setdefault(row.source, _Source())
        nis = update.nis if np.isnan(update.nis_monitor) else update.nis_monitor
        s.nis.append(float(nis))
        s.dims.append(int(update.dim))
        if len(s.nis) > self.settings.window:
            s.nis.popleft()
            s.dims.popleft()
        if len(s.nis) < self.settings.window:
            return None
        stat, dof = float(sum(s.nis)), int(sum(s.dims))
        thr = self.threshold(dof)
        self.tests += 1
        self.trace.append((row.stamp, row.source, stat, thr))
        self._quiet += 1
        if s.alarm:  # the episode lasts until the statistic is back at its median under the model
            s.alarm = stat > self.median(dof)
            return None
        if stat <= thr:
            return None
        s.alarm = True
        self._quiet = 0
        event = DriftEvent(row.stamp, row.source, filt.counts.updates, stat, thr, dof)
        if self.namer is not None:
            event.naming = self.namer(filt, list(self.rows))
            if self.settings.add_named:
                event.added = self._add(filt, event.naming)
        self.events.append(event)
        return event

    def _add(self, filt: OnlineEffects, naming: DriftNaming) -> list[str]:
        """The named trackable effects into the state at the window's estimate (with the tracked parameters'
        window estimate and the joint covariance); the windows restart."""
        chosen = [e for e in naming.named if e.trackable]
        if not chosen or naming.theta is None or naming.cov is None:
            return []
        n0 = filt.theta.shape[0]
        keep = list(range(n0))
        k = n0
        for e in naming.named:
            if e.trackable:
                keep.extend(range(k, k + e.effect.n_params))
            k += e.effect.n_params
        labels = len(filt.labels)
        filt.add_effects([tracked(e.effect, where=e.key) for e in chosen])
        filt.theta = np.asarray(naming.theta, float)[keep].copy()
        filt.P = np.asarray(naming.cov, float)[np.ix_(keep, keep)].copy()
        self.reset()
        return filt.labels[labels:]
