"""Reduced-precision CPU inference: bf16 through oneDNN where the CPU has it, fp32 elsewhere.

A network keeps its architecture: in bf16 its weights are converted once (:func:`to_bf16`) so
activations stay bf16 and channels-last from input to output (oneDNN's bf16 convolutions),
with the normalisations computing their statistics in float32 on the bf16 activations.
:class:`FastInference` converts the input and, for most models, hands back float32 outputs,
so everything after the network (keypoint selection, pooling, normalisation) works in fp32;
DISK takes its bf16 output and converts only what it reads. Convolution + batch-norm pairs are
folded first where a network has them. Which of these each model gets is :data:`MODEL_POLICIES`, chosen by
measurement (benchmarks/inference_speed.py); the accuracy guard is tests/ml/test_precision.py.

Nothing here reads the environment: the service passes its ``precision`` setting in.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import torch
import torch.nn.functional as F
from torch import nn

Precision = Literal["fp32", "bf16"]
PRECISION_CHOICES = ("auto", "fp32", "bf16")
# CPU flags of native bf16 arithmetic; without them oneDNN emulates bf16 and runs slower.
NATIVE_BF16_FLAGS = ("avx512_bf16", "amx_bf16")


@dataclass(frozen=True)
class ModelPolicy:
    """What a model gets besides the precision.

    Attributes:
        bf16: run in bf16 when the resolved precision is bf16 (False: always fp32).
        channels_last: NHWC input and weights (oneDNN's native layout; measured faster for all
            of our CNNs in bf16, and for the backbones in fp32).
        channels_last_fp32: keep NHWC when the model runs in fp32 (False: NCHW then).
        fold_batchnorm: fold eval-mode BatchNorm into the preceding convolution (torch.fx).
        float_outputs: hand back contiguous float32 outputs (False: the network's own dtype
            and layout, for a caller that converts only what it reads).
    """

    bf16: bool = True
    channels_last: bool = True
    channels_last_fp32: bool = True
    fold_batchnorm: bool = False
    float_outputs: bool = True


# DISK: bf16 where the CPU has bf16 dot products, its dense output read in place. XFeat and
# MobileNetV2 one frame at a time: bf16 measured no faster, and MobileNetV2's bf16 vectors moved
# a harness's R@1 beyond the guard. ResNet-18 is unmeasured (no weights here): fp32. Figures:
# benchmarks/RESULTS.md and benchmarks/archive/RESULTS-history.md.
MODEL_POLICIES: dict[str, ModelPolicy] = {
    # fp32 DISK in NCHW: its fp32 InstanceNorms copy a channels-last input to NCHW and back,
    # slower than NCHW on an AVX2 EPYC (benchmarks/archive/RESULTS-history.md)
    "disk": ModelPolicy(float_outputs=False, channels_last_fp32=False),
    "xfeat": ModelPolicy(bf16=False, channels_last=False),
    "mobilenetv2": ModelPolicy(bf16=False, fold_batchnorm=True),
    "resnet18": ModelPolicy(bf16=False, fold_batchnorm=True),
}


def _onednn_available() -> bool:
    return bool(torch.backends.mkldnn.is_available())  # type: ignore[no-untyped-call]


def _onednn_bf16_supported() -> bool:
    """oneDNN is built in and runs bf16 on this CPU at all (natively or emulated on AVX-512)."""
    if not _onednn_available():
        return False
    try:
        return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):
        return False


@functools.cache
def cpu_has_native_bf16(cpuinfo: Path = Path("/proc/cpuinfo")) -> bool:
    """True when oneDNN is built in and the CPU computes bf16 natively (AVX512-BF16 or AMX)."""
    if not _onednn_bf16_supported():
        return False
    try:
        flags = set(cpuinfo.read_text().split())
    except OSError:
        return False
    return any(flag in flags for flag in NATIVE_BF16_FLAGS)


def resolve_precision(requested: str) -> Precision:
    """``auto`` -> bf16 where the CPU has native bf16, else fp32; ``fp32``/``bf16`` as asked.

    Raises:
        ValueError: an unknown name, or ``bf16`` forced on a CPU without oneDNN bf16 support.
    """
    if requested not in PRECISION_CHOICES:
        raise ValueError(f"unknown precision {requested!r}; choose one of {PRECISION_CHOICES}")
    if requested == "auto":
        return "bf16" if cpu_has_native_bf16() else "fp32"
    if requested == "bf16" and not _onednn_bf16_supported():
        raise ValueError("precision 'bf16' was forced, but this CPU/torch has no oneDNN bf16")
    return "bf16" if requested == "bf16" else "fp32"


def _to_float32(output: Any) -> Any:
    if isinstance(output, torch.Tensor):
        return output.float().contiguous() if output.is_floating_point() else output
    if isinstance(output, tuple):
        return tuple(_to_float32(o) for o in output)
    if isinstance(output, list):
        return [_to_float32(o) for o in output]
    if isinstance(output, dict):
        return {k: _to_float32(v) for k, v in output.items()}
    return output


class Bf16InstanceNorm(nn.Module):
    """InstanceNorm2d (no affine, no running stats) for bf16 activations, layout kept.

    Statistics are computed in float32 and the normalised values rounded to bf16 once:
    ``batch_norm`` in training mode over one frame is its instance norm, and given float32
    weight and bias ATen runs it "mixed type" (float32 statistics and arithmetic on
    bf16 input and output). ``nn.InstanceNorm2d`` in bf16 instead rounds its mean to bf16 (a
    bias of every output, 0.01 of DISK's dense descriptor cosine) and first copies a
    channels-last input to NCHW.
    """

    ones: torch.Tensor
    zeros: torch.Tensor

    def __init__(self, num_features: int, eps: float) -> None:
        super().__init__()
        self.eps = eps
        self.register_buffer("ones", torch.ones(num_features))
        self.register_buffer("zeros", torch.zeros(num_features))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        frames = [
            F.batch_norm(x[i : i + 1], None, None, self.ones, self.zeros, True, 0.0, self.eps)
            for i in range(x.shape[0])
        ]
        return frames[0] if len(frames) == 1 else torch.cat(frames)

    @classmethod
    def replacing(cls, norm: nn.InstanceNorm2d) -> Bf16InstanceNorm:
        """The bf16 equivalent of ``norm``, which must be a plain (non-affine) InstanceNorm2d."""
        if norm.affine or norm.track_running_stats:
            raise ValueError("only InstanceNorm2d without affine parameters or running stats")
        return cls(norm.num_features, norm.eps)


# Normalisations whose parameters and buffers stay float32 in a bf16 network: ATen runs them
# mixed type (float32 statistics on bf16 activations).
MIXED_TYPE_NORMS: tuple[type[nn.Module], ...] = (
    Bf16InstanceNorm,
    nn.BatchNorm2d,
    nn.GroupNorm,
    nn.LayerNorm,
)


def to_bf16(module: nn.Module) -> nn.Module:
    """``module`` (in place) with bf16 weights and float32 normalisation statistics.

    Every InstanceNorm2d becomes a :class:`Bf16InstanceNorm`; the parameters and buffers of
    :data:`MIXED_TYPE_NORMS` stay float32, everything else becomes bf16, so activations stay
    bf16 from input to output with no conversion in between.
    """
    for name, child in module.named_children():
        if isinstance(child, nn.InstanceNorm2d):
            setattr(module, name, Bf16InstanceNorm.replacing(child))
        elif not isinstance(child, MIXED_TYPE_NORMS):
            to_bf16(child)
    for parameter in module.parameters(recurse=False):
        parameter.data = parameter.data.to(torch.bfloat16)
    for name, buffer in module.named_buffers(recurse=False):
        if buffer.is_floating_point():
            setattr(module, name, buffer.to(torch.bfloat16))
    return module


class FastInference(nn.Module):
    """Runs ``inner`` in the given precision and layout.

    Outputs are contiguous float32 when ``float_outputs``; otherwise they come back in the
    network's own dtype and layout (bf16, channels-last), for a caller that converts only the
    part it reads.
    """

    def __init__(
        self,
        inner: nn.Module,
        precision: Precision,
        channels_last: bool,
        float_outputs: bool = True,
    ) -> None:
        super().__init__()
        self.inner = inner
        self.precision: Precision = precision
        self.channels_last = channels_last
        self.float_outputs = float_outputs

    def forward(self, x: torch.Tensor) -> Any:
        dtype = torch.bfloat16 if self.precision == "bf16" else x.dtype
        if self.channels_last and x.dim() == 4:
            x = x.to(dtype=dtype, memory_format=torch.channels_last)
        else:
            x = x.to(dtype)
        out = self.inner(x)
        return _to_float32(out) if self.float_outputs else out

    def __getattr__(self, name: str) -> Any:
        # Sub-modules the caller reaches into (XFeat's fine matcher) stay reachable.
        try:
            return super().__getattr__(name)
        except AttributeError:
            return getattr(super().__getattr__("inner"), name)


def fold_batchnorm(module: nn.Module) -> nn.Module:
    """``module`` with each eval-mode Conv2d -> BatchNorm2d pair folded into one convolution.

    Uses torch.fx; a network fx cannot trace is returned unchanged.
    """
    from torch.fx.experimental.optimization import fuse

    try:
        return fuse(module.eval())
    except Exception:  # noqa: BLE001 - an untraceable network simply keeps its BatchNorms
        return module


def optimise(module: nn.Module, model_name: str, precision: Precision) -> nn.Module:
    """``module`` (in eval mode) prepared for inference by ``model_name``'s policy.

    In fp32 the layout and folding still apply: they change rounding only at the level of
    float32 reassociation.
    """
    policy = MODEL_POLICIES.get(model_name, ModelPolicy(channels_last=False))
    module = module.eval()
    if policy.fold_batchnorm:
        module = fold_batchnorm(module)
    effective: Precision = precision if policy.bf16 else "fp32"
    channels_last = policy.channels_last and (effective == "bf16" or policy.channels_last_fp32)
    if channels_last:
        module = module.to(memory_format=torch.channels_last)  # type: ignore[call-overload]
    if effective == "bf16":
        module = to_bf16(module)
    return FastInference(module, effective, channels_last, policy.float_outputs).eval()
