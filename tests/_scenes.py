"""Small in-memory scenes for field tests (no tests here)."""

from __future__ import annotations

import torch

from rainyscape.cameras import Cameras
from rainyscape.scene import SceneData


def forward_facing_scene(points: torch.Tensor | None = None) -> SceneData:
    """Six cameras on a small plane looking down +z (OpenCV), content 2 to 8 units ahead."""
    xs = torch.tensor([-0.2, 0.0, 0.2, -0.2, 0.0, 0.2])
    ys = torch.tensor([-0.1, -0.1, -0.1, 0.1, 0.1, 0.1])
    c2w = torch.eye(4).repeat(6, 1, 1)
    c2w[:, 0, 3], c2w[:, 1, 3] = xs, ys
    cams = Cameras(c2w, torch.full((6,), 30.0), torch.full((6,), 30.0), torch.full((6,), 16.0),
                   torch.full((6,), 12.0), 32, 24)
    return SceneData(name="ff", images=torch.zeros(6, 24, 32, 3, dtype=torch.uint8), cameras=cams,
                     image_names=[f"{i}.png" for i in range(6)], train_indices=[0, 1, 2, 3, 4],
                     eval_indices=[5], near=1.0, far=8.0, scene_box=torch.tensor([[-3.0] * 3, [3.0] * 3]),
                     points=points, forward_facing=True)
