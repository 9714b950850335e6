"""The tiny model configuration shared by the loss and training tests."""

from gensplat_transforms.geometry.model import ModelConfig

TINY = ModelConfig(
    dim=32, enc_depth=1, enc_heads=2, enc_pos_grid=2, dec_depth=4, dec_heads=2, head_dim=32, head_depth=1,
    head_heads=2, head_out_dim=32, camera_dim=32, gs_taps=(0, 1, 2, 3), gs_features=8, gs_rgb_features=8,
    sh_degree=0,
)  # fmt: skip


def tiny_model(seed: int = 0, config: ModelConfig = TINY):
    """A model of ``config`` with every parameter perturbed (LayerScale, registers and the
    cross-view blocks all matter), in eval mode."""
    import torch

    from gensplat_transforms.geometry.model import GenSplatModel

    torch.manual_seed(seed)
    model = GenSplatModel(config).eval()
    with torch.no_grad():
        for name, p in model.named_parameters():
            if name.endswith("gamma"):  # LayerScale starts at 0.01 in the decoder
                p.uniform_(0.5, 1.0)
            else:
                p.add_(torch.randn_like(p) * 0.05)
    return model
