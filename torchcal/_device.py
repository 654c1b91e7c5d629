"""Where torchcal computes: the ``--device`` option and :attr:`torchcal.pipeline.Options.device`.

The calibration path is float64 everywhere; CPU and CUDA devices compute it (Apple's MPS has no float64 and is
refused). Data are read and written on the CPU; a run moves the robot model and the measurements to its device
once, and every tensor built along the way takes the device of the tensors it combines with.
"""

from __future__ import annotations

import torch

from torchcal.errors import OptionError

#: what ``--device`` accepts
DEVICE_CHOICES = "cpu, cuda or cuda:N"


def resolve_device(spec: str | torch.device | None) -> torch.device:
    """The torch device named by ``spec`` (``cpu``, ``cuda``, ``cuda:N``; None: cpu), checked to exist here.

    ``cuda`` becomes ``cuda:<current device>`` so that devices compare equal to the tensors' own.

    Raises:
        OptionError: another device type, a malformed name, or a CUDA device that this machine or this torch
            build does not have.
    """
    if spec is None:
        return torch.device("cpu")
    text = str(spec).strip()
    try:
        dev = torch.device(text)
    except (RuntimeError, ValueError):
        raise OptionError(f"device '{text}' is not a device name; expected {DEVICE_CHOICES}") from None
    if dev.type == "cpu":
        return torch.device("cpu")
    if dev.type != "cuda":
        raise OptionError(
            f"device '{text}' is not supported; expected {DEVICE_CHOICES} (the calibration path is float64)"
        )
    if not torch.cuda.is_available():
        build = f"CUDA {torch.version.cuda}" if torch.version.cuda else "without CUDA"
        raise OptionError(
            f"device '{text}': no CUDA device is available (torch {torch.__version__}, built {build}); "
            "use device 'cpu' (--device cpu)"
        )
    count = torch.cuda.device_count()
    index = torch.cuda.current_device() if dev.index is None else dev.index
    if not 0 <= index < count:
        raise OptionError(f"device '{text}': this machine has {count} CUDA device(s), cuda:0 to cuda:{count - 1}")
    return torch.device("cuda", index)
