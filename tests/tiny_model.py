"""The tiny model configuration shared by the loss and training tests."""

from gensplat_transforms.model import GenSplatConfig

TINY = GenSplatConfig(
    dim=32, enc_depth=1, enc_heads=2, enc_pos_grid=2, dec_depth=4, dec_heads=2, head_dim=32, head_depth=1,
    head_heads=2, head_out_dim=32, camera_dim=32, gs_taps=(0, 1, 2, 3), gs_features=8, gs_rgb_features=8,
    sh_degree=0,
)  # fmt: skip
