"""Reduced-precision CPU inference: bf16 through oneDNN where the CPU has it, fp32 elsewhere.

A network is wrapped, never rewritten: :class:`FastInference` runs it on channels-last input
under ``torch.autocast(bfloat16)`` (oneDNN's bf16 convolutions and matrix products) and hands
back float32 outputs, so everything after the network (keypoint selection, pooling,
normalisation) keeps working in fp32. Convolution + batch-norm pairs are folded first where a
network has them. Which of these each model gets is :data:`MODEL_POLICIES`, chosen by
measurement (benchmarks/inference_speed.py); the accuracy guard is tests/ml/test_precision.py.

Nothing here reads the environment: the service passes its ``precision`` setting in.
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import torch
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
            of our CNNs even in fp32).
        fold_batchnorm: fold eval-mode BatchNorm into the preceding convolution (torch.fx).
    """

    bf16: bool = True
    channels_last: bool = True
    fold_batchnorm: bool = False


# DISK: bf16 several times faster. XFeat and MobileNetV2 one frame at a time: bf16 measured no
# faster, and MobileNetV2's bf16 vectors moved a harness's R@1 beyond the guard. ResNet-18 is
# unmeasured (no weights on the development machine): fp32.
MODEL_POLICIES: dict[str, ModelPolicy] = {
    "disk": ModelPolicy(),
    "xfeat": ModelPolicy(bf16=False, channels_last=False),
    "mobilenetv2": ModelPolicy(bf16=False, fold_batchnorm=True),
    "resnet18": ModelPolicy(bf16=False, fold_batchnorm=True),
}


def _onednn_available() -> bool:
    return bool(torch.backends.mkldnn.is_available())  # type: ignore[no-untyped-call]


@functools.cache
def cpu_has_native_bf16(cpuinfo: Path = Path("/proc/cpuinfo")) -> bool:
    """True when oneDNN is built in and the CPU computes bf16 natively (AVX512-BF16 or AMX)."""
    if not _onednn_available():
        return False
    try:
        if not torch.ops.mkldnn._is_mkldnn_bf16_supported():
            return False
    except (AttributeError, RuntimeError):
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
    if requested == "bf16" and not (
        _onednn_available() and torch.ops.mkldnn._is_mkldnn_bf16_supported()
    ):
        raise ValueError("precision 'bf16' was forced, but this CPU/torch has no oneDNN bf16")
    return "bf16" if requested == "bf16" else "fp32"


@contextlib.contextmanager
def autocast(precision: Precision) -> Iterator[None]:
    """bf16 autocast on the CPU when ``precision`` is bf16; nothing otherwise."""
    if precision == "bf16":
        with torch.autocast("cpu", dtype=torch.bfloat16):
            yield
    else:
        yield


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


# Normalisations that compute statistics of the activations lose most accuracy in bf16
# (DISK's InstanceNorms: dense descriptor cosine 0.983 -> 0.994 on day frames); they run in fp32.
FP32_LAYERS: tuple[type[nn.Module], ...] = (nn.InstanceNorm2d, nn.GroupNorm, nn.LayerNorm)


class Float32Island(nn.Module):
    """Runs ``inner`` in float32 inside a bf16 autocast region."""

    def __init__(self, inner: nn.Module) -> None:
        super().__init__()
        self.inner = inner

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        with torch.autocast("cpu", enabled=False):
            out: torch.Tensor = self.inner(x.float())
            return out


def keep_normalisations_in_fp32(module: nn.Module) -> nn.Module:
    """Wrap every :data:`FP32_LAYERS` sub-module of ``module`` (in place) in a Float32Island."""
    for name, child in module.named_children():
        if isinstance(child, FP32_LAYERS):
            setattr(module, name, Float32Island(child))
        else:
            keep_normalisations_in_fp32(child)
    return module


class FastInference(nn.Module):
    """Runs ``inner`` in the given precision and layout; outputs are contiguous float32."""

    def __init__(self, inner: nn.Module, precision: Precision, channels_last: bool) -> None:
        super().__init__()
        self.inner = inner
        self.precision: Precision = precision
        self.channels_last = channels_last

    def forward(self, x: torch.Tensor) -> Any:
        if self.channels_last and x.dim() == 4:
            x = x.contiguous(memory_format=torch.channels_last)
        with autocast(self.precision):
            return _to_float32(self.inner(x))

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
    if policy.channels_last:
        module = module.to(memory_format=torch.channels_last)  # type: ignore[call-overload]
    effective: Precision = precision if policy.bf16 else "fp32"
    if effective == "bf16":
        module = keep_normalisations_in_fp32(module)
    return FastInference(module, effective, policy.channels_last).eval()
