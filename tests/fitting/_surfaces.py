"""Shared inputs of the ICP-step tests: points on a box's faces with their normals, and a
known rigid motion."""

from __future__ import annotations

import math

import torch

from byoc_cli.geometry.transforms import axis_angle_to_matrix, make_transform


def box_surface(n: int, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """``(n, 3)`` points on the six faces of a 1 x 0.6 x 0.4 box and their normals."""
    half = torch.tensor([0.5, 0.3, 0.2], dtype=torch.float64)
    face = torch.randint(0, 6, (n,), generator=generator)
    axis, sign = face // 2, (face % 2) * 2 - 1
    p = (torch.rand(n, 3, generator=generator, dtype=torch.float64) * 2 - 1) * half
    p[torch.arange(n), axis] = sign.double() * half[axis]
    normal = torch.zeros(n, 3, dtype=torch.float64)
    normal[torch.arange(n), axis] = sign.double()
    return p, normal


def motion(angle_deg: float, t: list[float]) -> torch.Tensor:
    """``(4, 4)``: a turn of ``angle_deg`` about a fixed oblique axis, then ``t``."""
    axis = torch.tensor([0.3, -0.5, 0.8], dtype=torch.float64)
    R = axis_angle_to_matrix(axis / axis.norm() * math.radians(angle_deg))
    return make_transform(R, torch.tensor(t, dtype=torch.float64))
