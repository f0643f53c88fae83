"""The trace network of paper §6.4 with its lighting-pattern layer.

Input per trace entry (12-D, Eq. 4): the measurement as the camera's *linear pixel value*
(``scanner.exposure(pattern) * B``, RGB, what ``camera.decode`` gives back from an 8-bit photo), the
position in camera space normalised to the valid box ([-1, 1] per box axis), and the geometric
normal n^ and tangent t^ in camera space. Output: the grayscale diffuse lumitexel (384) and the
log(1 + x) of the grayscale specular lumitexel (6144), both in the trace's (n^, t^) frame.

In training, the lighting layer turns physical lumitexels into measurements: pattern = sigmoid(w)
(one weight per emitter and LED colour, i.e. it *is* the pattern), B = (pattern M^T) . m_phys,
scaled by the camera's auto-exposure (capped at ``max_exposure`` x the full-on exposure, so a
dim pattern costs light: ``scanner.auto_exposure``), then multiplicative noise, 8-bit quantisation
(straight-through) and the pipeline's validity test (every channel's code in [32, 224]) decide
which views enter the trace. Max pooling is masked:
padding or invalid entries never win; a trace with no valid entry pools to zeros.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np
import torch
from torch import Tensor, nn

from ..scanner.camera import code_is_valid
from ..scanner.pattern import named_pattern
from ..scanner.scanner import Scanner, auto_exposure

ENCODER_CHUNK = 8192  # entries per encoder pass in forward_ragged: its (chunk, 256) float32 output (8 MB) stays in L3

PRESETS: dict[str, dict] = {
    # widths as published: 6 shared per-entry layers to a 1024-D feature, 5 fc, then 4 / 7 fc
    "paper": dict(
        feature=[64, 64, 64, 128, 512, 1024],
        trunk=[1024] * 5,
        diffuse=[512, 512, 512],
        specular=[1024, 1024, 2048, 2048, 2048, 4096],
    ),
    # sized for fast CPU inference and a small shipped file
    "compact": dict(feature=[32, 64, 128, 256], trunk=[256, 256], diffuse=[256], specular=[512, 1024]),
    # a few MB: the lighting-pattern comparison networks of `ntp bench network` (Fig. 14)
    "small": dict(feature=[32, 64, 128], trunk=[128], diffuse=[128], specular=[256]),
}


@dataclass
class NetworkConfig:
    """Layer widths (from a preset unless given), dropout, output sizes, the pattern setting and noise."""

    preset: str = "compact"
    feature: list[int] = field(default_factory=list)
    trunk: list[int] = field(default_factory=list)
    diffuse: list[int] = field(default_factory=list)
    specular: list[int] = field(default_factory=list)
    dropout: float = 0.3
    diffuse_size: int = 384
    specular_size: int = 6144
    frozen_pattern: str | None = None  # None: learned; or full_on | point | binary | a file path
    noise_sigma: float = 0.05

    def __post_init__(self):
        if self.preset not in PRESETS:
            raise ValueError(f"unknown preset {self.preset!r} (choose from {', '.join(PRESETS)})")
        for k, v in PRESETS[self.preset].items():
            if not getattr(self, k):
                setattr(self, k, list(v))

    def to_dict(self) -> dict:
        """A JSON-able dict (``NetworkConfig(**d)`` rebuilds it)."""
        return asdict(self)


def _mlp(widths: list[int], dropout: float, last_plain: bool) -> nn.Sequential:
    layers: list[nn.Module] = []
    for i, (a, b) in enumerate(zip(widths[:-1], widths[1:])):
        layers.append(nn.Linear(a, b))
        if not (last_plain and i == len(widths) - 2):
            layers.append(nn.LeakyReLU(0.1))
            if dropout > 0:
                layers.append(nn.Dropout(dropout))
    return nn.Sequential(*layers)


class ChunkedLinear(nn.Linear):
    """``nn.Linear`` whose product is summed over fixed input chunks of ``CHUNK`` in a fixed order.
    A wide-in, narrow-out product (the compressed specular head's 1024 -> r) is split over its inputs
    by the BLAS when it has several threads, so its float32 sums — and every map after them — would
    depend on the thread count (seen on AVX-512 machines: 1 vs 2 threads differ by 1e-5); chunks this
    small are not split, and a block of the fit gives the same bits in any process (a Ray worker too)."""

    CHUNK = 256

    def forward(self, x: Tensor) -> Tensor:
        """``x (..., in_features)`` -> ``(..., out_features)``, as ``nn.Linear``."""
        out = self.bias.expand(*x.shape[:-1], -1)
        for a in range(0, self.in_features, self.CHUNK):
            out = out + x[..., a : a + self.CHUNK] @ self.weight[:, a : a + self.CHUNK].T
        return out


class TraceNet(nn.Module):
    """The trace network: lighting-pattern layer and sensor model (training), PointNet encoder, heads."""

    # buffers from the scanner (not trained): colour matrix, exposure calibration, valid box
    color_matrix: Tensor
    gain: Tensor
    max_exposure: Tensor
    pos_matrix: Tensor
    pos_center: Tensor

    def __init__(self, cfg: NetworkConfig, scanner: Scanner):
        super().__init__()
        self.cfg = cfg
        L = scanner.num_emitters
        self.pattern_logits = nn.Parameter(torch.zeros(L, 3), requires_grad=cfg.frozen_pattern is None)
        if cfg.frozen_pattern is not None:
            self.set_pattern(named_pattern(cfg.frozen_pattern, scanner))
        self.register_buffer("color_matrix", torch.as_tensor(scanner.color_matrix, dtype=torch.float32))
        self.register_buffer("gain", torch.tensor(float(scanner.gain)))
        self.register_buffer("max_exposure", torch.tensor(float(scanner.max_exposure)))
        axes = torch.as_tensor(scanner.valid_axes, dtype=torch.float32)
        half = torch.as_tensor(scanner.valid_size / 2, dtype=torch.float32)
        self.register_buffer("pos_matrix", (axes / half[:, None]).T.contiguous())  # x -> box coords
        self.register_buffer("pos_center", torch.as_tensor(scanner.valid_center, dtype=torch.float32))
        self.encoder = _mlp([12] + cfg.feature, 0.0, last_plain=False)
        self.trunk = _mlp([cfg.feature[-1]] + cfg.trunk, cfg.dropout, last_plain=False)
        self.diffuse_head = _mlp([cfg.trunk[-1]] + cfg.diffuse + [cfg.diffuse_size], cfg.dropout, last_plain=True)
        self.specular_head = _mlp([cfg.trunk[-1]] + cfg.specular + [cfg.specular_size], cfg.dropout, last_plain=True)
        for m in self.modules():
            if isinstance(m, nn.Linear):
                nn.init.xavier_uniform_(m.weight)
                nn.init.zeros_(m.bias)

    # ------------------------------------------------------------------ acquisition model
    def pattern(self) -> Tensor:
        """The lighting pattern ``(L, 3)`` in [0, 1]."""
        return torch.sigmoid(self.pattern_logits)

    @torch.no_grad()
    def set_pattern(self, pattern: np.ndarray, margin: float = 1e-6) -> None:
        """Set the lighting layer to ``pattern (L, 3)``, clipped to [margin, 1 - margin]."""
        p = np.clip(np.asarray(pattern, dtype=np.float64), margin, 1 - margin)
        self.pattern_logits.copy_(torch.as_tensor(np.log(p / (1 - p)), dtype=self.pattern_logits.dtype))

    def _p_eff_exposure(self) -> tuple[Tensor, Tensor]:
        p_eff = self.pattern() @ self.color_matrix.T
        return p_eff, auto_exposure(p_eff.mean(), self.gain, self.color_matrix.sum(1).mean(), self.max_exposure)

    def exposure(self) -> float:
        """Linear pixel value per unit of B under this network's pattern (``Scanner.exposure``'s rule
        with the gain and exposure limit it was trained with)."""
        with torch.no_grad():
            return float(self._p_eff_exposure()[1])

    def measure(
        self, m_phys: Tensor, length_mask: Tensor, gen: torch.Generator | None = None, noise: bool = True
    ) -> tuple[Tensor, Tensor]:
        """Physical lumitexels ``(B, V, L, 3)`` -> linear pixel values ``(B, V, 3)`` and the valid
        mask ``(B, V)`` after noise, 8-bit quantisation and the [32, 224] test."""
        p_eff, exposure = self._p_eff_exposure()
        return self._sensor(exposure * torch.einsum("bvlc,lc->bvc", m_phys, p_eff), length_mask, gen, noise)

    def measure_batch(self, batch, gen: torch.Generator | None = None, noise: bool = True) -> tuple[Tensor, Tensor]:
        """As ``measure`` for a ``TraceBatch``, from its factorised terms (no (B, V, L, 3) tensor)."""
        p_eff, exposure = self._p_eff_exposure()
        clean = batch.rho_d_view / torch.pi * (batch.terms_diffuse @ p_eff) + batch.rho_s_view * (
            batch.terms_specular @ p_eff
        )
        return self._sensor(exposure * clean, batch.length_mask, gen, noise)

    def _sensor(self, pixel: Tensor, length_mask: Tensor, gen, noise: bool) -> tuple[Tensor, Tensor]:
        if noise and self.cfg.noise_sigma > 0:
            eps = torch.randn(pixel.shape, generator=gen, device=pixel.device, dtype=pixel.dtype)
            pixel = pixel * (1 + self.cfg.noise_sigma * eps)
        code = 255.0 * pixel
        quant = torch.round(code.clamp(0, 255)) / 255.0
        pixel = pixel + (quant - pixel).detach()  # straight-through: gradients reach the pattern
        valid = length_mask & code_is_valid(code)
        return pixel, valid

    # ------------------------------------------------------------------ trace -> lumitexels
    def entries(self, pixel: Tensor, position: Tensor, normal: Tensor, tangent: Tensor) -> Tensor:
        """12-D trace entries ``(B, V, 12)``."""
        pos = (position - self.pos_center) @ self.pos_matrix
        return torch.cat([pixel, pos, normal, tangent], -1)

    def forward(self, entries: Tensor, mask: Tensor) -> tuple[Tensor, Tensor]:
        """``entries (B, V, 12)``, ``mask (B, V)`` -> diffuse ``(B, 384)``, log1p specular ``(B, 6144)``."""
        feat = self.encoder(entries)
        feat = feat.masked_fill(~mask[..., None], float("-inf")).amax(1)
        feat = torch.where(mask.any(1, keepdim=True), feat, torch.zeros_like(feat))
        h = self.trunk(feat)
        return self.diffuse_head(h), self.specular_head(h)

    def compress_specular(self, basis: Tensor, hidden_mean: Tensor) -> None:
        """Replace the specular head's last layer (the network's largest: 1024 -> 6144) by its
        projection onto ``basis (6144, r)`` (orthonormal columns) about the output the hidden mean
        ``hidden_mean (1024,)`` gives: y = y(h_mean) + B B^T W (h - h_mean), two layers of r rows.
        Exact for outputs in the span of B (``models.specular_basis`` finds one for the trained
        outputs); inference only — the state dict no longer matches ``model.pt``'s."""
        last = self.specular_head[-1]
        assert isinstance(last, nn.Linear)
        w, b = last.weight.detach().double(), last.bias.detach().double()
        basis, hidden_mean = basis.double(), hidden_mean.double()
        down = ChunkedLinear(w.shape[1], basis.shape[1])
        up = nn.Linear(basis.shape[1], w.shape[0])
        with torch.no_grad():
            down.weight.copy_(basis.T @ w)
            down.bias.copy_(-(basis.T @ w) @ hidden_mean)
            up.weight.copy_(basis)
            up.bias.copy_(w @ hidden_mean + b)
        self.specular_head[-1] = nn.Sequential(down, up).to(last.weight.device)

    def forward_ragged(self, entries: Tensor, offsets: Tensor) -> tuple[Tensor, Tensor]:
        """``forward`` on traces in CSR form, no padding: ``entries (E, 12)`` (as ``entries`` makes
        them), ``offsets (B + 1,)`` -> diffuse ``(B, 384)``, log1p specular ``(B, 6144)``. The same
        result (the encoder is per entry, the pooling a max); a trace with no entry pools zeros."""
        lengths = offsets[1:] - offsets[:-1]
        trace = torch.repeat_interleave(torch.arange(len(lengths), device=entries.device), lengths)
        pooled: Tensor | None = None
        # the encoder's (entries, 256) output pooled chunk by chunk: a chunk's stays in the cache
        for a in range(0, max(len(entries), 1), ENCODER_CHUNK):
            feat = self.encoder(entries[a : a + ENCODER_CHUNK])
            if pooled is None:
                pooled = torch.full((len(lengths), feat.shape[1]), -math.inf, dtype=feat.dtype, device=feat.device)
            t = trace[a : a + ENCODER_CHUNK, None].expand_as(feat)
            pooled.scatter_reduce_(0, t, feat, "amax", include_self=True)
        assert pooled is not None
        pooled = pooled.masked_fill((lengths == 0)[:, None], 0.0)  # an empty trace pools zeros
        h = self.trunk(pooled)
        return self.diffuse_head(h), self.specular_head(h)


def lumitexel_loss(
    pred_diffuse: Tensor,
    pred_log_specular: Tensor,
    label_diffuse: Tensor,
    label_specular: Tensor,
    beta: Tensor,
    lambda_d: float = 1.0,
    lambda_s: float = 0.01,
) -> tuple[Tensor, Tensor, Tensor]:
    """Eq. 5, averaged over the batch: (total, diffuse part, specular part)."""
    ld = ((pred_diffuse - label_diffuse) ** 2).sum(-1).mean()
    ls = (beta * ((pred_log_specular - torch.log1p(label_specular)) ** 2).sum(-1)).mean()
    return lambda_d * ld + lambda_s * ls, ld, ls


def num_parameters(model: nn.Module) -> int:
    """Number of parameters of ``model``."""
    return sum(p.numel() for p in model.parameters())
