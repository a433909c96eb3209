"""A learnable sky for the volume stage: an LDR equirect texture looked up by view direction.

The volume pass composites Gaussians over it: ``C = C_gauss + (1 - O) * sky(d)``. (The PBR pass
uses the HDR environment map instead; this sky only has to explain the sky pixels of the frames.)
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from core.conventions import direction_to_uv_torch


class SkyDome(torch.nn.Module):
    """Sky colour in [0, 1] as a sigmoid of an [H, W, 3] texture (world directions, project
    convention). Lookup is bilinear with wrap-around in azimuth."""

    def __init__(self, height: int = 16, width: int = 32, init_rgb=(0.6, 0.7, 0.8)):
        super().__init__()
        init = torch.logit(torch.tensor(init_rgb).clamp(0.02, 0.98))
        self.logits = torch.nn.Parameter(init.expand(height, width, 3).clone())

    @classmethod
    def from_state(cls, state: dict) -> "SkyDome":
        """A dome of the size a saved ``state_dict`` holds, loaded from it."""
        h, w, _ = state["logits"].shape
        sky = cls(int(h), int(w))
        sky.load_state_dict(state)
        return sky

    def forward(self, dirs_world: torch.Tensor) -> torch.Tensor:
        """dirs_world: [..., 3] -> RGB [..., 3]."""
        h, w, _ = self.logits.shape
        u, v = direction_to_uv_torch(dirs_world, h, w)
        tex = torch.sigmoid(self.logits).permute(2, 0, 1)[None]  # [1, 3, H, W]
        tex = torch.cat([tex[..., -1:], tex, tex[..., :1]], -1)  # wrap one column each side
        gx = (u + 1.0) / (w + 2) * 2 - 1  # pixel coords incl. the padded columns -> [-1, 1]
        gy = v / h * 2 - 1
        grid = torch.stack([gx, gy], -1).reshape(1, -1, 1, 2).to(tex.dtype)
        out = F.grid_sample(tex, grid, mode="bilinear", padding_mode="border", align_corners=False)
        return out[0, :, :, 0].T.reshape(*dirs_world.shape[:-1], 3)
