"""6D poses: ``/ground_truth/pose`` of the tool frame in the base frame, no nuisance.

Row ``i``: position residual ``p_meas - p_pred`` (base frame axes, [m]) and rotation residual
``Log(R_pred^T R_meas)`` (right tangent at the predicted tool frame, [rad]); the prediction's derivatives are the
point and frame Jacobians of the tool link times the effects' bases (position rotated into the base frame's axes
when the base is not the root; candidates upstream of the base are not proposed).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from ppoe_core import lie
from ppoe_core.analysis.diagnose.block import Linearisation, ResidualBlock, chain_columns, prior_covariance
from ppoe_core.analysis.diagnose.block_tracker import configuration_columns, time_columns
from ppoe_core.analysis.diagnose.candidates import candidate_effects, chain_jacobians, pose_links, predict_nominal
from ppoe_core.analysis.diagnose.stops import Stops
from ppoe_core.errors import MeasurementError
from ppoe_core.model.effects import Effect
from ppoe_core.robot.tree import KinematicTree

__all__ = ["PoseBlock"]


class PoseBlock(ResidualBlock):
    """Ground-truth poses (module docstring); ``stops.kind`` must be ``"pose"``."""

    kind = "pose"
    dim = 6
    nuisance_dim = 0
    unit = "m"

    def __init__(self, tree: KinematicTree, stops: Stops) -> None:
        if stops.kind != "pose" or stops.R_meas is None:
            raise MeasurementError(f"pose block: {stops.group_names}: stops are {stops.kind!r}, not 6D poses")
        self.stops = stops
        no_segment = np.full(len(stops), -1)
        super().__init__(tree, stops.q, stops.context, no_segment, [], stops.group, stops.group_names,
                         stops.reg_mask, stops.score_mask)
        self.dropped = 0

    def _chain(self, effects: Sequence[Effect]) -> tuple:
        s = self.stops
        poses, dq, dxi = self.chain(effects)
        x, R, *_ = predict_nominal(self.tree, s, (), (dq, dxi), poses=poses)
        assert R is not None and s.R_meas is not None
        Jq, Jx, Fq, Fx = chain_jacobians(self.tree, s, poses, dq, dxi)
        base_R = poses[s.base][..., :3, :3] if s.base and s.base != self.tree.root else None
        n = len(s)

        def joined(P: dict, F: dict, tail: tuple[int, ...]) -> dict:
            """Position rows (base axes) over rotation rows, per joint: (n, 6) + tail."""
            out = {}
            for k in [*P, *(j for j in F if j not in P)]:  # dict order, not a set's (string hashes vary per run)
                pos = P.get(k, np.zeros((n, 3) + tail))
                if base_R is not None:
                    pos = np.einsum("nji,nj...->ni...", base_R, pos)
                rot = F[k][:, 3:] if k in F else np.zeros((n, 3) + tail)
                out[k] = np.concatenate([pos, rot], axis=1)
            return out

        return x, R, joined(Jq, Fq, ()), joined(Jx, Fx, (6,))

    def linearise(self, effects: Sequence[Effect], candidates: Sequence[Effect], pert: Mapping[str, np.ndarray],
                  jnoise: Mapping[str, float], chain: bool = False) -> Linearisation:
        s = self.stops
        assert s.R_meas is not None
        x, R, Jq, Jx = self._chain(effects)
        n = len(s)
        r = np.concatenate([s.p_meas - x, lie.so3_log(np.swapaxes(R, -1, -2) @ s.R_meas)], axis=1)
        J = [chain_columns(Jq, Jx, self.basis(c), c.n_params, (n, 6)) for c in candidates]
        S = np.zeros((n, 6, 6))
        S[:, :3, :3] = s.sigma_rows()[:, None, None] ** 2 * np.eye(3)
        S[:, 3:, 3:] = s.sigma_rot ** 2 * np.eye(3)
        Q = prior_covariance(Jq, Jx, pert, jnoise, (n, 6))
        return Linearisation(r, J, np.zeros((n, 6, 0)), S, Q, Jq=Jq)

    def pose_links(self) -> list[str]:
        return pose_links(self.stops)

    def candidates(self) -> list[Effect]:
        return candidate_effects(self.tree, self.stops)

    def chain_links(self) -> list[str]:
        return self.stops.chain_links()

    def error_norm(self, r: np.ndarray) -> np.ndarray:
        return np.linalg.norm(r[..., :3], axis=-1)

    def structure_columns(self, lin: Linearisation) -> dict[str, np.ndarray]:
        return {**configuration_columns(self.tree, self.q, lin.Jq),
                "time": time_columns(self.context.get("time"), self.group, 6)}
