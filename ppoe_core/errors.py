"""The package's own exception types.

Every error that reaches a user names what is wrong and where (file, line,
joint, link, topic).  All derive from :class:`PpoeError` so callers can catch
one type.  No ROS import here: ``ppoe_core`` is pure Python + numpy.
"""

from __future__ import annotations

__all__ = [
    "PpoeError",
    "UrdfError",
    "ModelConfigError",
    "UnknownJointError",
    "UnknownFrameError",
    "JointValueError",
    "CovarianceError",
    "MeasurementError",
    "BagError",
    "ScenarioError",
    "DatasetError",
    "PpoeWarning",
]


class PpoeError(Exception):
    """Base class of every error raised by ppoe_core and ppoe_ros."""


class UrdfError(PpoeError):
    """A URDF that does not parse or is not a valid kinematic tree."""


class ModelConfigError(PpoeError):
    """A model YAML that is malformed: unknown key, wrong shape, bad value."""


class UnknownJointError(PpoeError, KeyError):
    """A joint name that the URDF does not contain."""

    def __str__(self) -> str:  # KeyError would quote the message
        return str(self.args[0]) if self.args else ""


class UnknownFrameError(PpoeError, KeyError):
    """A link / frame name that the URDF does not contain."""

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else ""


class JointValueError(PpoeError, ValueError):
    """A missing, NaN or infinite joint value, or joint values of the wrong shape."""


class CovarianceError(PpoeError, ValueError):
    """A covariance that is not 6x6 (or the stated size), not symmetric or not PSD."""


class MeasurementError(PpoeError, ValueError):
    """A measurement that cannot be used: NaN, wrong shape, point behind the camera."""


class BagError(PpoeError):
    """A bag that does not follow the recorded-bag contract (docs/conventions.md section 3)."""


class ScenarioError(PpoeError):
    """A simulation scenario file that is malformed."""


class DatasetError(PpoeError):
    """A measured dataset file (Hilti, Motoman) that cannot be imported."""


class PpoeWarning(UserWarning):
    """Input that was used only in part (counted in the message); the CLI prints it as one line."""
