"""The plan-conditioned view: the initial image read where the plan's hand meets the scene, trained end to end.

Why: what decides a grasp is often millimetres -- where the object really is against where the planner's
estimate sent the fingers, how close a neighbour stands to them. A whole image read at 84 px through a frozen
backbone sees 5-12 mm per pixel there. This module reads a higher-resolution initial image only where it
matters: for every event of the plan (:mod:`firp.model.plan_events`), the hand's pose by forward kinematics,
projected into the camera with its calibration, gives a crop

* centred on the tool point (between the fingertips),
* aligned with the hand: the crop's axes are the hand's x and y axes (y: the fingers' closing axis) as the
  camera sees them at that point -- an affine map from the plane through the tool point across the hand's
  approach axis to the image, so the fingers' footprint always falls on the same pixels,
* covering ``window`` metres at ``crop`` pixels (a fixed metric size, whatever the camera's distance),

sampled with ``grid_sample`` (differentiable, batched) and read by a small CNN trained with the rest of the
model. Augmentation in training is photometric (brightness, contrast): shifting a crop would blur exactly
the offset between the planned hand and the real object that it is there to read.

Shapes: B plans, E events, H x W view image, C crop pixels, D features.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from firp.model.config import PlanEventsConfig

__all__ = ["PlanView", "crop_grid", "project"]


def project(projection: Tensor, points: Tensor) -> Tensor:
    """Points ``(B, N, 3)`` of the base frame -> pixels ``(B, N, 2)`` through ``projection`` ``(B, 3, 4)``."""
    homogeneous = torch.cat([points, torch.ones_like(points[..., :1])], dim=-1)  # (B, N, 4)
    pix = torch.einsum("bij,bnj->bni", projection, homogeneous)  # (B, N, 3)
    return pix[..., :2] / pix[..., 2:].clamp(min=1e-6)


def crop_grid(projection: Tensor, pos: Tensor, rot: Tensor, window: float, crop: int, height: int, width: int
              ) -> Tensor:
    """``grid_sample`` grids ``(B * E, C, C, 2)`` of the hand-aligned metric crops (see the module docstring) at
    hand positions ``pos`` ``(B, E, 3)`` with rotations ``rot`` ``(B, E, 3, 3)``, in a ``height`` x ``width``
    image. The map from the crop's metric plane to pixels is the projection's Jacobian at the tool point,
    taken along the hand's x and y axes (finite differences of ``window / 2``)."""
    B, E, _ = pos.shape
    step = window / 2
    points = torch.stack([pos, pos + step * rot[..., :, 0], pos + step * rot[..., :, 1]], dim=2)  # (B, E, 3, 3)
    pix = project(projection, points.reshape(B, E * 3, 3)).reshape(B, E, 3, 2)
    centre, along_x, along_y = pix[:, :, 0], pix[:, :, 1] - pix[:, :, 0], pix[:, :, 2] - pix[:, :, 0]
    # crop coordinates in [-1, 1]: -> metric offsets (+-window / 2) -> pixels
    lin = torch.linspace(-1.0, 1.0, crop, device=pos.device, dtype=pos.dtype)
    a, b = torch.meshgrid(lin, lin, indexing="ij")  # a: rows (the hand's x), b: columns (its y, closing axis)
    grid = (centre[:, :, None, None, :] + a[..., None] * along_x[:, :, None, None, :]
            + b[..., None] * along_y[:, :, None, None, :])  # (B, E, C, C, 2) in pixels (u, v)
    # pixels -> grid_sample's [-1, 1] (align_corners=False: pixel centres at k + 0.5)
    scale = grid.new_tensor([2.0 / width, 2.0 / height])
    return (grid * scale - 1.0).reshape(B * E, crop, crop, 2)


class PlanView(nn.Module):
    """View images ``(B, H, W, 3)`` uint8 + hand poses at the events -> per-event features ``(B, E, D)``."""

    def __init__(self, cfg: PlanEventsConfig):
        super().__init__()
        self.cfg = cfg
        channels = (16, 32, 64, 64)
        layers: list[nn.Module] = []
        c_in = 3
        for c in channels:
            layers += [nn.Conv2d(c_in, c, 3, stride=2, padding=1), nn.GroupNorm(math.gcd(8, c), c), nn.ReLU()]
            c_in = c
        self.cnn = nn.Sequential(*layers)
        self.out = nn.Linear(channels[-1], cfg.view_dim)
        self.dim = cfg.view_dim

    def crops(self, view: Tensor, projection: Tensor, pos: Tensor, rot: Tensor) -> Tensor:
        """The hand-aligned crops ``(B, E, 3, C, C)`` in [0, 1] (for the model and for pictures)."""
        B, E = pos.shape[:2]
        H, W = view.shape[1:3]
        C = self.cfg.view_crop
        image = view.permute(0, 3, 1, 2).to(pos.dtype) / 255.0  # (B, 3, H, W)
        grid = crop_grid(projection.to(pos.dtype), pos, rot, self.cfg.view_window, C, H, W)  # (B * E, C, C, 2)
        # one grid per image, the events' crops stacked along its rows: no copy of the image per event
        out = F.grid_sample(image, grid.reshape(B, E * C, C, 2), mode="bilinear", padding_mode="zeros",
                            align_corners=False)  # (B, 3, E * C, C)
        return out.reshape(B, 3, E, C, C).permute(0, 2, 1, 3, 4)

    def forward(self, view: Tensor, projection: Tensor, pos: Tensor, rot: Tensor, augment: bool = False) -> Tensor:
        crops = self.crops(view, projection, pos, rot)  # (B, E, 3, C, C)
        B, E = crops.shape[:2]
        x = crops.reshape(B * E, *crops.shape[2:])
        if augment:  # photometric only: brightness and contrast per crop
            gain = 1.0 + 0.2 * (torch.rand(B * E, 1, 1, 1, device=x.device, dtype=x.dtype) - 0.5)
            shift = 0.1 * (torch.rand(B * E, 1, 1, 1, device=x.device, dtype=x.dtype) - 0.5)
            x = (x - 0.5) * gain + 0.5 + shift
        feats = self.cnn(x - 0.5).mean(dim=(2, 3))  # (B * E, 64)
        return self.out(feats).reshape(B, E, -1)
