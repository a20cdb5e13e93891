"""Which arithmetic a device computes fast: bfloat16 helps only where the hardware has it."""

from __future__ import annotations

import torch


def bf16_native(device: torch.device) -> bool:
    """Whether `device` computes in bfloat16 natively (CUDA with bf16, or a CPU with AVX-512 BF16/AMX), where
    autocast speeds the networks up; elsewhere bfloat16 is emulated and slower than float32 (a training step of
    the shipped AGM on a 2-core CPU without it: 20 s against 1.9 s)."""
    if device.type == "cuda":
        return torch.cuda.is_available() and torch.cuda.is_bf16_supported()
    try:
        return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):  # a torch without the oneDNN query
        return False
