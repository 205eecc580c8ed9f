"""The parsed robot: links, joints (origin, axis as a unit twist, limits, mimic) and the tree queries on them.

``Joint.origin`` is ``T_parent_joint``; a joint's twist is ``[rho; theta]`` (docs/conventions.md)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ppoe_core.errors import UnknownFrameError, UnknownJointError

#: Joint types the model supports.
JOINT_TYPES = ("revolute", "continuous", "prismatic", "fixed")
#: Joint types that move (have a joint value).
MOVABLE_TYPES = ("revolute", "continuous", "prismatic")


# ----------------------------------------------------------------------------
# Data classes
# ----------------------------------------------------------------------------


@dataclass(frozen=True)
class Inertial:
    """``<inertial>`` of a link.

    Attributes
    ----------
    mass : float
        Mass [kg].
    origin : ndarray, shape (4, 4)
        ``T_link_com``: centre-of-mass frame in link coordinates.
    inertia : ndarray, shape (3, 3)
        Inertia tensor about the centre of mass, in the COM frame axes [kg m^2].
    """

    mass: float
    origin: np.ndarray
    inertia: np.ndarray


@dataclass(frozen=True)
class Link:
    """A URDF link (a frame of the tree)."""

    name: str
    inertial: Inertial | None = None
    line: int = 0


@dataclass(frozen=True)
class JointLimit:
    """``<limit>``: position limits [rad or m] (None if absent), effort [N or Nm], velocity."""

    lower: float | None = None
    upper: float | None = None
    effort: float | None = None
    velocity: float | None = None


@dataclass(frozen=True)
class Mimic:
    """``<mimic>``: ``q = multiplier * q_joint + offset``."""

    joint: str
    multiplier: float = 1.0
    offset: float = 0.0


@dataclass(frozen=True)
class Joint:
    """A URDF joint.

    Attributes
    ----------
    name, type, parent, child : str
        ``type`` is one of :data:`JOINT_TYPES`.
    origin : ndarray, shape (4, 4)
        ``T_parent_jointframe`` (paper eq. 16, ``Exp(p_i)``).
    axis : ndarray, shape (3,)
        Unit joint axis in the joint frame (normalised from the URDF value).
    limit : JointLimit or None
    mimic : Mimic or None
        As written in the URDF (the direct master).
    mimic_root : tuple (str, float, float) or None
        ``(independent_master, multiplier, offset)`` after resolving mimic chains, so
        ``q = multiplier * q_master + offset``.
    line : int
        Line of the ``<joint>`` element in the source.
    """

    name: str
    type: str
    parent: str
    child: str
    origin: np.ndarray
    axis: np.ndarray
    limit: JointLimit | None = None
    mimic: Mimic | None = None
    mimic_root: tuple[str, float, float] | None = None
    line: int = 0

    @property
    def movable(self) -> bool:
        """True for revolute, continuous and prismatic joints."""
        return self.type in MOVABLE_TYPES

    @property
    def independent(self) -> bool:
        """True for movable joints that are not mimic joints (they get a joint value)."""
        return self.movable and self.mimic is None

    @property
    def twist(self) -> np.ndarray:
        """The joint's unit twist ``zeta`` (paper eq. 16), shape (6,), ``[rho; theta]``."""
        z = np.zeros(6)
        if self.type == "prismatic":
            z[:3] = self.axis
        elif self.type in ("revolute", "continuous"):
            z[3:] = self.axis
        return z


@dataclass(frozen=True)
class Robot:
    """A kinematic tree parsed from a URDF.

    Attributes
    ----------
    name : str
    links : dict[str, Link]
        In URDF order.
    joints : dict[str, Joint]
        In URDF order.
    root : str
        The single root link.
    source : str
        File name, or ``"<string>"`` for XML text.
    """

    name: str
    links: dict[str, Link]
    joints: dict[str, Joint]
    root: str
    source: str = "<string>"
    _parent_joint: dict[str, str] = field(default_factory=dict, repr=False)

    # -- queries ---------------------------------------------------------------
    @property
    def independent_joints(self) -> list[str]:
        """Movable, non-mimic joints in URDF order (the robot's joint-value vector)."""
        return [j.name for j in self.joints.values() if j.independent]

    @property
    def movable_joints(self) -> list[str]:
        """Revolute, continuous and prismatic joints (mimic included), URDF order."""
        return [j.name for j in self.joints.values() if j.movable]

    def joint(self, name: str) -> Joint:
        """The joint ``name``; raises :class:`UnknownJointError` naming it and the URDF."""
        try:
            return self.joints[name]
        except KeyError:
            raise UnknownJointError(
                f"unknown joint '{name}' (not in URDF {self.source}; joints: "
                f"{', '.join(self.joints) or 'none'})"
            ) from None

    def check_link(self, name: str) -> str:
        """Return ``name`` if it is a link of the URDF, else raise :class:`UnknownFrameError`."""
        if name not in self.links:
            raise UnknownFrameError(
                f"unknown frame/link '{name}' (not in URDF {self.source}; links: "
                f"{', '.join(self.links)})"
            )
        return name

    def parent_joint(self, link: str) -> Joint | None:
        """The joint whose child is ``link`` (None for the root)."""
        self.check_link(link)
        j = self._parent_joint.get(link)
        return None if j is None else self.joints[j]

    def path_from_root(self, link: str) -> list[str]:
        """Joint names from the root down to ``link`` (empty for the root)."""
        self.check_link(link)
        out: list[str] = []
        cur = link
        while cur in self._parent_joint:
            jn = self._parent_joint[cur]
            out.append(jn)
            cur = self.joints[jn].parent
        out.reverse()
        return out

    def chain(self, frm: str, to: str) -> tuple[list[str], list[str]]:
        """Joints between two links through their lowest common ancestor.

        Returns
        -------
        up : list[str]
            Joints walked upwards from ``frm`` to the common ancestor (``frm`` side first);
            these enter the chain inverted.
        down : list[str]
            Joints walked downwards from the common ancestor to ``to``.
        """
        pf = self.path_from_root(frm)
        pt = self.path_from_root(to)
        n = 0
        while n < min(len(pf), len(pt)) and pf[n] == pt[n]:
            n += 1
        return list(reversed(pf[n:])), pt[n:]

    def children(self, link: str) -> list[str]:
        """Joints whose parent is ``link``, URDF order."""
        self.check_link(link)
        return [j.name for j in self.joints.values() if j.parent == link]
