"""Tiny configs and helpers so every model test runs in milliseconds on a CPU."""

import torch

from firp.model import BaselineConfig, EncoderConfig, FIRPConfig, HeadConfig, RSSMConfig

TINY = FIRPConfig(
    encoder=EncoderConfig(backbone="small_cnn", feature_dim=6, image_size=32, small_cnn_channels=(8, 12),
                          projection_hidden=10),
    rssm=RSSMConfig(deter_dim=12, stoch_dim=4, hidden=10),
    head=HeadConfig(q_dim=5, n_prototypes=3, hidden=7),
    baseline=BaselineConfig(hidden=9, max_T=16, gru_hidden=11),
)
DB = TINY.encoder.backbone_dim  # 12


def random_plan(B: int, T: int) -> torch.Tensor:
    """Contract-shaped plans: one-hot categories in runs + joint targets."""
    cats = torch.randint(0, 7, (B, T // 3 + 1)).repeat_interleave(3, dim=1)[:, :T]
    plan = torch.zeros(B, T, 16)
    plan.scatter_(2, cats.unsqueeze(-1), 1.0)
    plan[..., 7:] = torch.randn(B, T, 9) * 0.5
    return plan


def assert_finite_grads(module: torch.nn.Module) -> None:
    missing = [n for n, p in module.named_parameters() if p.requires_grad and p.grad is None]
    assert not missing, f"no gradient reached {missing}"
    bad = [n for n, p in module.named_parameters() if p.grad is not None and not torch.isfinite(p.grad).all()]
    assert not bad, f"non-finite gradients in {bad}"
