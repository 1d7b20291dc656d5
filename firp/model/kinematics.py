"""Forward kinematics in torch, for any serial arm described as data (:class:`firp.core.kinematics.KinematicChain`).

The scorer reads where the hand goes from the plan's joint targets alone; the chain comes from the
dataset (and then the bundle), so the same code serves every arm. Batched and differentiable; the
numpy :meth:`KinematicChain.tool_pose` is the reference it is tested against.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor, nn

from firp.core.kinematics import KinematicChain

__all__ = ["ChainFK", "rotation_6d"]


class ChainFK(nn.Module):
    """Joint values ``(..., n)`` -> the tool point's pose in the robot base's frame: position ``(..., 3)`` and
    rotation ``(..., 3, 3)``. The chain's constants are non-persistent buffers: they follow ``.to(device)`` but
    are not weights (the chain travels in the config, not the state dict)."""

    def __init__(self, chain: KinematicChain):
        super().__init__()
        self.n_joints = len(chain)
        self.register_buffer("origins", torch.tensor(np.array([j.origin.matrix() for j in chain.joints]),
                                                     dtype=torch.float32), persistent=False)  # (n, 4, 4)
        self.register_buffer("axes", torch.tensor([j.axis for j in chain.joints], dtype=torch.float32),
                             persistent=False)  # (n, 3)
        self.register_buffer("prismatic", torch.tensor([j.type == "prismatic" for j in chain.joints]),
                             persistent=False)  # (n,)
        self.register_buffer("tool", torch.tensor(chain.tool.matrix(), dtype=torch.float32), persistent=False)

    def forward(self, q: Tensor) -> tuple[Tensor, Tensor]:
        if q.shape[-1] != self.n_joints:
            raise ValueError(f"joint values: the chain has {self.n_joints} joints, got shape {tuple(q.shape)}")
        dtype = q.dtype
        pose = torch.eye(4, dtype=dtype, device=q.device).expand(*q.shape[:-1], 4, 4)
        for i in range(self.n_joints):
            pose = pose @ self.origins[i].to(dtype) @ self._motion(i, q[..., i])
        pose = pose @ self.tool.to(dtype)
        return pose[..., :3, 3], pose[..., :3, :3]

    def _motion(self, i: int, value: Tensor) -> Tensor:
        """Joint ``i``'s own motion ``(..., 4, 4)``: Rodrigues' turn about its axis, or a slide along it."""
        axis = self.axes[i].to(value.dtype)
        eye = torch.eye(4, dtype=value.dtype, device=value.device).expand(*value.shape, 4, 4)
        if bool(self.prismatic[i]):
            shift = torch.zeros(*value.shape, 4, 4, dtype=value.dtype, device=value.device)
            shift[..., :3, 3] = value.unsqueeze(-1) * axis
            return eye + shift
        x, y, z = axis.unbind()
        zero = torch.zeros((), dtype=value.dtype, device=value.device)
        k = torch.stack([torch.stack([zero, -z, y]), torch.stack([z, zero, -x]), torch.stack([-y, x, zero])])
        s, c = torch.sin(value)[..., None, None], torch.cos(value)[..., None, None]
        rot = torch.eye(3, dtype=value.dtype, device=value.device) + s * k + (1 - c) * (k @ k)  # (..., 3, 3)
        out = torch.zeros(*value.shape, 4, 4, dtype=value.dtype, device=value.device)
        out[..., :3, :3] = rot
        out[..., 3, 3] = 1.0
        return out


def rotation_6d(rotation: Tensor) -> Tensor:
    """A rotation ``(..., 3, 3)`` as its first two columns ``(..., 6)``: continuous, unlike angles (Zhou et al.)."""
    return torch.cat([rotation[..., :, 0], rotation[..., :, 1]], dim=-1)
