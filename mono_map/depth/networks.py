"""The depth network: ResNet encoder (blocks written here; torchvision is not usable with this
torch build), spatial pyramid pooling, a U-Net-style decoder, and bilinear up-sampling of the
head's score maps to the input resolution (paper Fig. 2).

``ModelConfig`` names the architecture; ``paper-resnet50`` is the paper's configuration
(ResNet-50, bottleneck blocks [3,4,6,3]) and ``small`` a light default for 2 CPU cores.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import torch
import torch.nn as nn
import torch.nn.functional as F

from mono_map.depth.bins import DepthBins
from mono_map.depth.heads import get_head
from mono_map.errors import MonoMapError
from mono_map.schema import bounded, check_fields


@dataclass(frozen=True)
class ModelConfig:
    """Architecture + head + bins + inference input size (pixels, H×W, multiples of 32)."""

    name: str = "small"
    head: str = field(default="binary", metadata=bounded(nonempty=True))
    block: str = field(default="basic", metadata=bounded(choices=("basic", "bottleneck")))  # ResNet-18/34 or -50
    layers: tuple = field(default=(1, 1, 1, 1), metadata=bounded(item=int, length=4, lo=1, hi=64))  # blocks per stage
    widths: tuple = field(default=(32, 64, 96, 128), metadata=bounded(item=int, length=4, lo=1, hi=8192))  # stage widths (bottleneck output = 4× width)
    stem_width: int = field(default=24, metadata=bounded(lo=1, hi=8192))
    spp_levels: tuple = field(default=(1, 2, 4), metadata=bounded(item=int, nonempty=True, lo=1, hi=64))  # pyramid pooling grid sizes on the stride-32 map
    spp_width: int = field(default=32, metadata=bounded(lo=1, hi=8192))
    decoder_widths: tuple = field(default=(96, 64, 48), metadata=bounded(item=int, length=3, lo=1, hi=8192))  # decoder stages at strides 16, 8, 4
    dropout: float = field(default=0.5, metadata=bounded(lo=0, hi=1, hi_open=True))  # only used by *-dropout heads
    mc_samples: int = field(default=32, metadata=bounded(lo=1, hi=10000))  # Monte-Carlo samples at test time (*-dropout heads)
    num_bins: int = field(default=64, metadata=bounded(lo=2, hi=100000))
    min_depth: float = field(default=1.0, metadata=bounded(lo=0, lo_open=True))  # metres
    max_depth: float = field(default=80.0, metadata=bounded(lo=0, lo_open=True))  # metres, > min_depth
    input_height: int = field(default=192, metadata=bounded(lo=32, hi=8192, multiple_of=32))
    input_width: int = field(default=640, metadata=bounded(lo=32, hi=8192, multiple_of=32))
    beyond: bool = False                     # trained with beyond-range (sky) targets: heads say p(no surface)
    hypotheses: int = field(default=5, metadata=bounded(lo=1, hi=1000))  # M, only used by the mhl head
    wta_epsilon: float = field(default=0.05, metadata=bounded(lo=0, hi=1, hi_open=True))  # relaxed winner-takes-all ε (mhl)

    @property
    def bins(self) -> DepthBins:
        return DepthBins(self.num_bins, self.min_depth, self.max_depth)

    def to_dict(self) -> dict:
        d = asdict(self)
        return {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}

    @classmethod
    def from_dict(cls, d: dict, source: str = "config") -> "ModelConfig":
        d = check_fields(cls, d, source)  # types and ranges, naming source and key
        cfg = cls(**d)
        cfg.validate(source)
        return cfg

    def validate(self, source: str = "config") -> None:
        try:
            get_head(self.head)
        except MonoMapError as exc:
            raise MonoMapError(f"{source}: {exc}") from None
        if self.block not in ("basic", "bottleneck"):
            raise MonoMapError(f"{source}: block must be 'basic' or 'bottleneck', got {self.block!r}")
        if len(self.layers) != 4 or len(self.widths) != 4 or len(self.decoder_widths) != 3:
            raise MonoMapError(f"{source}: need 4 layers, 4 widths and 3 decoder_widths")
        if self.hypotheses < 1 or not 0 <= self.wta_epsilon < 1:
            raise MonoMapError(f"{source}: need hypotheses >= 1 and 0 <= wta_epsilon < 1")
        if self.input_height % 32 or self.input_width % 32:
            raise MonoMapError(f"{source}: input size {self.input_height}x{self.input_width} must be multiples of 32")
        if not self.min_depth < self.max_depth:
            raise MonoMapError(f"{source}: max_depth: must be above min_depth ({self.min_depth:g} m), "
                               f"got {self.max_depth:g}")
        self.bins  # validates the range


NAMED_CONFIGS = {
    "small": ModelConfig(),
    "paper-resnet50": ModelConfig(
        name="paper-resnet50", block="bottleneck", layers=(3, 4, 6, 3), widths=(64, 128, 256, 512),
        stem_width=64, spp_levels=(1, 2, 4, 8), spp_width=128, decoder_widths=(512, 256, 128),
        input_height=352, input_width=1216),
    # model v2's mapping network: ResNet-18 layout (2 basic blocks per stage) at 3/4 width, U-Net decoder
    "resnet18": ModelConfig(
        name="resnet18", block="basic", layers=(2, 2, 2, 2), widths=(48, 96, 192, 384), stem_width=48,
        spp_levels=(1, 2, 4), spp_width=96, decoder_widths=(192, 96, 64), beyond=True),
    # model v2's comparison network for the heads: the ResNet-18 layout at half width
    "resnet18-half": ModelConfig(
        name="resnet18-half", block="basic", layers=(2, 2, 2, 2), widths=(32, 64, 128, 256), stem_width=32,
        spp_levels=(1, 2, 4), spp_width=64, decoder_widths=(128, 64, 48), beyond=True),
}


def named_config(name: str, source: str | None = None, **overrides) -> ModelConfig:
    """Architecture ``name`` with ``overrides``; ``source`` (e.g. "run.toml [model]") names them in errors."""
    where = source or f"model {name}"
    if not isinstance(name, str) or name not in NAMED_CONFIGS:
        raise MonoMapError(f"{where}: arch: unknown architecture {name!r} (choose from {', '.join(NAMED_CONFIGS)})")
    d = NAMED_CONFIGS[name].to_dict()
    d.update(overrides)
    return ModelConfig.from_dict(d, source=where)


def conv_bn_relu(cin: int, cout: int, k: int = 3, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, k, stride, k // 2, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True))


class BasicBlock(nn.Module):
    expansion = 1

    def __init__(self, cin: int, width: int, stride: int = 1):
        super().__init__()
        cout = width * self.expansion
        self.conv1 = nn.Conv2d(cin, width, 3, stride, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(width)
        self.conv2 = nn.Conv2d(width, cout, 3, 1, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(cout)
        self.shortcut = _shortcut(cin, cout, stride)

    def forward(self, x):
        y = F.relu(self.bn1(self.conv1(x)), inplace=True)
        y = self.bn2(self.conv2(y))
        return F.relu(y + self.shortcut(x), inplace=True)


class Bottleneck(nn.Module):
    expansion = 4

    def __init__(self, cin: int, width: int, stride: int = 1):
        super().__init__()
        cout = width * self.expansion
        self.conv1 = nn.Conv2d(cin, width, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(width)
        self.conv2 = nn.Conv2d(width, width, 3, stride, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(width)
        self.conv3 = nn.Conv2d(width, cout, 1, bias=False)
        self.bn3 = nn.BatchNorm2d(cout)
        self.shortcut = _shortcut(cin, cout, stride)

    def forward(self, x):
        y = F.relu(self.bn1(self.conv1(x)), inplace=True)
        y = F.relu(self.bn2(self.conv2(y)), inplace=True)
        y = self.bn3(self.conv3(y))
        return F.relu(y + self.shortcut(x), inplace=True)


def _shortcut(cin: int, cout: int, stride: int) -> nn.Module:
    if stride == 1 and cin == cout:
        return nn.Identity()
    return nn.Sequential(nn.Conv2d(cin, cout, 1, stride, bias=False), nn.BatchNorm2d(cout))


class ResNetEncoder(nn.Module):
    """Stem (7×7/2 conv + 3×3/2 max-pool) and 4 stages; returns features at strides 2, 4, 8, 16, 32."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        block = BasicBlock if cfg.block == "basic" else Bottleneck
        self.stem = conv_bn_relu(3, cfg.stem_width, 7, 2)
        self.pool = nn.MaxPool2d(3, 2, 1)
        cin, stages, self.channels = cfg.stem_width, [], [cfg.stem_width]
        for i, (n, w) in enumerate(zip(cfg.layers, cfg.widths)):
            blocks = []
            for j in range(n):
                blocks.append(block(cin, w, 2 if (j == 0 and i > 0) else 1))
                cin = w * block.expansion
            stages.append(nn.Sequential(*blocks))
            self.channels.append(cin)
        self.stages = nn.ModuleList(stages)

    def forward(self, x):
        feats = [self.stem(x)]
        y = self.pool(feats[0])
        for stage in self.stages:
            y = stage(y)
            feats.append(y)
        return feats


class SpatialPyramidPooling(nn.Module):
    """Average-pool the stride-32 map to g×g grids, 1×1 conv, upsample back, concatenate, fuse."""

    def __init__(self, cin: int, levels: tuple, width: int, cout: int):
        super().__init__()
        self.levels = levels
        # no BatchNorm on pooled maps: a 1×1 grid with batch size 1 has a single value per channel
        self.branches = nn.ModuleList(nn.Sequential(nn.Conv2d(cin, width, 1), nn.ReLU(inplace=True)) for _ in levels)
        self.fuse = conv_bn_relu(cin + width * len(levels), cout, 3)

    def forward(self, x):
        h, w = x.shape[-2:]
        outs = [x]
        for g, branch in zip(self.levels, self.branches):
            y = branch(F.adaptive_avg_pool2d(x, (min(g, h), min(g, w))))
            outs.append(F.interpolate(y, size=(h, w), mode="bilinear", align_corners=False))
        return self.fuse(torch.cat(outs, 1))


class DepthNet(nn.Module):
    """Image (B,3,H,W) in [0,1] -> head output maps (B,C,H,W) at the input resolution."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        cfg.validate()
        self.cfg = cfg
        self.head = get_head(cfg.head)
        bins = cfg.bins
        self.encoder = ResNetEncoder(cfg)
        ch = self.encoder.channels  # strides 2,4,8,16,32
        d16, d8, d4 = cfg.decoder_widths
        self.spp = SpatialPyramidPooling(ch[4], cfg.spp_levels, cfg.spp_width, d16)
        self.up16 = conv_bn_relu(d16 + ch[3], d16)
        self.up8 = conv_bn_relu(d16 + ch[2], d8)
        self.up4 = conv_bn_relu(d8 + ch[1], d4)
        p = cfg.dropout if self.head.dropout else 0.0
        self.tail = nn.Sequential(nn.Dropout2d(p) if p else nn.Identity(), conv_bn_relu(d4, d4),
                                  nn.Dropout2d(p) if p else nn.Identity(),
                                  nn.Conv2d(d4, self.head.out_channels(bins, cfg.beyond, cfg.hypotheses), 3, 1, 1))
        self.register_buffer("mean", torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1), persistent=False)

    @staticmethod
    def _up_cat(x, skip):
        x = F.interpolate(x, size=skip.shape[-2:], mode="bilinear", align_corners=False)
        return torch.cat([x, skip], 1)

    def trunk(self, x):
        """Deterministic part (encoder, SPP, decoder) -> stride-4 features."""
        f = self.encoder((x - self.mean) / self.std)
        y = self.spp(f[4])
        y = self.up16(self._up_cat(y, f[3]))
        y = self.up8(self._up_cat(y, f[2]))
        return self.up4(self._up_cat(y, f[1]))

    def forward(self, x, mc_samples: int = 0, upsample: bool = True):
        """Returns (B,C,H,W); with mc_samples > 0 (dropout heads) (S,B,C,H,W) with dropout active.

        upsample=False returns the score maps at the decoder's stride-4 resolution.
        """
        size = x.shape[-2:]
        feat = self.trunk(x)
        if not upsample:
            size = feat.shape[-2:]
        if mc_samples <= 0:
            return F.interpolate(self.tail(feat), size=size, mode="bilinear", align_corners=False)
        was = self.tail.training
        self.tail.train()
        for m in self.tail.modules():  # keep BatchNorm in eval mode, only dropout stochastic
            if isinstance(m, nn.BatchNorm2d):
                m.eval()
        outs = torch.stack([F.interpolate(self.tail(feat), size=size, mode="bilinear", align_corners=False)
                            for _ in range(mc_samples)])
        self.tail.train(was)
        return outs
