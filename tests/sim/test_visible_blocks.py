"""The line-of-sight test in blocks of poses gives what one block gives (bounded memory, same campaign)."""

import torch

from torchcal.robot import load_robot
from torchcal.sim import poses


def test_visible_in_blocks_equals_one_block(monkeypatch):
    robot = load_robot("ur10")
    g = torch.Generator().manual_seed(5)
    q = poses.sample_joints(robot, 3000, g)
    tracker = torch.tensor([2.0, 0.5, 0.8], dtype=torch.float64)
    lever = torch.tensor([0.0, 0.0, 0.1], dtype=torch.float64)
    monkeypatch.setattr(poses, "VISIBLE_BLOCK", 10**9)
    whole = poses.visible(robot, q, tracker, lever)
    monkeypatch.setattr(poses, "VISIBLE_BLOCK", 700)  # 5 blocks, the last one short
    blocks = poses.visible(robot, q, tracker, lever)
    assert whole.shape == (3000,) and 0 < int(whole.sum()) < 3000  # the rule keeps some poses and drops others
    assert torch.equal(whole, blocks)
    assert poses.visible(robot, q[:0], tracker, lever).shape == (0,)
